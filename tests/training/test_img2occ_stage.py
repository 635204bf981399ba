"""The img2occ stage on the simulated tiny fixture: config, training, threshold, eval, export."""

from __future__ import annotations

import json
import math
import subprocess

import numpy as np
import pytest
import torch

from data_converters import ConvertOptions, create_data
from renderworld.constants import OCC3D_CLASSES
from renderworld.data import Img2OccDataset, OccSequenceDataset, load_infos, load_occ3d_labels
from renderworld.training import evaluate, train
from renderworld.training.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from renderworld.training.stages.img2occ import img2occ_config, load_img2occ
from renderworld.training.stages.img2occ.builders import checkpoint_architecture

from .conftest import PYTHON, REPO, compose_cfg, subprocess_env

EXPORT = str(REPO / "tools" / "export_occ.py")
EVAL = str(REPO / "tools" / "eval.py")
INITIAL = 0.99  # readout threshold before training ends: everything reads as free
CANDIDATES = [0.05, 0.1, 0.2, 0.3]


def _train_one_thread(cfg) -> dict:
    """``train(cfg)`` with seed 0 on one intra-op thread (restored after).

    Module fixtures run before the function-scoped single-thread fixture, so this pins it too:
    two OpenMP threads on a loaded 2-core machine make these tiny steps several times slower.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        torch.manual_seed(0)
        return train(cfg)
    finally:
        torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def converted(tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("img2occ_infos")
    create_data(tiny_dataset, "v1.0-mini", out=out, options=ConvertOptions(progress=False))
    return tiny_dataset, out


def stage_overrides(root, infos) -> list[str]:
    """A tiny Img2Occ on the tiny fixture (192x108 images, 48x27 labels), coarse grid."""
    return [
        "stage=img2occ",
        "dataset=sim_mini",
        f"dataset.data_root={root}",
        f"stage.infos_dir={infos}",
        "grid=coarse",
        "trainer=cpu",
        "stage.input_size=[56,96]",
        "stage.render_size=[27,48]",
        "stage.model.encoder_channels=[8,16,16]",
        "stage.model.feature_channels=16",
        "stage.model.head_channels=32",
        "stage.model.head_blocks=1",
        "stage.model.views_per_step=2",
        "stage.model.depth_l1_weight=1.0",
        f"stage.model.occupancy_threshold={INITIAL}",
        f"stage.threshold.candidates={CANDIDATES}",
        "stage.threshold.max_samples=4",
    ]


@pytest.fixture(scope="module")
def trained(converted, tmp_path_factory):
    root, infos = converted
    run = tmp_path_factory.mktemp("img2occ_run")
    cfg = compose_cfg(
        [
            *stage_overrides(root, infos),
            f"run_dir={run}",
            "stage.adjacent_frames=1",
            "trainer.max_steps=4",
            "trainer.batch_size=2",
            "trainer.val_every=2",
            "trainer.ckpt_every=2",
            "trainer.log_every=2",
            "trainer.progress_bar=false",
            "trainer.tensorboard=false",
            "trainer.monitor=val/cam/miou",
            "trainer.monitor_mode=max",
            "optimizer.lr=2e-3",
        ]
    )
    metrics = _train_one_thread(cfg)
    return root, infos, run, metrics


def test_stage_config_composes_and_validates(converted, tmp_path):
    root, infos = converted
    cfg = compose_cfg([*stage_overrides(root, infos), f"run_dir={tmp_path}"])
    mcfg = img2occ_config(cfg)
    assert mcfg.grid.shape == (50, 50, 4) and mcfg.input_size == (56, 96)
    assert mcfg.render_size == (27, 48) and mcfg.adjacent_frames is False
    assert mcfg.depth_l1_weight == 1.0
    mini = compose_cfg(["experiment=img2occ_mini", f"run_dir={tmp_path}"])
    img2occ_config(mini)  # sizes satisfy the model's divisibility rule
    # The 3-D GT upper reference is the same network and budget: only the supervision differs.
    ref = compose_cfg(["experiment=img2occ_mini_3dgt", f"run_dir={tmp_path}"])
    ref_model, mini_model = img2occ_config(ref), img2occ_config(mini)
    assert ref_model.supervision == "3d" and mini_model.supervision == "2d"
    assert mini_model.depth_bins > 0
    assert ref_model == type(ref_model)(**{**vars(mini_model), "supervision": "3d"})
    assert ref.trainer == mini.trainer and ref.optimizer == mini.optimizer
    bad = compose_cfg(
        [*stage_overrides(root, infos), "+stage.model.colour=1", f"run_dir={tmp_path}"]
    )
    with pytest.raises(ValueError, match=r"stage.model.colour: not an Img2OccConfig field"):
        img2occ_config(bad)
    bad = compose_cfg(
        [*stage_overrides(root, infos), "+stage.model.grid=occ3d", f"run_dir={tmp_path}"]
    )
    with pytest.raises(ValueError, match=r"stage.model.grid: set by the run config"):
        img2occ_config(bad)
    bad = compose_cfg(
        [*stage_overrides(root, infos), "stage.input_size=[50,96]", f"run_dir={tmp_path}"]
    )
    with pytest.raises(ValueError, match=r"stage \(Img2OccConfig\): input_size: .*divisible"):
        img2occ_config(bad)
    bad = compose_cfg(
        [*stage_overrides(root, infos), "stage.adjacent_frames=-1", f"run_dir={tmp_path}"]
    )
    with pytest.raises(ValueError, match=r"stage.adjacent_frames: expected an integer k >= 0"):
        img2occ_config(bad)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        (
            "stage.threshold.class_offsets=true",
            r"stage.threshold.class_offsets: expected true \(with per_class true\) or false",
        ),
        ("stage.threshold.criterion=f1", r"stage.threshold.criterion: expected 'miou' or 'iou'"),
        ("stage.threshold.candidates=[0.5,1.5]", r"stage.threshold.candidates: expected values"),
        ("stage.threshold.max_samples=0", r"stage.threshold.max_samples: expected null or an int"),
        (
            "stage.threshold.refit_root=/nonexistent/root",
            r"stage.threshold.refit_root: '/nonexistent/root' is not a folder",
        ),
        (
            "stage.threshold.per_class=yes",
            r"stage.threshold.per_class: expected true \(with criterion miou\) or false",
        ),
    ],
)
def test_bad_threshold_options_fail_before_training(converted, tmp_path, override, message):
    root, infos = converted
    run = tmp_path / "run"
    cfg = compose_cfg([*stage_overrides(root, infos), override, f"run_dir={run}"])
    with pytest.raises(ValueError, match=message):
        train(cfg)
    assert not run.exists()


def test_training_gives_finite_occ3d_metrics(trained):
    _, _, run, metrics = trained
    assert metrics["step"] == 4 and math.isfinite(metrics["train/loss"])
    for prefix in ("cam/", "lidar/", "full/"):
        for name in ("miou", "iou"):
            assert math.isfinite(metrics[f"val/{prefix}{name}"]), (prefix, name)
    per_class = [f"val/cam/iou_{c}" for c in OCC3D_CLASSES[:-1]]
    assert set(per_class) <= set(metrics)
    assert metrics["val/samples"] == 8
    assert (run / "checkpoints" / "last.pt").is_file() and (
        run / "checkpoints" / "best.pt"
    ).is_file()


def test_threshold_chosen_at_train_end_is_in_both_checkpoints(trained):
    _, _, run, metrics = trained
    summary = json.loads((run / "threshold.json").read_text())
    for name in ("last.pt", "best.pt"):
        ckpt = load_checkpoint(run / "checkpoints" / name, "img2occ")
        record = ckpt["threshold"]
        assert record["value"] in CANDIDATES and record["initial"] == pytest.approx(INITIAL)
        assert record["split"] == "train" and record["samples"] == 4
        assert float(ckpt["model"]["occupancy_threshold"]) == pytest.approx(record["value"])
        assert summary[name]["value"] == record["value"] and summary[name]["step"] == ckpt["step"]
        # At 0.99 nothing is occupied; with the chosen threshold the geometry is found.
        assert record["metrics_at_initial"]["val/cam/iou"] == 0.0
        assert ckpt["metrics"]["val/cam/iou"] > 0.0
    assert load_checkpoint(run / "checkpoints" / "best.pt")["step"] == 2  # own weights, own search
    # train() returns (and logs) the final weights scored with their chosen readout.
    last = load_checkpoint(run / "checkpoints" / "last.pt", "img2occ")
    for key in ("val/cam/miou", "val/cam/iou", "val/full/miou"):
        assert metrics[key] == last["metrics"][key], key
    assert metrics["val/cam/iou"] != last["threshold"]["metrics_at_initial"]["val/cam/iou"]


def test_eval_tool_uses_the_stored_threshold_and_writes_picture_and_table(trained, tmp_path):
    root, infos, run, _ = trained
    ckpt = run / "checkpoints" / "last.pt"
    out = tmp_path / "eval"
    proc = subprocess.run(
        [PYTHON, EVAL, *stage_overrides(root, infos), f"ckpt={ckpt}", f"run_dir={out}"],
        cwd=tmp_path, env=subprocess_env(), capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    metrics = json.loads((out / "eval_metrics.json").read_text())
    stored = load_checkpoint(ckpt)
    for key in ("val/cam/miou", "val/cam/iou", "val/lidar/miou", "val/full/iou"):
        assert metrics[key] == pytest.approx(stored["metrics"][key], rel=1e-9), key
    png = (out / "img2occ_views.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    table = (out / "occ3d_metrics.md").read_text()
    assert "camera mask (Occ3D official)" in table and "| 4 | car |" in table
    assert f"opacity > {stored['threshold']['value']:g}" in table
    assert f"| {100 * metrics['val/cam/miou']:.2f} |" in table


def test_export_tool_writes_labels_readable_by_the_sequence_dataset(trained, tmp_path):
    """Exported on CPU, read out again here on CPU: bit-identical labels (same device, same
    float32 kernels; across devices see test_cuda_export_matches_the_cpu_export)."""
    root, infos, run, _ = trained
    ckpt, out = run / "checkpoints" / "last.pt", tmp_path / "pseudo"
    proc = subprocess.run(
        [PYTHON, EXPORT, f"ckpt={ckpt}", f"data_root={root}", f"infos_dir={infos}", f"out={out}",
         "progress=false", "device=cpu"],
        cwd=tmp_path, env=subprocess_env(), capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "exported 16 samples {'train': 8, 'val': 8}" in proc.stdout
    files = sorted((out / "gts").glob("*/*/labels.npz"))
    assert len(files) == 16
    model, _ = load_img2occ(ckpt, "cpu")
    val = Img2OccDataset(load_infos(infos, "val"), root, (56, 96), (27, 48), "coarse")
    item = val[3]
    meta = item["meta"]
    labels = load_occ3d_labels(out / "gts" / meta["scene"] / meta["sample_token"] / "labels.npz")
    batch = {k: v[None] for k, v in item.items() if isinstance(v, torch.Tensor)}
    with torch.no_grad():
        expect = model.readout(model(batch, render=False))[0].numpy()
    np.testing.assert_array_equal(labels.semantics, expect)
    np.testing.assert_array_equal(labels.mask_camera, item["mask_camera"].numpy())
    np.testing.assert_array_equal(labels.mask_lidar, item["mask_lidar"].numpy())
    seq = OccSequenceDataset(
        load_infos(infos, "val"), root, history=2, future=1, grid="coarse", occ_root=out
    )
    window = seq[2]  # frames 2, 3, 4 of the val scene
    np.testing.assert_array_equal(window["occ"][1].numpy(), expect)
    info = json.loads((out / "export_info.json").read_text())
    assert info["files_per_split"] == {"train": 8, "val": 8} and info["grid"]["shape"] == [
        50,
        50,
        4,
    ]


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_export_matches_the_cpu_export(trained, tmp_path):
    """The same checkpoint exported on CUDA and on CPU: labels are decided in float32 with TF32
    off (renderworld.precision.exact_float32), so only voxels whose opacity or class score sits
    within float32 summation-order rounding of a threshold / tie may differ: at most 0.1 %."""
    root, infos, run, _ = trained
    ckpt = run / "checkpoints" / "last.pt"
    labels = {}
    for device in ("cpu", "cuda"):
        out = tmp_path / device
        proc = subprocess.run(
            [PYTHON, EXPORT, f"ckpt={ckpt}", f"data_root={root}", f"infos_dir={infos}",
             f"out={out}", "progress=false", f"device={device}"],
            cwd=tmp_path, env=subprocess_env(), capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        files = sorted((out / "gts").glob("*/*/labels.npz"))
        labels[device] = np.stack(
            [load_occ3d_labels(f).semantics for f in files]
        )  # same relative paths, same order
    differ = float((labels["cpu"] != labels["cuda"]).mean())
    assert differ <= 1e-3, f"{differ:.2e} of voxels differ between the CPU and CUDA exports"


def test_export_refuses_another_stage_checkpoint(converted, tmp_path):
    root, infos = converted
    bad = tmp_path / "tok.pt"
    save_checkpoint(
        {"schema_version": 1, "stage": "tokenizer", "step": 0, "config": "", "model": {}}, bad
    )
    with pytest.raises(
        CheckpointError, match="written by stage 'tokenizer', expected stage 'img2occ'"
    ):
        load_img2occ(bad)
    proc = subprocess.run(
        [PYTHON, EXPORT, f"ckpt={bad}", f"data_root={root}", f"infos_dir={infos}",
         f"out={tmp_path / 'x'}"],
        cwd=tmp_path, env=subprocess_env(), capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode != 0
    assert "expected stage 'img2occ'" in proc.stdout + proc.stderr
    assert not (tmp_path / "x").exists()


def test_3d_supervised_depth_aware_stage_trains(converted, tmp_path):
    """supervision=3d (the upper reference) with depth-aware lifting through the stage."""
    root, infos = converted
    cfg = compose_cfg(
        [
            *stage_overrides(root, infos),
            f"run_dir={tmp_path}",
            "stage.model.supervision=3d",
            "stage.model.depth_bins=8",
            "trainer.max_steps=2",
            "trainer.val_every=2",
            "trainer.ckpt_every=2",
            "trainer.log_every=1",
            "trainer.progress_bar=false",
            "trainer.tensorboard=false",
            "trainer.monitor=val/cam/miou",
            "trainer.monitor_mode=max",
        ]
    )
    metrics = _train_one_thread(cfg)
    assert math.isfinite(metrics["train/loss"]) and math.isfinite(metrics["val/cam/iou"])
    model, _ = load_img2occ(tmp_path / "checkpoints" / "last.pt")
    assert model.cfg.supervision == "3d" and model.cfg.depth_bins == 8


def test_per_class_thresholds_are_saved_and_used_by_eval_and_export(trained, tmp_path):
    # Re-run the end-of-training selection with stage.threshold.per_class=true on a copy of
    # the trained run, then evaluate and export from it as a user would.
    import shutil

    from renderworld.training.stages.img2occ import Img2OccStage

    root, infos, run, _ = trained
    copy = tmp_path / "run"
    shutil.copytree(run / "checkpoints", copy / "checkpoints")
    cfg = compose_cfg(
        [
            *stage_overrides(root, infos),
            f"run_dir={copy}",
            "stage.threshold.per_class=true",
            "stage.threshold.class_offsets=true",
        ]
    )
    stage = Img2OccStage(cfg)
    stage.build_datasets(cfg)
    model, _ = load_img2occ(copy / "checkpoints" / "last.pt")
    stage.on_train_end(model, str(copy))
    ckpt = load_checkpoint(copy / "checkpoints" / "last.pt", "img2occ")
    per_class = ckpt["threshold"]["per_class"]
    assert set(per_class) == set(OCC3D_CLASSES[:-1])
    assert all(t in CANDIDATES for t in per_class.values())
    assert ckpt["model"]["class_thresholds"].tolist() == pytest.approx(list(per_class.values()))
    offsets = ckpt["threshold"]["class_offsets"]
    assert set(offsets) == set(OCC3D_CLASSES[:-1])
    assert ckpt["model"]["class_offsets"].tolist() == pytest.approx(list(offsets.values()))
    out = tmp_path / "eval"
    proc = subprocess.run(
        [PYTHON, EVAL, *stage_overrides(root, infos), f"ckpt={copy / 'checkpoints' / 'last.pt'}",
         f"run_dir={out}"],
        cwd=tmp_path, env=subprocess_env(), capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    table = (out / "occ3d_metrics.md").read_text()
    assert "opacity > the stored per-class threshold of the argmax class (others " in table
    metrics = json.loads((out / "eval_metrics.json").read_text())
    assert metrics["val/cam/miou"] == pytest.approx(ckpt["metrics"]["val/cam/miou"], rel=1e-9)
    pseudo = tmp_path / "pseudo"
    proc = subprocess.run(
        [PYTHON, EXPORT, f"ckpt={copy / 'checkpoints' / 'last.pt'}", f"data_root={root}",
         f"infos_dir={infos}", f"out={pseudo}", "progress=false"],
        cwd=tmp_path, env=subprocess_env(), capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "readout opacity > the per-class thresholds" in proc.stdout
    info = json.loads((pseudo / "export_info.json").read_text())
    assert info["class_thresholds"] == pytest.approx(per_class)
    if any(offsets.values()):
        assert info["class_offsets"] == pytest.approx(offsets)
        assert "plus the stored per-class offsets" in table


def _rechosen_copy(run, tmp_path, overrides: list[str]):
    """A copy of ``run``'s checkpoints whose readout the end-of-training selection re-chose
    under ``overrides``; returns the copy's ``last.pt`` path."""
    import shutil

    from renderworld.training.stages.img2occ import Img2OccStage

    copy = tmp_path / "run"
    shutil.copytree(run / "checkpoints", copy / "checkpoints")
    cfg = compose_cfg([*overrides, f"run_dir={copy}"])
    stage = Img2OccStage(cfg)
    stage.build_datasets(cfg)
    model, _ = load_img2occ(copy / "checkpoints" / "last.pt")
    stage.on_train_end(model, str(copy))
    return copy / "checkpoints" / "last.pt"


