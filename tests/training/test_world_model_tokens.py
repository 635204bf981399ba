"""The ``tokens`` forecaster reads the history only, though evaluation hands it the whole window.

``WorldModelStage.evaluate`` encodes every frame of a window (the teacher-forced loss needs them)
and passes those codes to ``forecast``, which must roll out from the first ``history`` frames
alone: changing anything after the current frame t (occupancy, its codes, sample tokens, masks,
poses, displacements, boxes) leaves the forecast and the plan bit-identical.
"""

from __future__ import annotations

import copy

import torch
from torch.utils.data import DataLoader

from renderworld.training.stages.world_model import WorldModelStage
from renderworld.world import WorldModel

from . import test_world_model_stage as base
from .conftest import compose_cfg

HISTORY, FUTURE = base.HISTORY, base.FUTURE
# The stage tests' module fixtures: the tiny fixture, its tiny tokenizer and the overrides.
converted, tokenizer_ckpt, wm_overrides = base.converted, base.tokenizer_ckpt, base.wm_overrides


def perturb_future(batch: dict, history: int, seed: int = 0) -> dict:
    """A copy of a collated window batch with every input after the current frame replaced.

    Frames ``history..`` get random occupancy, inverted camera masks and new sample tokens (so
    no cache can hand back their old codes); future poses, trajectories, boxes, box masks and
    the displacements out of the current frame onwards are random. The history is untouched.
    """
    g = torch.Generator().manual_seed(seed)
    other = copy.deepcopy(batch)
    h = history
    for key in ("occ", "occ_target"):
        if key in other:
            shape = other[key][:, h:].shape
            other[key][:, h:] = torch.randint(0, 18, shape, generator=g).to(torch.uint8)
    for key in ("mask_camera", "mask_camera_target"):
        if key in other:
            other[key][:, h:] = ~other[key][:, h:]
    for key in ("future_poses", "future_traj", "future_boxes"):
        other[key] = torch.randn(other[key].shape, generator=g) * 10
    disp = other["ego_displacements"]
    disp[:, h - 1 :] = torch.randn(disp[:, h - 1 :].shape, generator=g) * 5
    other["future_boxes_mask"] = ~other["future_boxes_mask"]
    tokens = other["meta"]["sample_tokens"]
    other["meta"]["sample_tokens"] = tokens[:h] + [
        [f"{t}-changed" for t in column] for column in tokens[h:]
    ]
    return other


def _random_codes(codes, frames: slice, sizes, g: torch.Generator) -> torch.Tensor:
    """``codes`` [B, T, G, h, w] with the ``frames`` drawn at random from each codebook."""
    out = codes.clone()
    for i, k in enumerate(sizes):
        out[:, frames, i] = torch.randint(0, k, out[:, frames, i].shape, generator=g)
    return out


def busy_stage(overrides: list[str], tmp_path) -> tuple:
    """(stage, model, val windows) of ``overrides``: a fresh model with every weight moved, so
    the ego / pose head is not its prior and the token net is busy."""
    cfg = compose_cfg([*overrides, f"run_dir={tmp_path}"])
    stage = WorldModelStage(cfg)
    _, val_set = stage.build_datasets(cfg)
    model = stage.build_model(cfg).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return stage, model, val_set


def test_changing_the_future_leaves_the_forecast_and_plan_unchanged(wm_overrides, tmp_path):
    stage, model, val_set = busy_stage(wm_overrides, tmp_path)
    assert stage.forecaster == "tokens" and isinstance(model, WorldModel)
    batch = next(iter(DataLoader(val_set, batch_size=2)))
    setting, h = stage.eval_settings[0], HISTORY
    window = HISTORY + FUTURE
    cpu = torch.device("cpu")
    # As evaluate() calls it: the codes of the whole window, the future ones included.
    tokens = stage.window_tokens(batch, window, cpu)
    fc, traj = stage.forecast(model, batch, setting, tokens)
    other = perturb_future(batch, h)
    changed = stage.window_tokens(other, window, cpu)
    assert torch.equal(changed[:, :h], tokens[:, :h]) and not torch.equal(changed, tokens)
    g = torch.Generator().manual_seed(1)
    random_codes = _random_codes(changed, slice(h, None), model.config.codebook_sizes, g)
    for future_codes in (changed, random_codes, None):  # None: forecast encodes the history
        fc2, traj2 = stage.forecast(model, other, setting, future_codes)
        for k in ("model", "copy_paste", "warp_cv", "warp_ctr"):
            assert torch.equal(fc[k], fc2[k]), k
        for k in ("model", "cv_traj", "ctr_traj"):
            assert torch.equal(traj[k], traj2[k]), k
    # The history does drive it (the test above could not pass by ignoring every input).
    old_codes = _random_codes(tokens, slice(0, h - 1), model.config.codebook_sizes, g)
    fc3, traj3 = stage.forecast(model, batch, setting, old_codes)
    assert not torch.equal(fc3["model"], fc["model"])
    assert not torch.equal(traj3["model"], traj["model"])
    moved = copy.deepcopy(batch)
    moved["ego_displacements"][:, : h - 1] += 0.5
    _, traj4 = stage.forecast(model, moved, setting, tokens)
    assert not torch.equal(traj4["model"], traj["model"])
