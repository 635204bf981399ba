"""The paper-scale experiments end to end on the full-grid simulated preset, on CPU (slow).

``configs/experiment/paper_*.yaml`` unchanged but for the trainer (CPU, 32-bit, two steps,
batch 1, no workers) and the readout search's sample count: Img2Occ at the Occ3D grid (640k
Gaussians, 256x704 inputs, 225x400 renders) trains, evaluates and exports pseudo labels; the
paper tokenizer (latent 50x50x128, 512 codes) and world model train on the GT, the Camera
setting's world model on the pseudo labels, and the world model plans through a planner bundle.
``benchmarks/bench_scale.py`` times the same steps. 39 minutes on the shared 2-core CPU (load ~8).
"""

from __future__ import annotations

import json
import math
import subprocess

import numpy as np
import pytest
import torch

from data_converters import ConvertOptions, create_data
from renderworld.constants import FREE_ID
from renderworld.data import load_occ3d_labels
from renderworld.training import evaluate, train
from renderworld.training.checkpoint import load_checkpoint

from .conftest import PYTHON, REPO, compose_cfg, subprocess_env

pytestmark = pytest.mark.slow

VERSION = "v1.0-trainval"  # the preset's layout: dataset=nuscenes reads it as is
CPU = [
    "trainer.device=cpu",
    "trainer.precision=32",
    "trainer.max_epochs=null",
    "trainer.max_steps=2",
    "trainer.batch_size=1",
    "trainer.num_workers=0",
    "trainer.pin_memory=false",
    "trainer.val_every=0",
    "trainer.ckpt_every=0",
    "trainer.progress_bar=false",
    "trainer.tensorboard=false",
    "trainer.num_threads=2",
]


@pytest.fixture(scope="module")
def full(full_dataset, tmp_path_factory):
    """The full-grid preset converted with 225x400 labels (as real 1600x900 images get)."""
    infos = tmp_path_factory.mktemp("full_infos")
    opts = ConvertOptions(progress=False, label_size=(225, 400))
    create_data(full_dataset, VERSION, out=infos, options=opts)
    return full_dataset, infos


def _data(full) -> list[str]:
    root, infos = full
    return [f"dataset.data_root={root}", f"stage.infos_dir={infos}"]


def _train(experiment: str, full, run, *extra: str) -> dict:
    torch.manual_seed(0)
    cfg = compose_cfg([f"experiment={experiment}", *_data(full), *CPU, f"run_dir={run}", *extra])
    assert cfg.dataset.name == "nuscenes" and cfg.grid.name == "occ3d"
    return train(cfg)


@pytest.fixture(scope="module")
def img2occ_run(full, tmp_path_factory):
    run = tmp_path_factory.mktemp("paper_img2occ")
    metrics = _train("paper_img2occ", full, run, "stage.threshold.max_samples=2")
    return run, metrics


@pytest.fixture(scope="module")
def pseudo_labels(full, img2occ_run, tmp_path_factory):
    root, infos = full
    run, _ = img2occ_run
    out = tmp_path_factory.mktemp("pseudo")
    proc = subprocess.run(
        [PYTHON, str(REPO / "tools" / "export_occ.py"), f"ckpt={run / 'checkpoints' / 'last.pt'}",
         f"data_root={root}", f"infos_dir={infos}", f"version={VERSION}", f"out={out}",
         "device=cpu", "progress=false"],
        cwd=tmp_path_factory.getbasetemp(), env=subprocess_env(), capture_output=True,
        text=True, timeout=3600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return out


@pytest.fixture(scope="module")
def tokenizer_ckpt(full, tmp_path_factory):
    run = tmp_path_factory.mktemp("paper_tokenizer")
    metrics = _train("paper_tokenizer", full, run)
    assert math.isfinite(metrics["train/loss"])
    return run / "checkpoints" / "last.pt"


def test_paper_img2occ_trains_evaluates_and_exports(full, img2occ_run, pseudo_labels, tmp_path):
    run, metrics = img2occ_run
    assert metrics["step"] == 2 and math.isfinite(metrics["train/loss"])
    assert metrics["val/samples"] == 12
    cfg = compose_cfg(
        ["experiment=paper_img2occ", "stage=img2occ", *_data(full), *CPU,
         f"ckpt={run / 'checkpoints' / 'last.pt'}", f"run_dir={tmp_path}"],
        config_name="eval",
    )  # fmt: skip
    out = evaluate(cfg)
    # A fresh evaluation scores what the training run stored after its readout search.
    stored = load_checkpoint(run / "checkpoints" / "last.pt", expected_stage="img2occ")
    assert out["val/cam/miou"] == pytest.approx(stored["metrics"]["val/cam/miou"], abs=1e-9)
    files = sorted((pseudo_labels / "gts").glob("*/*/labels.npz"))
    assert len(files) == 24
    labels = load_occ3d_labels(files[0])
    assert labels.semantics.shape == (200, 200, 16)
    assert int(labels.semantics.max()) <= FREE_ID
    info = json.loads((pseudo_labels / "export_info.json").read_text())
    assert info["grid"]["shape"] == [200, 200, 16]


def test_paper_tokenizer_and_world_model_plan(full, tokenizer_ckpt, tmp_path):
    from renderworld.planning import PlanRequest, load_planner
    from renderworld.training.stages.world_model import export_planner_bundle

    tok = f"stage.tokenizer_ckpt={tokenizer_ckpt}"
    metrics = _train("paper_world_model", full, tmp_path / "wm", tok)
    assert metrics["step"] == 2 and math.isfinite(metrics["train/loss"])
    bundle = export_planner_bundle(
        tmp_path / "wm" / "checkpoints" / "last.pt", tokenizer_ckpt, tmp_path / "planner.pt"
    )
    planner = load_planner(bundle)
    occ = np.full((5, 200, 200, 16), FREE_ID, dtype=np.uint8)
    occ[..., 0] = 11  # driveable surface
    disp = np.tile([[2.0, 0.0]], (4, 1))
    res = planner.plan(PlanRequest(occ, disp, "straight"))
    assert res.trajectory.shape == (6, 2) and np.isfinite(res.trajectory).all()
    assert res.occupancy_forecast.shape == (6, 200, 200, 16)


def test_paper_camera_setting_trains_on_pseudo_labels(
    full, tokenizer_ckpt, pseudo_labels, tmp_path
):
    # The Camera setting's own tokenizer would be paper_tokenizer on the pseudo labels; the GT
    # one stands in here (same architecture) to keep the test's time down.
    metrics = _train(
        "paper_camera", full, tmp_path, f"stage.tokenizer_ckpt={tokenizer_ckpt}",
        f"stage.occ_root={pseudo_labels}",
    )  # fmt: skip
    assert metrics["step"] == 2 and math.isfinite(metrics["train/loss"])
