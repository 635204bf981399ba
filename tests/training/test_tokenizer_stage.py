"""The ``tokenizer`` stage's evaluation: the OccWorld protocol on its reconstructions."""

from __future__ import annotations

import pytest
import torch

from renderworld.constants import GRIDS
from renderworld.data import load_infos
from renderworld.metrics import OccupancyMetric
from renderworld.training import evaluate
from renderworld.training.stages.tokenizer import OccFrames, load_tokenizer

from . import test_world_model_stage as base
from .conftest import compose_cfg

# The world-model tests' module fixtures: the tiny fixture and a tiny tokenizer trained on it.
converted, tokenizer_ckpt = base.converted, base.tokenizer_ckpt


def test_eval_scores_the_reconstructions_with_renderworld_metrics(
    converted, tokenizer_ckpt, tmp_path
):
    """``val/miou`` / ``val/iou`` (full volume) and ``val/cam/*`` (camera mask) are what
    :class:`OccupancyMetric` gives on decode(encode(occ)) of every val frame, accumulated."""
    root, infos = converted
    cfg = compose_cfg(
        ["stage=tokenizer", *base._data(converted), f"ckpt={tokenizer_ckpt}",
         f"run_dir={tmp_path}", *base.QUIET, *base.TINY_TOKENIZER],
        "eval",
    )  # fmt: skip
    got = evaluate(cfg)
    tok = load_tokenizer(tokenizer_ckpt)
    frames = OccFrames(load_infos(infos, "val"), root, GRIDS["coarse"])
    full, cam = OccupancyMetric(), OccupancyMetric(mask_name="camera")
    with torch.no_grad():
        for i in range(len(frames)):
            occ, mask = frames[i]["occ"][None], frames[i]["mask_camera"][None]
            rec = tok.decode(tok.encode(occ))
            full.update(rec, occ)
            cam.update(rec, occ, mask=mask)
    want, want_cam = full.compute(), cam.compute()
    assert got["val/miou"] == pytest.approx(want["miou"], abs=1e-12)
    assert got["val/iou"] == pytest.approx(want["iou_geometry"], abs=1e-12)
    assert got["val/cam/miou"] == pytest.approx(want_cam["miou"], abs=1e-12)
    assert got["val/cam/iou"] == pytest.approx(want_cam["iou_geometry"], abs=1e-12)
    assert got["val/miou"] != pytest.approx(got["val/cam/miou"])  # the mask is applied
    assert 0.0 < got["val/miou"] < 1.0  # a 2-step tokenizer: neither nothing nor everything


def test_prior_init_starts_the_heads_at_the_training_frames_class_frequencies(converted, tmp_path):
    from renderworld.training.stages.tokenizer import TokenizerStage

    over = ["stage=tokenizer", *base._data(converted), f"run_dir={tmp_path}", *base.QUIET,
            *base.TINY_TOKENIZER]  # fmt: skip
    stage = TokenizerStage(compose_cfg([*over, "stage.prior_init=true"]))
    stage.build_datasets(stage.cfg)
    model = stage.build_model(stage.cfg)
    before = model.air_head.conv.bias.clone()
    stage.warm_start(model)
    # The ground level is never free, the levels above it mostly are.
    bias = model.air_head.conv.bias
    assert not torch.equal(before, bias)
    assert bias[0] < -5.0 and (bias[1:] > 1.0).all()
    off = TokenizerStage(compose_cfg(over))  # the default: untouched
    off.build_datasets(off.cfg)
    plain = off.build_model(off.cfg)
    b = plain.air_head.conv.bias.clone()
    off.warm_start(plain)
    assert torch.equal(b, plain.air_head.conv.bias)
    with pytest.raises(ValueError, match="stage.prior_init: expected true or false"):
        TokenizerStage(compose_cfg([*over, "stage.prior_init=3"]))


