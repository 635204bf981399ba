"""One ``planner`` point of the sweep: the main job's planner, one option changed, timed.

Nothing is trained. Options (the point's ``key=value`` overrides; defaults in brackets):
``forecast`` [true] (false: trajectory only), ``precision`` [float32] (bfloat16: the decoder
under autocast), ``threads`` [1] (torch intra-op threads), ``check`` [false] (true: the plan
checked against the forecast, :mod:`renderworld.planning.checked`), ``grid`` [mini]: ``mini`` is
the bundle of ``world_model_ckpt`` + ``tokenizer_ckpt`` (the main job's, 50x50x4) planning on
``windows`` validation windows of ``dataset.data_root``; ``occ3d`` is a paper-sized untrained
AM-VAE and pose-warp world model with a mover head (the main job's kind) at 200x200x16 on
street-like requests (``OCC3D_REQUESTS`` of them): latency only, its metrics are NaN;
``occ3d-checked`` the same with ``check`` true. ``repeats`` [3] and ``warmup`` [2] set the
timing's passes.

``result.json`` (same fields as a training point's, ``train_s`` 0):

* ``infer_ms``: :func:`renderworld.bench.planner_latency.time_plans` (batch 1, one
  ``PlannerSession.push`` + ``plan`` per window, best of ``REPEATS``, median over windows);
* ``metrics["val/l2_3s"]``: mean L2 (m) between the plan's 3 s waypoint and the logged one over
  the timed windows whose 3 s frame exists;
* ``metrics["val/forecast_equal"]``: fraction of forecast voxels equal to a float32 planner's on
  the same windows (1 for float32; NaN without a forecast).
"""

from __future__ import annotations

import json
import resource
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import OmegaConf
from torch.utils.data import DataLoader, Subset

from renderworld.bench.knobs import KNOBS
from renderworld.bench.planner_latency import (
    bundle_planner,
    cpu_seconds,
    make_request,
    occ3d_models,
    pose_warp_model,
    requests_from_windows,
    time_plans,
)
from renderworld.planning import Planner
from renderworld.training.checkpoint import load_checkpoint

__all__ = ["run", "planner_options", "OCC3D_REQUESTS"]

WARMUP = 2
REPEATS = 3
OCC3D_REQUESTS = 2
_DEFAULTS = {"forecast": "true", "precision": "float32", "threads": "1", "grid": "mini",
             "check": "false"}  # fmt: skip


def planner_options(overrides: list[str]) -> dict[str, Any]:
    """The point's options from its ``key=value`` overrides, typed, defaults filled in.

    Raises:
        ValueError: an override without ``=``, or a bad option value (naming the option).
    """
    raw = dict(_DEFAULTS)
    for o in overrides:
        if "=" not in o:
            raise ValueError(f"overrides: expected key=value, got {o!r}")
        key, value = o.split("=", 1)
        raw[key] = value
    if raw["forecast"] not in ("true", "false"):
        raise ValueError(f"forecast: expected true or false, got {raw['forecast']!r}")
    if raw["grid"] not in ("mini", "occ3d", "occ3d-checked"):
        raise ValueError(f"grid: expected mini, occ3d or occ3d-checked, got {raw['grid']!r}")
    if raw["check"] not in ("true", "false"):
        raise ValueError(f"check: expected true or false, got {raw['check']!r}")
    if raw["grid"] == "occ3d-checked":
        raw = {**raw, "grid": "occ3d", "check": "true"}
    threads = int(raw["threads"])
    if threads < 1:
        raise ValueError(f"threads: expected an int >= 1, got {threads}")
    return {**raw, "forecast": raw["forecast"] == "true", "check": raw["check"] == "true",
            "threads": threads,
            "windows": int(raw.get("windows", 7)), "repeats": int(raw.get("repeats", REPEATS)),
            "warmup": int(raw.get("warmup", WARMUP))}  # fmt: skip


