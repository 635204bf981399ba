"""One bench point, in its own process: train, evaluate, time inference, report peak memory.

    python -m renderworld.bench.point <point_dir>/spec.json

(``renderworld.bench.sweep.run_point`` writes the spec and starts it.) Writes
``<point_dir>/result.json`` (a ``planner`` point: :func:`renderworld.bench.planner_point.run`):

* ``metrics``: ``evaluate(cfg)`` of the final ``last.pt`` on the stage's validation split (the
  stage's own metrics; Img2Occ with the readout threshold chosen at the end of training);
* ``train_s``: the training loop's own clock (``elapsed_s`` stored in ``last.pt``: optimizer
  steps and data loading, not the final validation / threshold search), ``train_wall_s`` all
  of ``train(cfg)``, ``train_cpu_s`` its CPU seconds and ``point_cpu_s`` the whole point's
  (on a shared machine wall time grows with the others' load, CPU time of one thread much
  less); ``steps`` the optimizer steps done (fewer than ``max_steps`` when the
  ``max_minutes`` cap stopped the run);
* ``infer_ms``: median over ``infer_frames`` validation samples of one sample's forward pass,
  each sample's time the best of ``REPEATS`` passes (the shared machine's load spikes inflate
  single passes by up to ~2x); batch 1, no grad, 1 torch thread, eval mode, after 2 warm-up
  passes, data loading excluded; what one sample is depends on the stage,
  ``STAGE_METRICS[stage]["sample"]``: the world model is timed through the public planner
  (its checkpoint and the tokenizer's exported as a bundle, ``load_planner``, a
  ``PlannerSession`` per window: :mod:`renderworld.bench.planner_latency`), whichever its
  forecaster;
* ``metrics`` of a world-model point also hold ``heldout/<metric>``: the same checkpoint
  evaluated on the held-out fixture (``bench.heldout_root``) when the sweep names one;
* ``peak_rss_mib``: this process's ``ru_maxrss`` at the end (training, evaluation and timing,
  including the Python / torch baseline of a few hundred MiB);
* ``knob_value``: the knob's value in the composed config (the default point's included).
"""

from __future__ import annotations

import json
import resource
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from torch.utils.data import DataLoader, Subset

from renderworld.bench.knobs import KNOBS, format_value
from renderworld.bench.planner_latency import (
    bundle_planner,
    cpu_seconds,
    requests_from_windows,
    time_plans,
)
from renderworld.training.api import evaluate, train
from renderworld.training.checkpoint import load_checkpoint
from renderworld.training.registry import get_stage

__all__ = ["run", "knob_value", "time_inference", "split_bench_overrides",
           "WARMUP", "REPEATS"]  # fmt: skip

WARMUP = 2
REPEATS = 3


def knob_value(cfg: Any, stage: str, knob: str) -> str:
    """The knob's value in a composed config, as text (``"auto 25x25"`` for a derived one)."""
    if knob == "default":
        return ""
    key = KNOBS[stage][knob].key
    if key == "grid":
        return str(cfg.grid.name)
    value = OmegaConf.select(cfg, key)
    if value is None and knob == "latent_size":
        from renderworld.training.stages.tokenizer import tokenizer_config

        return format_value(list(tokenizer_config(cfg).latent_shape))
    if OmegaConf.is_config(value):
        value = OmegaConf.to_container(value)
    if KNOBS[stage][knob].kind == "library":
        return "on" if value else "off"
    return format_value(value)


def _forward_fn(stage_name: str, stage: Any, model: torch.nn.Module, cfg: Any):
    """The stage's inference on one batch (see ``STAGE_METRICS[...]["sample"]``)."""
    if stage_name == "img2occ":
        return lambda b: model.readout(model(b, render=False))
    if stage_name == "tokenizer":
        return lambda b: model.decode(model.encode(b["occ"]))
    raise ValueError(f"stage: no inference timing for {stage_name!r}")


def time_inference(cfg: Any, ckpt_path: Path, frames: int) -> tuple[float, int]:
    """Median over samples of the best-of-``REPEATS`` ms of one sample's forward pass.

    Batch 1, eval mode, no grad, after ``WARMUP`` passes; batches are built beforehand.

    Args:
        cfg: the point's resolved training config.
        ckpt_path: checkpoint whose weights are timed.
        frames: validation samples timed (evenly spaced over the split).

    Returns:
        (median ms, the model's parameter count).
    """
    name = str(cfg.stage.name)
    stage = get_stage(name, cfg.stage.get("_target_module_"))(cfg)
    if name == "world_model":
        return _world_model_latency(stage, cfg, ckpt_path, frames)
    model = stage.build_model(cfg)
    model.load_state_dict(load_checkpoint(ckpt_path, expected_stage=name)["model"], strict=True)
    model.eval()
    _, val = stage.build_datasets(cfg)
    idx = _spaced(len(val), frames)
    loader = DataLoader(Subset(val, idx), batch_size=1, collate_fn=stage.collate_fn())
    batches = [stage.transfer_batch(b, torch.device("cpu")) for b in loader]
    fn = _forward_fn(name, stage, model, cfg)
    times = []
    with torch.no_grad():
        for b in batches[:1] * WARMUP:
            fn(b)
        for b in batches:
            best = float("inf")
            for _ in range(REPEATS):
                t0 = time.perf_counter()
                fn(b)
                best = min(best, 1000.0 * (time.perf_counter() - t0))
            times.append(best)
    return float(statistics.median(times)), sum(p.numel() for p in model.parameters())


