"""``tools/bench.py``: a ``configs/bench.yaml`` config -> sweep -> tables and Pareto plots."""

from __future__ import annotations

import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from renderworld.bench.estimate import estimate_text
from renderworld.bench.plots import plot_pareto
from renderworld.bench.report import result_rows, write_csv, write_markdown
from renderworld.bench.run import run_sweep
from renderworld.bench.sweep import expand_points

__all__ = ["run_bench", "bench_points", "resolve_jobs", "write_outputs"]

_TOP_KEYS = {"bench", "out", "data_root", "tokenizer_ckpt", "world_model_ckpt", "scenario_library",
             "heldout_root", "infer_frames", "overwrite", "point_timeout_s", "jobs"}  # fmt: skip


def bench_points(cfg: Any) -> list:
    """The points of a composed ``configs/bench.yaml`` config (validated, nothing run).

    The world-model points train on the main job's recipe: with the scenario library
    (``scenario_library``) when that folder exists (else without it, and a
    ``scenario_library`` knob is an error), and are also scored on ``heldout_root`` when that
    folder exists. The planner points read ``tokenizer_ckpt`` and ``world_model_ckpt``.

    Raises:
        ValueError: an unknown top-level key, a preset without ``name`` / ``stages``, a missing
            data root, tokenizer or world-model checkpoint (each message names the key).
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
    unknown = set(preset) - {"name", "stages", "ranking"}
    if unknown:
        raise ValueError(
            f"bench.{sorted(unknown)[0]}: unknown preset key; expected name, stages, ranking"
        )
    if not isinstance(preset.get("ranking", False), bool):
        raise ValueError(f"bench.ranking: expected true or false, got {preset['ranking']!r}")
    if not preset.get("ranking", False):  # the stages' ranking points are opt-in
        preset["stages"] = {
            k: ({n: v for n, v in s.items() if n != "ranking"} if isinstance(s, dict) else s)
            for k, s in (preset.get("stages") or {}).items()
        }
    data = Path(str(cfg.data_root)).resolve()
    if not (data / "renderworld_infos").is_dir():
        raise ValueError(
            f"data_root: {str(data)!r} has no renderworld_infos/ (run make demo, or "
            "tools/make_fixtures.py + tools/create_data.py, or pass data_root=DIR)"
        )
    stages = preset.get("stages") or {}
    upstream: dict[str, list[str]] = {}
    library = None
    if "world_model" in stages or "planner" in stages:
        tok = _required_file(cfg, "tokenizer_ckpt", "a coarse-grid tokenizer checkpoint")
        upstream["world_model"] = [f"stage.tokenizer_ckpt={tok}"]
        upstream["planner"] = [f"tokenizer_ckpt={tok}"]
    if "world_model" in stages:
        library = _folder(cfg, "scenario_library")
        if library is not None:
            upstream["world_model"].append(f"stage.extra_train_roots=[{library}]")
        heldout = _folder(cfg, "heldout_root")
        if heldout is not None:
            upstream["world_model"].append(f"bench.heldout_root={heldout}")
    if "planner" in stages:
        wm = _required_file(cfg, "world_model_ckpt", "the main job's world-model checkpoint")
        upstream["planner"].append(f"world_model_ckpt={wm}")
    return expand_points(
        preset,
        common=[f"dataset.data_root={data}"],
        upstream=upstream,
        library=str(library) if library is not None else None,
    )


def resolve_jobs(jobs: Any) -> int:
    """How many training points run at once: ``jobs``, or for None both cores of the 2-core CPU
    the presets are sized for (1 on a 1-core machine).

    Raises:
        ValueError: ``jobs`` is not None or an int >= 1 (the message names ``jobs``).
    """
    if jobs is None:
        return min(2, os.cpu_count() or 1)
    if not isinstance(jobs, int) or isinstance(jobs, bool) or jobs < 1:
        raise ValueError(f"jobs: expected an int >= 1 or null (points run at once), got {jobs!r}")
    return jobs


def _required_file(cfg: Any, key: str, what: str) -> Path:
    path = Path(str(cfg.get(key))).resolve()
    if not path.is_file():
        raise ValueError(
            f"{key}: {str(path)!r} does not exist; the sweep needs {what} (make demo writes "
            f"one), pass {key}=PATH"
        )
    return path


def _folder(cfg: Any, key: str) -> Path | None:
    """``cfg[key]`` resolved when it names an existing folder, else None."""
    value = cfg.get(key)
    if value is None or not Path(str(value)).is_dir():
        return None
    return Path(str(value)).resolve()


def run_bench(cfg: Any, repo: Path) -> dict[str, Path]:
    """Run (or resume) the sweep of ``cfg`` and write its outputs; return their paths."""
    points = bench_points(cfg)
    jobs = resolve_jobs(cfg.get("jobs"))
    out = Path(str(cfg.out)).resolve()
    name = str(cfg.bench.name)
    print(f"bench {name!r}: {len(points)} points, outputs in {out}", flush=True)
    print(estimate_text(points, out, int(cfg.infer_frames), jobs), flush=True)
    notes = []
    if not cfg.bench.get("ranking", False):
        staged = [k for k, s in cfg.bench.stages.items() if s.get("ranking") is not None]
        if staged:
            notes.append(
                f"Ranking check not run in this invocation ({', '.join(staged)} have ranking "
                f"points at the main job's step count): add them with `python tools/bench.py "
                f"bench={name} bench.ranking=true` (same output folder; measured points are "
                "reused)."
            )
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
        jobs=jobs,
    )
    wall = time.perf_counter() - t0
    measured = sum(float(r.get("point_wall_s", 0.0)) for r in results)
    title = (
        f"Bench `{name}`: accuracy vs cost ({len(points)} points; measuring them took "
        f"{measured:.0f} s, this invocation {wall:.0f} s with {jobs} point(s) at a time)"
    )
    paths = write_outputs(results, out, title, notes)
    print(paths["md"].read_text(), flush=True)
    print("wrote " + ", ".join(str(p) for p in paths.values()), flush=True)
    return paths


def write_outputs(
    results: Sequence[Mapping[str, Any]], out: Path, title: str = "", notes: Sequence[str] = ()
) -> dict[str, Path]:
    """``results.csv``, ``results.md`` and one ``pareto_<stage>.png`` per stage under ``out``."""
    rows = result_rows(results)
    out = Path(out)
    paths = {"csv": write_csv(rows, out / "results.csv")}
    paths["md"] = write_markdown(rows, out / "results.md", title, notes)
    for stage in dict.fromkeys(r["stage"] for r in rows):
        png = plot_pareto(rows, stage, out / f"pareto_{stage}.png")
        if png is not None:
            paths[f"pareto_{stage}"] = png
    return paths
