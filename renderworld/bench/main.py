"""``tools/bench.py``: a ``configs/bench.yaml`` config -> sweep -> tables and Pareto plots."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from renderworld.bench.report import write_outputs
from renderworld.bench.sweep import expand_points, run_sweep

__all__ = ["run_bench", "bench_points"]

_TOP_KEYS = {"bench", "out", "data_root", "tokenizer_ckpt", "infer_frames", "overwrite",
             "point_timeout_s"}  # fmt: skip


def bench_points(cfg: Any) -> list:
    """The points of a composed ``configs/bench.yaml`` config (validated, nothing run).

    Raises:
        ValueError: an unknown top-level key, a preset without ``name`` / ``stages``, a missing
            data root or tokenizer checkpoint (each message names the key).
    """
    extra = set(cfg) - _TOP_KEYS
    if extra:
        raise ValueError(f"{sorted(extra)[0]}: unknown bench key; expected {sorted(_TOP_KEYS)}")
    preset = OmegaConf.to_container(cfg.bench, resolve=True) if cfg.get("bench") else None
    if not isinstance(preset, dict) or not preset.get("name"):
        raise ValueError(
            f"bench: expected a preset with `name` and `stages` (bench=quick|full, "
            f"configs/bench/), got {preset!r}"
        )
    unknown = set(preset) - {"name", "stages"}
    if unknown:
        raise ValueError(f"bench.{sorted(unknown)[0]}: unknown preset key; expected name, stages")
    data = Path(str(cfg.data_root)).resolve()
    if not (data / "renderworld_infos").is_dir():
        raise ValueError(
            f"data_root: {str(data)!r} has no renderworld_infos/ (run make demo, or "
            "tools/make_fixtures.py + tools/create_data.py, or pass data_root=DIR)"
        )
    upstream = {}
    if "world_model" in (preset.get("stages") or {}):
        tok = Path(str(cfg.tokenizer_ckpt)).resolve()
        if not tok.is_file():
            raise ValueError(
                f"tokenizer_ckpt: {str(tok)!r} does not exist; the world model points need a "
                "coarse-grid tokenizer checkpoint (make demo writes one), pass tokenizer_ckpt=PATH"
            )
        upstream["world_model"] = [f"stage.tokenizer_ckpt={tok}"]
    return expand_points(preset, common=[f"dataset.data_root={data}"], upstream=upstream)


def run_bench(cfg: Any, repo: Path) -> dict[str, Path]:
    """Run (or resume) the sweep of ``cfg`` and write its outputs; return their paths."""
    points = bench_points(cfg)
    out = Path(str(cfg.out)).resolve()
    name = str(cfg.bench.name)
    print(f"bench {name!r}: {len(points)} points, outputs in {out}", flush=True)
    t0 = time.perf_counter()
    timeout = cfg.get("point_timeout_s")
    results = run_sweep(
        points,
        out,
        infer_frames=int(cfg.infer_frames),
        overwrite=bool(cfg.overwrite),
        repo=Path(repo),
        timeout_s=float(timeout) if timeout is not None else None,
        echo=lambda s: print(s, flush=True),
    )
    wall = time.perf_counter() - t0
    measured = sum(float(r.get("point_wall_s", 0.0)) for r in results)
    title = (
        f"Bench `{name}`: accuracy vs cost ({len(points)} points; measuring them took "
        f"{measured:.0f} s, this invocation {wall:.0f} s)"
    )
    paths = write_outputs(results, out, title)
    print(paths["md"].read_text(), flush=True)
    print("wrote " + ", ".join(str(p) for p in paths.values()), flush=True)
    return paths
