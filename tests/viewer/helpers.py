"""Helpers of the viewer tests."""

from __future__ import annotations

import dataclasses

import yaml

from renderworld.training.checkpoint import save_checkpoint


def tokenizer_checkpoint(tok, path):
    """A ``tokenizer`` checkpoint of ``tok`` with the run config its loader reads."""
    cfg = dataclasses.asdict(tok.cfg)
    model = {k: list(v) if isinstance(v, tuple) else v for k, v in cfg.items()}
    model.pop("grid_shape")
    config = {
        "grid": {"name": "coarse", "range_min": [-40.0, -40.0, -1.0],
                 "range_max": [40.0, 40.0, 5.4], "shape": list(tok.cfg.grid_shape)},
        "stage": {"name": "tokenizer", "model": model},
    }  # fmt: skip
    state = {"schema_version": 1, "stage": "tokenizer", "step": 0,
             "config": yaml.safe_dump(config), "model": tok.state_dict()}  # fmt: skip
    return save_checkpoint(state, path)


def world_model_checkpoint(wm, tokenizer_ckpt, path, forecaster="tokens", grid=None, **stage):
    """A ``world_model`` checkpoint of ``wm`` trained (as its config says) on ``tokenizer_ckpt``
    (``forecaster``: the ``stage.forecaster`` its config records; ``grid``: its ``grid`` group,
    default the coarse Occ3D-range grid; ``stage``: more ``stage`` keys)."""
    c = wm.config
    model = {"embed_dim": c.embed_dim, "num_heads": c.num_heads, "num_scales": c.num_scales,
             "layers_per_scale": list(c.layers_per_scale)}  # fmt: skip
    config = {
        "grid": grid or {"name": "coarse", "range_min": [-40.0, -40.0, -1.0],
                         "range_max": [40.0, 40.0, 5.4], "shape": [50, 50, 4]},
        "stage": {"name": "world_model", "history": c.history_frames, "future": c.future_frames,
                  "lambda_l2": 1.0, "tokenizer_ckpt": str(tokenizer_ckpt), "model": model,
                  "forecaster": forecaster, **stage},
    }  # fmt: skip
    state = {"schema_version": 1, "stage": "world_model", "step": 0,
             "config": yaml.safe_dump(config), "model": wm.state_dict()}  # fmt: skip
    return save_checkpoint(state, path)


def img2occ_checkpoint(model, path):
    """An ``img2occ`` checkpoint of ``model`` (the tiny coarse-grid one of conftest)."""
    c = model.cfg
    config = {
        "grid": {"name": "coarse", "range_min": list(c.grid.range_min),
                 "range_max": list(c.grid.range_max), "shape": list(c.grid.shape)},
        "stage": {"name": "img2occ", "input_size": list(c.input_size),
                  "render_size": list(c.render_size), "adjacent_frames": 0,
                  "model": {"encoder_channels": list(c.encoder_channels),
                            "feature_channels": c.feature_channels,
                            "head_channels": c.head_channels, "head_blocks": c.head_blocks}},
    }  # fmt: skip
    state = {"schema_version": 1, "stage": "img2occ", "step": 0,
             "config": yaml.safe_dump(config), "model": model.state_dict()}  # fmt: skip
    return save_checkpoint(state, path)