def _spaced(n: int, frames: int) -> list[int]:
    """``frames`` indices evenly spaced over ``range(n)`` (fewer when ``n`` is smaller)."""
    return sorted({round(i * (n - 1) / max(frames - 1, 1)) for i in range(frames)})


def _world_model_latency(stage: Any, cfg: Any, ckpt_path: Path, frames: int) -> tuple[float, int]:
    """A world-model point's latency through the planner API (either forecaster)."""
    planner = bundle_planner(ckpt_path, Path(str(cfg.stage.tokenizer_ckpt)), fast=True)
    val = stage.build_val_dataset(cfg)
    loader = DataLoader(Subset(val, _spaced(len(val), frames)), batch_size=1,
                        collate_fn=stage.collate_fn())  # fmt: skip
    history = int(cfg.stage.history)
    requests = [r for b in loader for r in requests_from_windows(b, history)]
    ms, _ = time_plans(planner, requests, forecast=True, repeats=REPEATS, warmup=WARMUP)
    params = sum(p.numel() for p in planner.world_model.parameters())
    return ms, params


#: A point is measured on one thread (points run side by side); the experiments' own thread
#: count (``trainer.num_threads``, 2 for the main job's) would otherwise apply to its evaluation.
ONE_THREAD = "trainer.num_threads=1"


def split_bench_overrides(overrides: list[str]) -> tuple[list[str], dict[str, str]]:
    """(Hydra overrides, ``{key: value}`` of the ``bench.<key>=value`` ones)."""
    hydra, bench = [], {}
    for o in overrides:
        if o.startswith("bench."):
            key, value = o[len("bench.") :].split("=", 1)
            bench[key] = value
        else:
            hydra.append(o)
    return hydra, bench


def _heldout_metrics(spec: dict[str, Any], overrides: list[str], last: Path, point_dir: Path):
    """``heldout/<metric>`` of the checkpoint on ``bench.heldout_root`` ({} when none)."""
    _, bench = split_bench_overrides(spec["eval_overrides"])
    root = bench.get("heldout_root")
    if spec["stage"] != "world_model" or not root:
        return {}
    with initialize_config_dir(config_dir=spec["config_dir"], version_base="1.3"):
        cfg = compose(
            "eval",
            overrides=[f"experiment={spec['experiment']}", *overrides, f"dataset.data_root={root}",
                       f"ckpt={last}", f"run_dir={point_dir / 'eval_heldout'}", ONE_THREAD],
        )  # fmt: skip
    return {f"heldout/{k}": float(v) for k, v in evaluate(cfg).items()}


def run(spec: dict[str, Any]) -> dict[str, Any]:
    """Train, evaluate and time one point; write and return ``result.json``."""
    torch.set_num_threads(1)
    point_dir = Path(spec["point_dir"])
    run_dir, eval_dir = point_dir / "train", point_dir / "eval"
    exp = f"experiment={spec['experiment']}"
    train_ov, _ = split_bench_overrides(spec["overrides"])
    eval_ov, _ = split_bench_overrides(spec["eval_overrides"])
    with initialize_config_dir(config_dir=spec["config_dir"], version_base="1.3"):
        tcfg = compose("train", overrides=[exp, *train_ov, f"run_dir={run_dir}"])
        last = run_dir / "checkpoints" / "last.pt"
        ecfg = compose(
            "eval", overrides=[exp, *eval_ov, f"ckpt={last}", f"run_dir={eval_dir}", ONE_THREAD]
        )
    resolved = OmegaConf.create(OmegaConf.to_container(tcfg, resolve=False))
    resolved.run_dir = str(run_dir)
    resolved = OmegaConf.create(OmegaConf.to_container(resolved, resolve=True))
    t0, c0 = time.perf_counter(), cpu_seconds()
    train(tcfg)
    train_wall, train_cpu = time.perf_counter() - t0, cpu_seconds() - c0
    ck = load_checkpoint(last, expected_stage=str(resolved.stage.name))
    t0 = time.perf_counter()
    metrics = evaluate(ecfg)
    metrics.update(_heldout_metrics(spec, eval_ov, last, point_dir))
    eval_s = time.perf_counter() - t0
    infer_ms, params = time_inference(resolved, last, int(spec["infer_frames"]))
    result = {
        "stage": spec["stage"],
        "knob": spec["knob"],
        "value": spec["value"],
        "seed": int(spec.get("seed", 0)),
        "phase": spec.get("phase", ""),
        "knob_value": knob_value(resolved, spec["stage"], spec["knob"]),
        "knob_values": {k: knob_value(resolved, spec["stage"], k) for k in KNOBS[spec["stage"]]},
        "experiment": spec["experiment"],
        "grid": str(resolved.grid.name),
        "steps": int(ck["step"]),
        "max_steps": int(resolved.trainer.max_steps),
        "max_minutes": resolved.trainer.max_minutes,
        "train_s": float(ck.get("elapsed_s", float("nan"))),
        "train_wall_s": train_wall,
        "train_cpu_s": train_cpu,
        "eval_s": eval_s,
        "infer_ms": infer_ms,
        "infer_frames": int(spec["infer_frames"]),
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "point_cpu_s": cpu_seconds(),
        "params": int(params),
        "metrics": {k: float(v) for k, v in metrics.items()},
        "torch_threads": torch.get_num_threads(),
    }
    (point_dir / "result.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def main(argv: list[str]) -> None:
    if len(argv) != 2:
        raise SystemExit("usage: python -m renderworld.bench.point <spec.json>")
    spec = json.loads(Path(argv[1]).read_text())
    if spec["stage"] == "planner":
        from renderworld.bench.planner_point import run as run_planner

        run_planner(spec)
    else:
        run(spec)


if __name__ == "__main__":
    main(sys.argv)
