"""DDP on CPU: two gloo processes under torchrun against one process at the same global batch."""

from __future__ import annotations

import csv
import subprocess

import pytest
import torch

from renderworld.training import evaluate, train

from .conftest import PYTHON, REPO, SEARCHPATH, compose_cfg, fit_cfg, params_of, subprocess_env
from .regression_stage import RegressionStage

# 63 validation samples: rank shards of 32 and 31, so a mean of per-rank means would be off.
COMMON = [
    "trainer.max_steps=24",
    "trainer.val_every=12",
    "stage.num_val=63",
    "trainer.val_batch_size=5",
]


def _final_val_loss(run) -> float:
    with open(run / "metrics.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["key"] == "val/loss"]
    return float(rows[-1]["value"])


@pytest.fixture(scope="module")
def ddp_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("ddp") / "run"
    cmd = [
        PYTHON, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
        str(REPO / "tools" / "train.py"), SEARCHPATH, "experiment=regression_fit", *COMMON,
        "trainer.batch_size=8", "stage.dump_params=true", f"run_dir={run}",
    ]  # fmt: skip
    proc = subprocess.run(
        cmd, cwd=run.parent, env=subprocess_env(), capture_output=True, text=True, timeout=180
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return run


def test_ranks_hold_identical_parameters(ddp_run):
    p0 = torch.load(ddp_run / "params_rank0.pt", weights_only=True)
    p1 = torch.load(ddp_run / "params_rank1.pt", weights_only=True)
    for k in p0:
        assert torch.equal(p0[k], p1[k]), k
    assert not (ddp_run.parent / "outputs").exists()  # rank 1 wrote no Hydra dirs


def test_two_ranks_match_one_process_at_the_same_global_batch(ddp_run, tmp_path):
    # 2 ranks x batch 8 == 1 process x batch 16: same samples per step, averaged gradients.
    train(fit_cfg(tmp_path, *COMMON, "trainer.batch_size=16"))
    one = params_of(tmp_path / "checkpoints" / "last.pt")
    two = params_of(ddp_run / "checkpoints" / "last.pt")
    for k in one:
        torch.testing.assert_close(two[k], one[k], rtol=1e-5, atol=1e-6)


def test_validation_metrics_are_reduced_exactly(ddp_run, tmp_path):
    # Re-evaluate the DDP checkpoint in one process over all 63 samples.
    cfg = compose_cfg(
        ["stage=regression", "trainer=cpu", "stage.num_val=63", "trainer.val_batch_size=5",
         f"ckpt={ddp_run / 'checkpoints' / 'last.pt'}", f"run_dir={tmp_path}"],
        config_name="eval",
    )  # fmt: skip
    single = evaluate(cfg)["val/loss"]
    # Batches of 5 over different shards round differently in float32: ~1e-8 relative.
    assert _final_val_loss(ddp_run) == pytest.approx(single, rel=1e-6)
    # ... while a mean of the two shard means would be off by far more than that tolerance.
    stage = RegressionStage(cfg)
    model = stage.build_model(cfg)
    model.load_state_dict(torch.load(cfg.ckpt, weights_only=True)["model"])
    val = stage.build_datasets(cfg)[1]
    with torch.no_grad():
        per_sample = (model(val.x) - val.y).pow(2).mean(dim=1).double()
    mean_of_means = (per_sample[0::2].mean() + per_sample[1::2].mean()) / 2
    assert float(per_sample.mean()) == pytest.approx(single, rel=1e-6)
    assert abs(float(mean_of_means) - single) > 100 * 1e-6 * single