def test_class_balance_weights_the_cross_entropy_by_inverse_training_frequency(converted, tmp_path):
    """``stage.class_balance`` p: at the start of training (fresh or resumed) the model's CE
    weights become (f_c / f_max) ** -p of the training frames' class frequencies, so a rare
    class's voxel weighs more than a free one and the loss of the same batch changes."""
    from renderworld.training.stages.tokenizer import TokenizerStage, balanced_class_weights

    over = ["stage=tokenizer", *base._data(converted), f"run_dir={tmp_path}", *base.QUIET,
            *base.TINY_TOKENIZER]  # fmt: skip
    stage = TokenizerStage(compose_cfg([*over, "stage.class_balance=0.5"]))
    train, _ = stage.build_datasets(stage.cfg)
    model = stage.build_model(stage.cfg)
    batch = torch.stack([train[i]["occ"] for i in range(2)])
    torch.manual_seed(0)
    plain_loss = model(batch).loss.item()
    assert model.class_weights is None
    stage.on_train_start(model, str(tmp_path))
    w = model.class_weights
    counts = torch.zeros(18, dtype=torch.float64)
    for i in range(len(train)):
        counts += torch.bincount(train[i]["occ"].long().reshape(-1), minlength=18).double()
    seen = counts > 0
    assert w[counts.argmax()] == pytest.approx(1.0)
    torch.testing.assert_close(
        w[seen].double(), (counts[seen] / counts.max()) ** -0.5, rtol=1e-5, atol=0
    )
    assert (w[~seen] == w[seen].max()).all()
    torch.manual_seed(0)
    assert model(batch).loss.item() != pytest.approx(plain_loss, rel=1e-4)
    off = TokenizerStage(compose_cfg(over))  # the default leaves the CE unweighted
    off.build_datasets(off.cfg)
    plain = off.build_model(off.cfg)
    off.on_train_start(plain, str(tmp_path))
    assert plain.class_weights is None
    assert torch.equal(balanced_class_weights(counts, 0.0), torch.ones(18))
    with pytest.raises(ValueError, match="power: expected a number >= 0"):
        balanced_class_weights(counts, -0.5)
    with pytest.raises(ValueError, match="counts: expected"):
        balanced_class_weights(torch.zeros(18), 0.5)
    with pytest.raises(ValueError, match="stage.class_balance: expected a number >= 0"):
        TokenizerStage(compose_cfg([*over, "stage.class_balance=-1"]))
    with pytest.raises(ValueError, match="not both"):
        TokenizerStage(
            compose_cfg([*over, "stage.class_balance=0.5",
                         f"+stage.model.class_weights={[1.0] * 18}"])
        )  # fmt: skip


def test_eval_builds_the_checkpoints_architecture_when_the_config_differs(
    converted, tokenizer_ckpt, tmp_path
):
    """A checkpoint trained with another ``stage.model`` (here 32 codes, the run saying 64)
    evaluates as itself, with a warning naming what differs; a checkpoint of another grid is a
    clear error naming ``ckpt``."""
    over = ["stage=tokenizer", *base._data(converted), f"ckpt={tokenizer_ckpt}", *base.QUIET,
            *base.TINY_TOKENIZER]  # fmt: skip
    same = evaluate(compose_cfg([*over, f"run_dir={tmp_path / 'same'}"], "eval"))
    with pytest.warns(UserWarning, match=r"trained with stage.model codebook_size=32"):
        other = evaluate(
            compose_cfg(
                [*over, "stage.model.codebook_size=64", f"run_dir={tmp_path / 'other'}"], "eval"
            )
        )
    assert other["val/miou"] == same["val/miou"] and other["val/iou"] == same["val/iou"]
    with pytest.raises(ValueError, match=r"ckpt: .* was trained on a \(50, 50, 4\) grid"):
        half = ["grid=half" if o == "grid=coarse" else o for o in over]
        evaluate(compose_cfg([*half, f"run_dir={tmp_path / 'grid'}"], "eval"))
