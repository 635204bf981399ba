"""EMA of the weights: the average itself, the checkpoint layout, exact resume, bad input."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from renderworld.training import evaluate, train
from renderworld.training.checkpoint import load_checkpoint
from renderworld.training.ema import WeightEMA

from .conftest import compose_cfg, fit_cfg


class _Tiny(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.zeros(3))
        self.register_buffer("threshold", torch.tensor(0.5))


def test_average_follows_the_ema_recursion_and_copies_buffers():
    model, decay = _Tiny(), 0.75
    ema = WeightEMA(model, decay)
    values = [torch.tensor([1.0, 2.0, 3.0]), torch.tensor([5.0, 0.0, -1.0]), torch.full((3,), 2.0)]
    expected = None
    for v in values:
        with torch.no_grad():
            model.w.copy_(v)
        ema.update(model)
        # The first update copies the weights, later ones blend them in.
        expected = v.clone() if expected is None else decay * expected + (1 - decay) * v
        torch.testing.assert_close(ema.module.w, expected)
    assert ema.state() == {"decay": decay, "n_averaged": 3}
    model.threshold.fill_(0.8)  # a buffer the stage sets on purpose is the trained model's
    ema.update(model)
    assert float(ema.module.threshold) == pytest.approx(0.8)
    # The weights blend in once more, unaffected by the buffer.
    torch.testing.assert_close(ema.module.w, decay * expected + (1 - decay) * values[-1])


def test_checkpoint_holds_the_average_as_model_and_the_trained_weights_as_model_raw(tmp_path):
    metrics = train(fit_cfg(tmp_path / "run", "trainer.max_steps=40", "trainer.ema_decay=0.9"))
    ckpt = load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt", "regression")
    assert ckpt["ema"] == {"decay": 0.9, "n_averaged": 40}
    assert set(ckpt["model"]) == set(ckpt["model_raw"])
    assert any(not torch.equal(ckpt["model"][k], ckpt["model_raw"][k]) for k in ckpt["model"])
    # Validation during training and tools/eval.py (which loads "model") score the average.
    out = evaluate(
        compose_cfg(
            [
                "stage=regression",
                "trainer=cpu",
                f"ckpt={tmp_path / 'run' / 'checkpoints' / 'last.pt'}",
                f"run_dir={tmp_path / 'eval'}",
            ],
            config_name="eval",
        )
    )
    assert out["val/loss"] == pytest.approx(metrics["val/loss"], rel=1e-6)


def test_crash_and_resume_with_an_ema_is_exact(tmp_path):
    common = [
        "stage.dropout=0.1",
        "trainer.max_steps=30",
        "trainer.ckpt_every=7",
        "trainer.val_every=10",
        "trainer.ema_decay=0.8",
    ]
    train(fit_cfg(tmp_path / "ref", *common))
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(fit_cfg(tmp_path / "run", *common, "stage.crash_at_call=20"))
    train(fit_cfg(tmp_path / "run", *common, "resume=true"))
    ref = load_checkpoint(tmp_path / "ref" / "checkpoints" / "last.pt")
    got = load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")
    assert got["ema"] == ref["ema"]
    for key in ("model", "model_raw"):
        for name in ref[key]:
            assert torch.equal(ref[key][name], got[key][name]), (key, name)


def test_turning_the_ema_on_at_a_resume_starts_the_average_there(tmp_path):
    train(fit_cfg(tmp_path, "trainer.max_steps=10"))
    plain = load_checkpoint(tmp_path / "checkpoints" / "last.pt")
    assert "model_raw" not in plain and "ema" not in plain
    train(fit_cfg(tmp_path, "trainer.max_steps=15", "trainer.ema_decay=0.9", "resume=true"))
    ckpt = load_checkpoint(tmp_path / "checkpoints" / "last.pt")
    assert ckpt["step"] == 15 and ckpt["ema"]["n_averaged"] == 5


@pytest.mark.parametrize("decay", [1.0, -0.5, 1.5])
def test_bad_decay_names_the_key(tmp_path, decay):
    with pytest.raises(ValueError, match=r"trainer\.ema_decay"):
        train(fit_cfg(tmp_path, f"trainer.ema_decay={decay}"))
    with pytest.raises(ValueError, match=r"trainer\.ema_decay"):
        WeightEMA(_Tiny(), decay)
