"""The entry points as a user runs them: subprocesses from outside the repo, SIGKILL, multirun."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time

import pytest
import torch

from renderworld.training import train
from renderworld.training.checkpoint import load_checkpoint

from .conftest import PYTHON, REPO, SEARCHPATH, fit_cfg, params_of, subprocess_env

TRAIN = str(REPO / "tools" / "train.py")
EVAL = str(REPO / "tools" / "eval.py")


def _run(args, cwd, timeout=120):
    proc = subprocess.run(
        [PYTHON, *args], cwd=cwd, env=subprocess_env(), capture_output=True, text=True,
        timeout=timeout,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc


def test_train_then_eval_end_to_end(tmp_path):
    run, ev = tmp_path / "run", tmp_path / "eval"
    # cwd outside the repo and no PYTHONPATH: the tools must find the package themselves.
    _run([TRAIN, SEARCHPATH, "experiment=regression_fit", "trainer.max_steps=30", f"run_dir={run}"],
         cwd=tmp_path)  # fmt: skip
    assert (run / "checkpoints" / "last.pt").exists() and (run / "config.yaml").exists()
    assert list(run.glob(".hydra/*/overrides.yaml")), "Hydra's record goes into the run dir"
    assert not (tmp_path / "outputs").exists()
    ckpt = run / "checkpoints" / "last.pt"
    _run([EVAL, SEARCHPATH, "stage=regression", "trainer=cpu", f"ckpt={ckpt}", f"run_dir={ev}"],
         cwd=tmp_path)  # fmt: skip
    out = json.loads((ev / "eval_metrics.json").read_text())
    assert out["stage"] == "regression" and out["step"] == 30
    assert out["val/loss"] == pytest.approx(load_checkpoint(ckpt)["metrics"]["val/loss"], rel=1e-6)


def test_sigkilled_run_resumes_exactly(tmp_path):
    common = [
        "stage.dropout=0.1",
        "stage.jitter=0.05",
        "trainer.max_steps=40",
        "trainer.ckpt_every=5",
        "trainer.val_every=10",
    ]
    run = tmp_path / "run"
    last = run / "checkpoints" / "last.pt"
    proc = subprocess.Popen(
        [PYTHON, TRAIN, SEARCHPATH, "experiment=regression_fit", *common, "stage.step_sleep=0.05",
         f"run_dir={run}"],
        cwd=tmp_path, env=subprocess_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while proc.poll() is None and not last.exists() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert proc.poll() is None, "the run ended before it could be killed: " + str(
            proc.stderr.read()[-2000:] if proc.stderr else ""
        )
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
        if proc.stderr:
            proc.stderr.close()
    killed_at = load_checkpoint(last, "regression", for_training=True)["step"]
    assert 0 < killed_at < 40

    train(fit_cfg(tmp_path / "ref", *common))
    metrics = train(fit_cfg(run, *common, "resume=true"))
    assert metrics["step"] == 40
    ref, got = params_of(tmp_path / "ref/checkpoints/last.pt"), params_of(last)
    for k in ref:
        assert torch.equal(ref[k], got[k]), k


def test_multirun_sweep_writes_one_run_per_job(tmp_path):
    proc = _run([TRAIN, SEARCHPATH, "stage=regression", "hparams_search=lr_sweep", "debug=fast",
                 f"hydra.sweep.dir={tmp_path / 'sweep'}"], cwd=tmp_path)  # fmt: skip
    jobs = sorted((tmp_path / "sweep").iterdir())
    assert [j.name for j in jobs if j.is_dir()] == [str(i) for i in range(6)], proc.stdout[-2000:]
    lrs = set()
    for job in (j for j in jobs if j.is_dir()):
        ckpt = load_checkpoint(job / "checkpoints" / "last.pt", "regression")
        assert ckpt["step"] == 3
        lrs.add(float(ckpt["config"].split("lr: ")[1].split()[0]))
    assert lrs == {1e-4, 3e-4, 1e-3}
