"""One bench point, in its own process: train, evaluate, time inference, report peak memory.

    python -m renderworld.bench.point <point_dir>/spec.json

(``renderworld.bench.sweep.run_point`` writes the spec and starts it.) Writes
``<point_dir>/result.json``:

* ``metrics``: ``evaluate(cfg)`` of the final ``last.pt`` on the stage's validation split (the
  stage's own metrics; Img2Occ with the readout threshold chosen at the end of training);
* ``train_s``: the training loop's own clock (``elapsed_s`` stored in ``last.pt``: optimizer
  steps and data loading, not the final validation / threshold search), ``train_wall_s`` all
  of ``train(cfg)``; ``steps`` the optimizer steps done (fewer than ``max_steps`` when the
  ``max_minutes`` cap stopped the run);
* ``infer_ms``: median over ``infer_frames`` validation samples of one sample's forward pass,
  each sample's time the best of ``REPEATS`` passes (the shared machine's load spikes inflate
  single passes by up to ~2x); batch 1, no grad, 1 torch thread, eval mode, after 2 warm-up
  passes, data loading excluded; what one sample is depends on the stage,
  ``bench.STAGE_METRICS[stage]["sample"]``;
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

from renderworld.bench.sweep import KNOBS, format_value
from renderworld.training.api import evaluate, train
from renderworld.training.checkpoint import load_checkpoint
from renderworld.training.registry import get_stage

__all__ = ["run", "knob_value", "time_inference", "WARMUP", "REPEATS"]

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
    return format_value(value)


def _forward_fn(stage_name: str, stage: Any, model: torch.nn.Module, cfg: Any):
    """The stage's inference on one batch (see ``STAGE_METRICS[...]["sample"]``)."""
    if stage_name == "img2occ":
        return lambda b: model.readout(model(b, render=False))
    if stage_name == "tokenizer":
        return lambda b: model.decode(model.encode(b["occ"]))
    if stage_name == "world_model":
        from renderworld.tokenizer import Tokens

        tok, h, f = stage.tokenizer, int(cfg.stage.history), int(cfg.stage.future)

        def forecast(b):
            occ = b["occ"][:, :h]
            codes = tok.encode(occ.flatten(0, 1)).indices
            codes = codes.view(occ.shape[0], h, *codes.shape[1:]).long()
            disp = b["ego_displacements"].float()[:, : h - 1]
            ro = model.rollout(codes, disp, b["command"].long(), steps=f)
            names, sizes = tok.cfg.codebook_names, tok.cfg.codebook_sizes
            return [tok.decode(Tokens(ro.tokens[:, k], sizes, names)) for k in range(f)]

        return forecast
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
    model = stage.build_model(cfg)
    model.load_state_dict(load_checkpoint(ckpt_path, expected_stage=name)["model"], strict=True)
    model.eval()
    _, val = stage.build_datasets(cfg)
    n = len(val)
    idx = sorted({round(i * (n - 1) / max(frames - 1, 1)) for i in range(frames)})
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


def run(spec: dict[str, Any]) -> dict[str, Any]:
    """Train, evaluate and time one point; write and return ``result.json``."""
    torch.set_num_threads(1)
    point_dir = Path(spec["point_dir"])
    run_dir, eval_dir = point_dir / "train", point_dir / "eval"
    exp = f"experiment={spec['experiment']}"
    with initialize_config_dir(config_dir=spec["config_dir"], version_base="1.3"):
        tcfg = compose("train", overrides=[exp, *spec["overrides"], f"run_dir={run_dir}"])
        last = run_dir / "checkpoints" / "last.pt"
        ecfg = compose(
            "eval",
            overrides=[exp, *spec["eval_overrides"], f"ckpt={last}", f"run_dir={eval_dir}"],
        )
    resolved = OmegaConf.create(OmegaConf.to_container(tcfg, resolve=False))
    resolved.run_dir = str(run_dir)
    resolved = OmegaConf.create(OmegaConf.to_container(resolved, resolve=True))
    t0 = time.perf_counter()
    train(tcfg)
    train_wall = time.perf_counter() - t0
    ck = load_checkpoint(last, expected_stage=str(resolved.stage.name))
    t0 = time.perf_counter()
    metrics = evaluate(ecfg)
    eval_s = time.perf_counter() - t0
    infer_ms, params = time_inference(resolved, last, int(spec["infer_frames"]))
    result = {
        "stage": spec["stage"],
        "knob": spec["knob"],
        "value": spec["value"],
        "knob_value": knob_value(resolved, spec["stage"], spec["knob"]),
        "knob_values": {k: knob_value(resolved, spec["stage"], k) for k in KNOBS[spec["stage"]]},
        "experiment": spec["experiment"],
        "grid": str(resolved.grid.name),
        "steps": int(ck["step"]),
        "max_steps": int(resolved.trainer.max_steps),
        "max_minutes": resolved.trainer.max_minutes,
        "train_s": float(ck.get("elapsed_s", float("nan"))),
        "train_wall_s": train_wall,
        "eval_s": eval_s,
        "infer_ms": infer_ms,
        "infer_frames": int(spec["infer_frames"]),
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "params": int(params),
        "metrics": {k: float(v) for k, v in metrics.items()},
        "torch_threads": torch.get_num_threads(),
    }
    (point_dir / "result.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def main(argv: list[str]) -> None:
    if len(argv) != 2:
        raise SystemExit("usage: python -m renderworld.bench.point <spec.json>")
    run(json.loads(Path(argv[1]).read_text()))


if __name__ == "__main__":
    main(sys.argv)