def _val_windows(opts: dict[str, Any]) -> tuple[list, list]:
    """Requests of ``windows`` evenly spaced validation windows and their logged futures."""
    from renderworld.training.stages.world_model import WorldModelStage

    ckpt = load_checkpoint(opts["world_model_ckpt"], expected_stage="world_model")
    cfg = OmegaConf.create(ckpt["config"])
    cfg.dataset.data_root = opts["dataset.data_root"]
    cfg.stage.tokenizer_ckpt = opts["tokenizer_ckpt"]
    stage = WorldModelStage(cfg)
    val = stage.build_val_dataset(cfg)
    n, k = len(val), opts["windows"]
    idx = sorted({round(i * (n - 1) / max(k - 1, 1)) for i in range(k)})
    loader = DataLoader(Subset(val, idx), batch_size=1, collate_fn=stage.collate_fn())
    requests, futures = [], []
    for b in loader:
        requests += requests_from_windows(b, int(cfg.stage.history))
        futures.append((b["future_traj"][0].double().numpy(), b["future_mask"][0].bool().numpy()))
    return requests, futures


def _l2_3s(results, futures) -> float:
    errs = [
        float(np.linalg.norm(r.trajectory[-1] - traj[-1]))
        for r, (traj, valid) in zip(results, futures, strict=True)
        if valid[-1]
    ]
    return float(np.mean(errs)) if errs else float("nan")


def run(spec: dict[str, Any]) -> dict[str, Any]:
    """Time one planner point; write and return ``<point_dir>/result.json``."""
    opts = planner_options(spec["overrides"])
    torch.set_num_threads(opts["threads"])
    torch.manual_seed(int(spec.get("seed", 0)))
    point_dir = Path(spec["point_dir"])
    options = {"fast": True, "precision": opts["precision"]}
    metrics = {"val/l2_3s": float("nan"), "val/forecast_equal": float("nan")}
    if opts["grid"] == "mini":
        wm, tok = Path(opts["world_model_ckpt"]), Path(opts["tokenizer_ckpt"])
        planner = bundle_planner(wm, tok, **options)
        requests, futures = _val_windows(opts)
        ms, results = time_plans(
            planner, requests, opts["forecast"], opts["repeats"], opts["warmup"], opts["check"]
        )
        metrics["val/l2_3s"] = _l2_3s(results, futures)
        if opts["forecast"]:
            equal = 1.0
            if opts["precision"] != "float32":
                ref = bundle_planner(wm, tok, fast=True)
                _, refs = time_plans(ref, requests, True, 1, 0)
                equal = float(np.mean([
                    (a.occupancy_forecast == b.occupancy_forecast).mean()
                    for a, b in zip(results, refs, strict=True)
                ]))  # fmt: skip
            metrics["val/forecast_equal"] = equal
    else:
        tok, world = occ3d_models()
        world = pose_warp_model(world, movers="learned")
        planner = Planner(tok, world, **options)
        h = world.config.history_frames
        requests = [make_request((200, 200, 16), h, np.random.default_rng(i))
                    for i in range(OCC3D_REQUESTS)]  # fmt: skip
        ms, _ = time_plans(planner, requests, opts["forecast"], opts["repeats"], opts["warmup"],
                           opts["check"])  # fmt: skip
    params = sum(p.numel() for m in (planner.world_model, planner.tokenizer)
                 if isinstance(m, torch.nn.Module) for p in m.parameters())  # fmt: skip
    defaults = {**_DEFAULTS}
    result = {
        "stage": "planner",
        "knob": spec["knob"],
        "value": spec["value"],
        "seed": int(spec.get("seed", 0)),
        "phase": "",
        "knob_value": "" if spec["knob"] == "default" else str(spec["value"]).lower(),
        "knob_values": {k: defaults[k] for k in KNOBS["planner"]},
        "experiment": "",
        "grid": "occ3d 200x200x16" if opts["grid"] == "occ3d" else "mini 50x50x4",
        "steps": 0,
        "max_steps": 0,
        "max_minutes": None,
        "train_s": 0.0,
        "train_wall_s": 0.0,
        "eval_s": 0.0,
        "infer_ms": ms,
        "infer_frames": len(requests),
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "point_cpu_s": cpu_seconds(),
        "params": int(params),
        "metrics": metrics,
        "torch_threads": torch.get_num_threads(),
    }
    (point_dir / "result.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":  # pragma: no cover - run through renderworld.bench.point
    run(json.loads(Path(sys.argv[1]).read_text()))
