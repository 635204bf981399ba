"""Checkpoint files: atomic writes, weights-only strict loads, clear failures, safe resumes."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
import torch
from torch import nn

from renderworld.training import train
from renderworld.training.checkpoint import (
    CHECKPOINT_SCHEMA_VERSION,
    CheckpointError,
    load_checkpoint,
    load_model_weights,
    save_checkpoint,
)

from .conftest import fit_cfg, params_of


def _ckpt(model: nn.Module, stage: str = "regression", **extra) -> dict:
    return {
        "schema_version": CHECKPOINT_SCHEMA_VERSION,
        "stage": stage,
        "step": 3,
        "config": "seed: 0\n",
        "model": model.state_dict(),
        **extra,
    }


def _snapshot(directory: Path) -> dict[str, str]:
    """Every file under ``directory`` with a hash of its bytes."""
    return {
        str(p.relative_to(directory)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


def test_round_trip_and_weights_only(tmp_path):
    model = nn.Linear(4, 2)
    path = save_checkpoint(_ckpt(model), tmp_path / "sub" / "a.pt")
    other = nn.Linear(4, 2)
    ckpt = load_model_weights(other, path, expected_stage="regression")
    assert ckpt["step"] == 3
    for a, b in zip(model.parameters(), other.parameters()):
        assert torch.equal(a, b)
    assert [p.name for p in path.parent.iterdir()] == ["a.pt"]  # no temp files left


def test_interrupted_write_keeps_the_old_file(tmp_path, monkeypatch):
    model = nn.Linear(4, 2)
    path = save_checkpoint(_ckpt(model), tmp_path / "last.pt")
    before = path.read_bytes()

    def torn_save(obj, f, *args, **kwargs):
        f.write(b"PK\x03\x04 half a zip")
        raise KeyboardInterrupt  # a kill arriving mid-write

    monkeypatch.setattr(torch, "save", torn_save)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(_ckpt(model, step=4), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"]


def test_truncated_file_fails_clearly(tmp_path):
    path = save_checkpoint(_ckpt(nn.Linear(4, 2)), tmp_path / "last.pt")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match=r"last\.pt' cannot be read: .*truncated or corrupt"):
        load_checkpoint(path)


def test_other_stage_fails_clearly(tmp_path):
    path = save_checkpoint(_ckpt(nn.Linear(4, 2), stage="tokenizer"), tmp_path / "t.pt")
    with pytest.raises(CheckpointError, match="written by stage 'tokenizer', expected stage 'img2"):
        load_checkpoint(path, expected_stage="img2occ")


def test_other_schema_version_fails_clearly(tmp_path):
    state = _ckpt(nn.Linear(4, 2))
    state["schema_version"] = CHECKPOINT_SCHEMA_VERSION + 1
    path = save_checkpoint(state, tmp_path / "v.pt")
    with pytest.raises(
        CheckpointError, match=r"schema version 2, this RenderWorld reads version 1"
    ):
        load_checkpoint(path)


def test_non_checkpoint_files_fail_clearly(tmp_path):
    bare = tmp_path / "bare.pt"
    torch.save(nn.Linear(4, 2).state_dict(), bare)  # a bare state_dict: no schema
    with pytest.raises(CheckpointError, match="schema version None"):
        load_checkpoint(bare)
    pickled = tmp_path / "pickled.pt"
    torch.save({"schema_version": 1, "obj": nn.Linear(2, 2)}, pickled)  # needs code to load
    with pytest.raises(CheckpointError, match="holds objects other than tensors"):
        load_checkpoint(pickled)
    with pytest.raises(CheckpointError, match="no such file"):
        load_checkpoint(tmp_path / "missing.pt")
    partial = save_checkpoint({"schema_version": 1, "stage": "x"}, tmp_path / "partial.pt")
    with pytest.raises(CheckpointError, match=r"missing entries \['step', 'config', 'model'\]"):
        load_checkpoint(partial)


def test_key_mismatch_lists_missing_and_unexpected(tmp_path):
    src = nn.Sequential(nn.Linear(4, 3), nn.ReLU(), nn.Linear(3, 2))
    path = save_checkpoint(_ckpt(src), tmp_path / "m.pt")
    dst = nn.Sequential(nn.Linear(4, 3), nn.ReLU(), nn.Linear(3, 5), nn.Linear(5, 1))
    with pytest.raises(CheckpointError) as info:
        load_model_weights(dst, path)
    msg = str(info.value)
    assert "missing keys (2): 3.bias, 3.weight" in msg
    assert "shape mismatches (2): 2.bias: model (5,) vs checkpoint (2,)" in msg
    small = nn.Sequential(nn.Linear(4, 3))
    with pytest.raises(CheckpointError, match=r"unexpected keys \(2\): 2.bias, 2.weight"):
        load_model_weights(small, path)
    with pytest.raises(TypeError, match="model: expected a torch.nn.Module"):
        load_model_weights("not a model", path)  # type: ignore[arg-type]


def test_save_validates_its_input(tmp_path):
    with pytest.raises(ValueError, match="a checkpoint needs 'schema_version'"):
        save_checkpoint({"stage": "x"}, tmp_path / "x.pt")
    with pytest.raises(TypeError, match="state: expected a mapping"):
        save_checkpoint([1, 2], tmp_path / "x.pt")  # type: ignore[arg-type]


# ------------------------------------------------------------------ failed resumes
@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("run")
    train(fit_cfg(run, "trainer.max_steps=20", "trainer.val_every=10"))
    return run


def _corrupt(kind: str, path: Path) -> None:
    if kind == "truncated":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 3])
        return
    ckpt = torch.load(path, weights_only=True)
    if kind == "other_stage":
        ckpt["stage"] = "world_model"
    elif kind == "schema":
        ckpt["schema_version"] = 0
    elif kind == "no_rng":
        del ckpt["rng"]
    torch.save(ckpt, path)


@pytest.mark.parametrize(
    ("kind", "match"),
    [
        ("truncated", "truncated or corrupt"),
        ("other_stage", "written by stage 'world_model', expected stage 'regression'"),
        ("schema", "schema version 0"),
        ("no_rng", r"missing entries \['rng'\]"),
    ],
)
def test_failed_resume_overwrites_nothing(trained_run, tmp_path, kind, match):
    run = tmp_path / "copy"
    run.mkdir()
    for p in trained_run.rglob("*"):
        if p.is_file():
            dst = run / p.relative_to(trained_run)
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.write_bytes(p.read_bytes())
    _corrupt(kind, run / "checkpoints" / "last.pt")
    before = _snapshot(run)
    with pytest.raises(CheckpointError, match=match):
        train(fit_cfg(run, "resume=true", "trainer.max_steps=40"))
    assert _snapshot(run) == before


def test_resume_into_a_different_model_overwrites_nothing(trained_run):
    before = _snapshot(trained_run)
    with pytest.raises(CheckpointError, match=r"shape mismatches \(2\): 1.bias: model \(4,\)"):
        train(fit_cfg(trained_run, "resume=true", "stage.out_features=4"))
    assert _snapshot(trained_run) == before


def test_fresh_run_refuses_a_run_dir_with_a_checkpoint(trained_run):
    before = _snapshot(trained_run)
    with pytest.raises(ValueError, match="already holds last.pt: pass resume=true"):
        train(fit_cfg(trained_run))
    assert _snapshot(trained_run) == before


def test_resume_without_checkpoint_fails_clearly(tmp_path):
    with pytest.raises(CheckpointError, match=r"checkpoints/last\.pt': no such file"):
        train(fit_cfg(tmp_path, "resume=true"))
    assert not any(tmp_path.iterdir())


# ------------------------------------------------------------------ init_from
def test_init_from_starts_from_the_weights_with_a_fresh_schedule(trained_run, tmp_path):
    src = trained_run / "checkpoints" / "last.pt"
    want = params_of(src)
    runs = {}
    for name, extra in (("init", (f"init_from={src}",)), ("fresh", ())):
        runs[name] = tmp_path / name
        train(fit_cfg(runs[name], *extra, "optimizer.lr=1e-12", "trainer.max_steps=2"))
    init = torch.load(runs["init"] / "checkpoints" / "last.pt", weights_only=True)
    assert init["step"] == 2  # a new run: step, optimizer and schedule start at 0
    for key, value in want.items():
        assert torch.allclose(init["model"][key], value, atol=1e-9), key
    fresh = params_of(runs["fresh"] / "checkpoints" / "last.pt")
    assert not all(torch.allclose(fresh[k], v) for k, v in want.items())


def test_init_from_another_stage_fails_before_writing(trained_run, tmp_path):
    src = tmp_path / "other.pt"
    ckpt = torch.load(trained_run / "checkpoints" / "last.pt", weights_only=True)
    ckpt["stage"] = "world_model"
    torch.save(ckpt, src)
    run = tmp_path / "run"
    with pytest.raises(CheckpointError, match="init_from: checkpoint .* written by stage"):
        train(fit_cfg(run, f"init_from={src}"))
    assert not run.exists()


def test_init_from_another_architecture_fails_before_writing(trained_run, tmp_path):
    run = tmp_path / "run"
    src = trained_run / "checkpoints" / "last.pt"
    with pytest.raises(CheckpointError, match=r"init_from .*shape mismatches"):
        train(fit_cfg(run, f"init_from={src}", "stage.out_features=4"))
    assert not run.exists()