def test_eval_refit_root_rechooses_the_readout_for_the_evaluated_weights(trained, tmp_path):
    # The checkpoint holds one global threshold; evaluating with per_class=true and refit_root
    # re-chooses per-class thresholds for its weights, as the end of training would have, and
    # scores with them. Oracle: the end-of-training selection with the same options on a copy.
    root, infos, run, _ = trained
    ckpt = run / "checkpoints" / "last.pt"
    before = ckpt.read_bytes()
    options = [*stage_overrides(root, infos), "stage.threshold.per_class=true"]
    out = tmp_path / "eval"
    proc = subprocess.run(
        [PYTHON, EVAL, *options, f"stage.threshold.refit_root={root}", f"ckpt={ckpt}",
         f"run_dir={out}"],
        cwd=tmp_path, env=subprocess_env(), capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert ckpt.read_bytes() == before  # the checkpoint file is not changed
    record = json.loads((out / "threshold_refit.json").read_text())
    assert record["root"] == str(root) and record["split"] == "train" and record["samples"] == 4
    oracle = load_checkpoint(_rechosen_copy(run, tmp_path, options), "img2occ")
    assert record["per_class"] == pytest.approx(oracle["threshold"]["per_class"])
    assert record["value"] == pytest.approx(oracle["threshold"]["value"])
    metrics = json.loads((out / "eval_metrics.json").read_text())
    for key in ("val/cam/miou", "val/cam/iou", "val/full/miou"):
        assert metrics[key] == pytest.approx(oracle["metrics"][key], rel=1e-9), key
    table = (out / "occ3d_metrics.md").read_text()
    assert f"opacity > the re-chosen (on `{root}`) per-class threshold" in table


def test_eval_refit_root_without_per_class_drops_the_checkpoints_per_class_readout(
    trained, tmp_path
):
    # A copy of the trained run re-chosen with per-class thresholds and offsets, evaluated with
    # refit_root and the default options (one threshold, no offsets): its readout is the one
    # the end of training chose for the same weights with those options, the trained run's.
    root, infos, run, _ = trained
    per_class = [*stage_overrides(root, infos), "stage.threshold.per_class=true"]
    rechosen = _rechosen_copy(run, tmp_path, [*per_class, "stage.threshold.class_offsets=true"])
    assert min(load_checkpoint(rechosen)["threshold"]["per_class"].values()) >= 0
    out = tmp_path / "eval"
    proc = subprocess.run(
        [PYTHON, EVAL, *stage_overrides(root, infos), f"stage.threshold.refit_root={root}",
         f"ckpt={rechosen}", f"run_dir={out}"],
        cwd=tmp_path, env=subprocess_env(), capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    original = load_checkpoint(run / "checkpoints" / "last.pt")
    record = json.loads((out / "threshold_refit.json").read_text())
    assert record["per_class"] is None and record["class_offsets"] is None
    assert record["value"] == pytest.approx(original["threshold"]["value"])
    metrics = json.loads((out / "eval_metrics.json").read_text())
    for key in ("val/cam/miou", "val/cam/iou", "val/full/miou"):
        assert metrics[key] == pytest.approx(original["metrics"][key], rel=1e-9), key
    table = (out / "occ3d_metrics.md").read_text()
    assert f"opacity > {record['value']:g} (re-chosen on `{root}`)" in table


def test_eval_builds_the_checkpoints_architecture_when_the_config_differs(trained, tmp_path):
    """A checkpoint evaluated under another ``stage.model`` (here wider heads) evaluates as
    itself, with a warning naming what differs; one of another grid is an error naming ckpt."""
    root, infos, run, _ = trained
    over = [*stage_overrides(root, infos), f"ckpt={run / 'checkpoints' / 'last.pt'}"]
    same = evaluate(compose_cfg([*over, f"run_dir={tmp_path / 'same'}"], "eval"))
    with pytest.warns(UserWarning, match=r"trained with stage.model head_channels=32"):
        other = evaluate(
            compose_cfg(
                [*over, "stage.model.head_channels=64", f"run_dir={tmp_path / 'o'}"], "eval"
            )
        )
    for key in ("val/cam/miou", "val/cam/iou", "val/full/iou"):
        assert other[key] == same[key], key
    with pytest.raises(ValueError, match=r"ckpt: .* was trained on the 'coarse' grid"):
        half = ["grid=half" if o == "grid=coarse" else o for o in over]
        evaluate(compose_cfg([*half, f"run_dir={tmp_path / 'grid'}"], "eval"))


def test_eval_keeps_the_runs_readout_options_with_the_checkpoints_architecture(trained):
    """Only the weights' shape comes from the checkpoint: a readout option the run sets (here
    the mirrored readout) is what the evaluation runs."""
    root, infos, run, _ = trained
    cfg = compose_cfg([*stage_overrides(root, infos), "stage.model.head_channels=64",
                       "stage.model.mirror_readout=true"])  # fmt: skip
    with pytest.warns(UserWarning, match=r"head_channels=32; evaluating"):
        got = checkpoint_architecture(img2occ_config(cfg), run / "checkpoints" / "last.pt")
    assert got.head_channels == 32 and got.mirror_readout is True
