"""The loop on a real (small) learning problem: learning, exact resume, accumulation, budget."""

from __future__ import annotations

import copy
import csv
import random
import sys
import types

import pytest
import torch

from renderworld.training import evaluate, train
from renderworld.training.checkpoint import load_checkpoint
from renderworld.training.schedule import read_schedule

from .conftest import compose_cfg, fit_cfg, params_of


def _rows(run) -> list[dict[str, str]]:
    with open(run / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_regression_learns_and_returns_metrics(tmp_path):
    metrics = train(fit_cfg(tmp_path))
    # y = A x + b with A, b ~ N(0, 1) in 8 dims: predicting 0 costs ~9 MSE; noise floor 0.0025.
    assert metrics["val/loss"] < 0.05
    assert metrics["step"] == 150 and metrics["stopped_early"] == 0.0
    record = read_schedule(tmp_path)
    assert (record["step"], record["max_steps"], record["stopped_early"]) == (150, 150, False)
    assert {"train/loss", "val/loss", "val/mae", "best/val/loss"} <= set(metrics)
    rows = _rows(tmp_path)
    val = [(int(r["step"]), float(r["value"])) for r in rows if r["key"] == "val/loss"]
    assert [s for s, _ in val] == [50, 100, 150]
    assert val[0][1] > val[-1][1]
    best = load_checkpoint(tmp_path / "checkpoints" / "best.pt", "regression")
    assert best["best"]["value"] == pytest.approx(min(v for _, v in val))
    assert (tmp_path / "config.yaml").read_text().startswith("task: train")
    assert {"train/samples_per_s", "train/lr", "train/grad_norm"} <= {r["key"] for r in rows}


def test_a_stages_lr_scales_reach_the_optimizer(tmp_path, monkeypatch):
    from tests.training.regression_stage import RegressionStage

    def run(name: str, steps: int) -> dict[str, torch.Tensor]:
        train(fit_cfg(tmp_path / name, f"trainer.max_steps={steps}"))
        return params_of(tmp_path / name / "checkpoints" / "last.pt")

    a, b = run("plain10", 10), run("plain20", 20)
    assert (a["1.bias"] - b["1.bias"]).abs().max() > 1e-3  # the bias trains
    monkeypatch.setattr(RegressionStage, "lr_scales", lambda self: {"1.bias": 1e-9})
    c, d = run("scaled10", 10), run("scaled20", 20)
    torch.testing.assert_close(c["1.bias"], d["1.bias"], atol=1e-6, rtol=0)  # at ~0 rate
    assert (c["1.weight"] - d["1.weight"]).abs().max() > 1e-3  # the rest still trains


def test_warm_start_runs_once_on_a_fresh_run_and_keeps_the_rng_stream(tmp_path, monkeypatch):
    from tests.training.regression_stage import RegressionStage

    common = ["stage.dropout=0.1", "trainer.max_steps=12", "trainer.ckpt_every=6"]
    train(fit_cfg(tmp_path / "ref", *common))
    calls = []

    def draws(self, model):  # random numbers only: the run's own stream must not shift
        calls.append("draws")
        torch.rand(100)
        random.random()

    monkeypatch.setattr(RegressionStage, "warm_start", draws)
    train(fit_cfg(tmp_path / "draws", *common))
    assert calls == ["draws"]
    ref = params_of(tmp_path / "ref/checkpoints/last.pt")
    got = params_of(tmp_path / "draws/checkpoints/last.pt")
    for k in ref:
        assert torch.equal(ref[k], got[k]), k
    # Not again on a resume: the checkpoint already holds its result.
    train(fit_cfg(tmp_path / "draws", "stage.dropout=0.1", "trainer.max_steps=18",
                  "trainer.ckpt_every=6", "resume=true"))  # fmt: skip
    assert calls == ["draws"]

    def moves(self, model):  # what it fits is kept into the training
        with torch.no_grad():
            model[1].bias.fill_(50.0)

    monkeypatch.setattr(RegressionStage, "warm_start", moves)
    train(fit_cfg(tmp_path / "moves", "stage.dropout=0.1", "trainer.max_steps=1"))
    bias = params_of(tmp_path / "moves/checkpoints/last.pt")["1.bias"]
    assert (bias > 40).all()


def test_evaluate_reproduces_final_validation(tmp_path):
    metrics = train(fit_cfg(tmp_path / "run", "trainer.max_steps=30"))
    cfg = compose_cfg(
        [
            "stage=regression",
            "trainer=cpu",
            f"ckpt={tmp_path / 'run' / 'checkpoints' / 'last.pt'}",
            f"run_dir={tmp_path / 'eval'}",
        ],
        config_name="eval",
    )
    out = evaluate(cfg)
    assert out["val/loss"] == pytest.approx(metrics["val/loss"], rel=1e-6)
    assert out["step"] == 30
    assert (tmp_path / "eval" / "eval_metrics.json").exists()


def test_eval_requires_ckpt(tmp_path):
    cfg = compose_cfg(["stage=regression", f"run_dir={tmp_path}"], config_name="eval")
    with pytest.raises(ValueError, match=r"ckpt: required config value is missing \(\?\?\?\)"):
        evaluate(cfg)


@pytest.mark.parametrize(
    ("workers", "steps", "crash_call", "ckpt_step"), [(0, 40, 24, 21), (2, 20, 17, 14)]
)
def test_crash_and_resume_is_exact(tmp_path, workers, steps, crash_call, ckpt_step):
    """A run that crashes mid-epoch and resumes ends bit-identical to an uninterrupted run.

    Dropout and per-sample jitter make the result depend on every RNG stream the checkpoint
    must restore (torch, and the data order / worker seeds).
    """
    common = [
        "stage.dropout=0.1",
        "stage.jitter=0.05",
        f"trainer.max_steps={steps}",
        "trainer.ckpt_every=7",
        "trainer.val_every=10",
        f"trainer.num_workers={workers}",
    ]
    train(fit_cfg(tmp_path / "ref", *common))
    crash = fit_cfg(tmp_path / "run", *common, f"stage.crash_at_call={crash_call}")
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(crash)
    assert load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")["step"] == ckpt_step
    metrics = train(fit_cfg(tmp_path / "run", *common, "resume=true"))
    assert metrics["step"] == steps
    ref, got = (
        params_of(tmp_path / "ref/checkpoints/last.pt"),
        params_of(tmp_path / "run/checkpoints/last.pt"),
    )
    for k in ref:
        assert torch.equal(ref[k], got[k]), k
    # metrics.csv: nothing logged twice across the crash.
    keys = [(r["step"], r["key"]) for r in _rows(tmp_path / "run")]
    assert len(keys) == len(set(keys))
    assert (tmp_path / "run" / f"config.resume-step{ckpt_step}.yaml").exists()


def test_resume_may_change_the_micro_batch_layout(tmp_path):
    """The data position is global: resuming batch 16 as 8 x 2 accumulation sees the same data."""
    common = ["trainer.max_steps=40", "trainer.ckpt_every=7"]
    train(fit_cfg(tmp_path / "ref", *common))
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(fit_cfg(tmp_path / "run", *common, "stage.crash_at_call=24"))
    layout = ["trainer.batch_size=8", "trainer.grad_accum=2"]
    assert train(fit_cfg(tmp_path / "run", *common, *layout, "resume=true"))["step"] == 40
    ref = params_of(tmp_path / "ref/checkpoints/last.pt")
    got = params_of(tmp_path / "run/checkpoints/last.pt")
    for k in ref:
        torch.testing.assert_close(got[k], ref[k], rtol=1e-5, atol=1e-6)


def test_gradient_accumulation_matches_a_larger_batch(tmp_path):
    a = train(fit_cfg(tmp_path / "a", "trainer.max_steps=20", "trainer.batch_size=16"))
    b = train(
        fit_cfg(
            tmp_path / "b", "trainer.max_steps=20", "trainer.batch_size=8", "trainer.grad_accum=2"
        )
    )
    pa, pb = (
        params_of(tmp_path / "a/checkpoints/last.pt"),
        params_of(tmp_path / "b/checkpoints/last.pt"),
    )
    for k in pa:
        torch.testing.assert_close(pa[k], pb[k], rtol=1e-5, atol=1e-6)
    assert a["val/loss"] == pytest.approx(b["val/loss"], rel=1e-4)


def test_time_budget_stops_cleanly_and_checkpoints(tmp_path):
    cfg = fit_cfg(tmp_path, "trainer.max_minutes=0.005", "stage.step_sleep=0.02")
    metrics = train(cfg)  # 0.3 s budget, >= 20 ms per step: far fewer than 150 steps
    assert metrics["stopped_early"] == 1.0
    assert 0 < metrics["step"] < 150
    ckpt = load_checkpoint(tmp_path / "checkpoints" / "last.pt", "regression", for_training=True)
    assert ckpt["step"] == metrics["step"]
    assert ckpt["elapsed_s"] >= 0.3
    # The run dir says where the guard stopped it, for reports.
    record = read_schedule(tmp_path)
    assert record["stopped_early"] and record["step"] == metrics["step"]
    assert record["max_steps"] == 150 and record["max_minutes"] == 0.005
    # Resuming with the same budget stops at once; a larger budget continues.
    again = train(fit_cfg(tmp_path, "resume=true", "trainer.max_minutes=0.005"))
    assert again["step"] == metrics["step"]


def test_epochs_bound_the_run(tmp_path):
    # 256 samples / batch 16 = 16 steps per epoch.
    metrics = train(fit_cfg(tmp_path, "trainer.max_steps=null", "trainer.max_epochs=2"))
    assert metrics["step"] == 32


@pytest.mark.parametrize("precision", ["bf16", "fp16"])
def test_mixed_precision_on_cpu_learns_under_autocast(tmp_path, precision, monkeypatch):
    """The trainer's mixed-precision path runs on CPU too (autocast("cpu")): the linear model's
    matmul really runs in the low precision, fp16 through a gradient scaler."""
    seen = []
    real = torch.nn.functional.linear

    def spy(x, w, b=None):
        out = real(x, w, b)
        seen.append(out.dtype)
        return out

    monkeypatch.setattr(torch.nn.functional, "linear", spy)
    metrics = train(fit_cfg(tmp_path, f"trainer.precision={precision}"))
    # Noise floor 0.0025; bf16 / fp16 outputs of |y| ~ 3 round by <= 0.012.
    assert metrics["val/loss"] < 0.05
    low = torch.bfloat16 if precision == "bf16" else torch.float16
    assert low in seen
    ckpt = load_checkpoint(tmp_path / "checkpoints" / "last.pt", for_training=True)
    assert bool(ckpt["grad_scaler"]) == (precision == "fp16")


def test_fp16_skips_an_overflowing_step_instead_of_stopping(tmp_path):
    # bf16 / 32-bit raise on a non-finite gradient (next test); fp16's scaler skips the step,
    # halves its scale and trains on: overflow is expected there.
    scales = []
    for name, extra in (("ref", []), ("nan", ["stage.nan_at_call=3"])):
        metrics = train(fit_cfg(tmp_path / name, "trainer.precision=fp16", *extra))
        assert metrics["val/loss"] < 0.05 and metrics["step"] == 150
        ckpt = load_checkpoint(tmp_path / name / "checkpoints" / "last.pt", for_training=True)
        scales.append(ckpt["grad_scaler"]["scale"])
    assert scales[1] == scales[0] / 2  # one more skipped step (no growth within 150 steps)


def test_non_finite_loss_stops_with_a_clear_error(tmp_path):
    with pytest.raises(FloatingPointError, match="non-finite gradient norm .* at step 3"):
        train(fit_cfg(tmp_path, "stage.nan_at_call=3"))


def test_unknown_monitor_metric_fails_clearly(tmp_path):
    with pytest.raises(
        ValueError, match=r"metric 'val/iou' not produced; .*\['val/loss', 'val/mae'\]"
    ):
        train(fit_cfg(tmp_path, "trainer.monitor=val/iou", "trainer.max_steps=10"))


def test_missing_required_key_fails_clearly(tmp_path):
    with pytest.raises(ValueError, match=r"stage.upstream_ckpt: required config value is missing"):
        train(fit_cfg(tmp_path, "+stage.upstream_ckpt=???"))


def test_bad_seed_fails_clearly(tmp_path):
    with pytest.raises(ValueError, match=r"seed: expected an int in \[0, 2\*\*31\), got -1"):
        train(fit_cfg(tmp_path, "seed=-1"))


def test_data_seed_sets_the_sample_order_alone(tmp_path, monkeypatch):
    # seed=1 with trainer.data_seed=0: seed 0's batches, seed 1's initial weights.
    from tests.training.regression_stage import RegressionStage

    seen: list[tuple[torch.Tensor, dict[str, torch.Tensor] | None]] = []
    loss = RegressionStage.loss

    def recording(self, model, batch):
        first = {k: v.detach().clone() for k, v in model.state_dict().items()}
        seen.append((batch["x"].clone(), first if not seen else None))
        return loss(self, model, batch)

    monkeypatch.setattr(RegressionStage, "loss", recording)

    def run(name: str, *over: str):
        seen.clear()
        train(fit_cfg(tmp_path / name, "trainer.max_steps=6", "trainer.val_every=0", *over))
        return torch.stack([x for x, _ in seen]), seen[0][1]

    x1, init1 = run("s1", "seed=1")
    x0, init0 = run("s0", "seed=0")
    xd, initd = run("s1d0", "seed=1", "trainer.data_seed=0")
    assert torch.equal(xd, x0) and not torch.equal(xd, x1)
    assert all(torch.equal(initd[k], init1[k]) for k in init1)
    assert any(not torch.equal(init0[k], init1[k]) for k in init1)
    with pytest.raises(ValueError, match=r"trainer.data_seed: expected null or an int"):
        train(fit_cfg(tmp_path / "bad", "trainer.data_seed=-1"))


def test_unknown_stage_module_fails_clearly(tmp_path):
    cfg = fit_cfg(tmp_path, "stage.name=nope", "stage._target_module_=tests.training.no_such")
    with pytest.raises(ValueError, match="stage 'nope': cannot import its module"):
        train(cfg)


def test_train_outside_hydra_needs_run_dir():
    cfg = compose_cfg(["experiment=regression_fit"])
    with pytest.raises(ValueError, match="run_dir: cannot be resolved outside a Hydra app"):
        train(cfg)


def test_tensorboard_is_used_when_installed(tmp_path, monkeypatch):
    logged = []

    class FakeWriter:
        def __init__(self, log_dir):
            self.log_dir = log_dir

        def add_scalar(self, key, value, global_step):
            logged.append((key, global_step))

        def flush(self):
            pass

        def close(self):
            pass

    fake = types.ModuleType("torch.utils.tensorboard")
    fake.SummaryWriter = FakeWriter
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", fake)
    train(fit_cfg(tmp_path, "trainer.tensorboard=true", "trainer.max_steps=10"))
    assert ("train/loss", 10) in logged and ("val/loss", 10) in logged


@pytest.mark.slow
def test_worker_count_does_not_change_results(tmp_path):
    """Per-sample seeding: augmentation in workers depends on (seed, epoch, index) only."""
    common = ["stage.jitter=0.1", "trainer.max_steps=20"]
    train(fit_cfg(tmp_path / "w1", *common, "trainer.num_workers=1"))
    train(fit_cfg(tmp_path / "w2", *common, "trainer.num_workers=2"))
    p1, p2 = (
        params_of(tmp_path / "w1/checkpoints/last.pt"),
        params_of(tmp_path / "w2/checkpoints/last.pt"),
    )
    for k in p1:
        assert torch.equal(p1[k], p2[k]), k


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("precision", ["32", "bf16", "fp16"])
def test_cuda_mixed_precision_learns(tmp_path, precision):
    metrics = train(fit_cfg(tmp_path, "trainer.device=cuda", f"trainer.precision={precision}"))
    assert metrics["val/loss"] < 0.05
    ckpt = load_checkpoint(tmp_path / "checkpoints" / "last.pt", for_training=True)
    assert all(t.device.type == "cpu" for t in ckpt["model"].values())
    assert bool(ckpt["grad_scaler"]) == (precision == "fp16")


def test_evaluate_shows_a_bar_over_the_batches_and_scores_the_same(tmp_path, capsys):
    """A long evaluation shows its progress; the bar changes nothing in what is scored."""
    train(fit_cfg(tmp_path / "run", "trainer.max_steps=5"))
    capsys.readouterr()
    out = {}
    for bar in (True, False):
        cfg = compose_cfg(
            ["stage=regression", "trainer=cpu", f"trainer.progress_bar={bar}",
             f"ckpt={tmp_path / 'run' / 'checkpoints' / 'last.pt'}",
             f"run_dir={tmp_path / f'eval_{bar}'}"],
            config_name="eval",
        )  # fmt: skip
        out[bar] = evaluate(cfg)
        err = capsys.readouterr().err
        assert ("regression: validation" in err) == bar
    assert out[True] == out[False]


def test_the_progress_loader_is_the_loader_to_a_stage():
    from renderworld.training.validation import ProgressLoader

    loader = torch.utils.data.DataLoader(list(range(7)), batch_size=3)
    wrapped = ProgressLoader(loader, "x")
    assert wrapped.dataset is loader.dataset and wrapped.batch_size == 3 and len(wrapped) == 3
    assert [b.tolist() for b in wrapped] == [b.tolist() for b in loader]
    assert copy.copy(wrapped).loader is loader  # a copy is built before its loader is set
