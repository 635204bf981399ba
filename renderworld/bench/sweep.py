"""Accuracy-vs-time sweep (``tools/bench.py``): expand a preset into points and run them.

A point is ``(stage, knob, value)``: the stage's mini experiment (``configs/experiment/``) with
the preset's budget (the same ``trainer.max_steps`` / ``trainer.max_minutes`` for every point of
a stage) and ONE knob changed from the stage default; the point ``knob = "default"`` changes
nothing and is the reference of every ratio. Each point runs in its own subprocess
(``python -m renderworld.bench.point``: train, evaluate, time inference, report its own
peak RSS), one at a time, and leaves ``<out>/points/<id>/result.json``. A point whose
``result.json`` carries the same fingerprint (stage, experiment, every override, the budget,
the data root and the upstream checkpoint's size and mtime) is reused unless ``overwrite``;
the package's code is not fingerprinted (after changing a model, re-measure with ``overwrite``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    "KNOBS",
    "STAGE_METRICS",
    "Knob",
    "BenchPoint",
    "expand_points",
    "point_fingerprint",
    "run_point",
    "run_sweep",
]


@dataclass(frozen=True)
class Knob:
    """A swept setting: the Hydra key it overrides and how a value is written there."""

    key: str
    kind: str  # "name" (a config-group option), "bool", "int", "float", "size" ([h, w])
    what: str


#: Knobs per stage (name -> Knob). A preset naming another knob is an error.
KNOBS: dict[str, dict[str, Knob]] = {
    "img2occ": {
        "grid": Knob("grid", "name", "voxel grid (Occ3D range)"),
        "input_size": Knob("stage.input_size", "size", "network input [H, W] of the 6 images"),
        "render_size": Knob("stage.render_size", "size", "rendered / label maps [H, W]"),
        "views_per_step": Knob("stage.model.views_per_step", "int", "cameras rendered per step"),
        "prune_opacity": Knob(
            "stage.model.prune_opacity", "float", "skip Gaussians below this opacity (0: off)"
        ),
        "fine_semantics": Knob(
            "stage.model.fine_semantics", "bool", "stride-2 per-pixel class head (on/off)"
        ),
        "feature_stride": Knob("stage.model.feature_stride", "int", "lifted feature stride"),
        "backproject_weight": Knob(
            "stage.model.backproject_weight", "float", "back-projected voxel targets (0: off)"
        ),
    },
    "tokenizer": {
        "latent_size": Knob("stage.model.latent_shape", "size", "token grid [h, w]"),
        "latent_channels": Knob("stage.model.latent_channels", "int", "latent channels"),
        "codebook_size": Knob("stage.model.codebook_size", "int", "codebook entries K"),
    },
    "world_model": {
        "history": Knob("stage.history", "int", "input frames (0.5 s apart)"),
    },
}

#: Per stage: (primary metric, higher is better), (secondary metric, higher is better), and
#: what one inference sample is.
STAGE_METRICS: dict[str, dict[str, Any]] = {
    "img2occ": {
        "metric": ("val/cam/miou", True, "mIoU, camera mask (%)"),
        "metric2": ("val/cam/iou", True, "IoU, camera mask (%)"),
        "sample": "one 6-camera keyframe -> occupancy (forward + readout)",
    },
    "tokenizer": {
        "metric": ("val/miou", True, "recon. mIoU (%)"),
        "metric2": ("val/iou", True, "recon. IoU (%)"),
        "sample": "one occupancy frame -> codes -> occupancy (encode + decode)",
    },
    "world_model": {
        "metric": ("val/model/miou_avg", True, "forecast mIoU, mean 1-3 s (%)"),
        "metric2": ("val/model/l2_at_horizon_3s", False, "L2 @ 3 s (m)"),
        "sample": "one window: encode the history, roll out and decode 3 s (6 frames)",
    },
}
DEFAULT = "default"


@dataclass(frozen=True)
class BenchPoint:
    """One measurement: the stage's experiment with one knob changed.

    Attributes:
        stage: ``img2occ`` | ``tokenizer`` | ``world_model``.
        knob: a key of ``KNOBS[stage]`` or ``"default"``.
        value: the knob's value as written in the preset (None for the default point).
        experiment: Hydra experiment (``configs/experiment/<name>.yaml``).
        overrides: every Hydra override of the training command, in order (common, budget, knob).
        eval_overrides: the evaluation command's overrides (all but the budget).
        upstream: files the point reads besides the data (fingerprinted by size and mtime).
    """

    stage: str
    knob: str
    value: Any
    experiment: str
    overrides: tuple[str, ...]
    eval_overrides: tuple[str, ...]
    upstream: tuple[str, ...] = field(default=())

    @property
    def point_id(self) -> str:
        """Folder-safe id, e.g. ``img2occ__views_per_step-1``."""
        if self.knob == DEFAULT:
            return f"{self.stage}__default"
        return f"{self.stage}__{self.knob}-{format_value(self.value)}"


def format_value(value: Any) -> str:
    """A knob value as text: ``[96, 176]`` -> ``96x176``, ``0.0`` -> ``0``."""
    if isinstance(value, (list, tuple)):
        return "x".join(format_value(v) for v in value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def _override(knob: Knob, name: str, value: Any, where: str) -> str:
    bad = TypeError(f"{where}: expected {_KIND_TEXT[knob.kind]} for knob {name!r}, got {value!r}")
    if knob.kind == "name":
        if not isinstance(value, str) or not value:
            raise bad
        return f"{knob.key}={value}"
    if knob.kind == "bool":
        if not isinstance(value, bool):
            raise bad
        return f"{knob.key}={str(value).lower()}"
    if knob.kind == "int":
        if not isinstance(value, int) or isinstance(value, bool):
            raise bad
        return f"{knob.key}={value}"
    if knob.kind == "float":
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise bad
        return f"{knob.key}={float(value)!r}"
    ok = (
        isinstance(value, (list, tuple))
        and len(value) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value)
    )
    if not ok:
        raise bad
    return f"{knob.key}=[{int(value[0])},{int(value[1])}]"


_KIND_TEXT = {
    "name": "a config option name (str)",
    "bool": "true or false",
    "int": "an int",
    "float": "a number",
    "size": "a pair of positive ints [h, w]",
}
_STAGE_KEYS = {"experiment", "budget", "overrides", "knobs"}


def expand_points(
    preset: Mapping[str, Any],
    common: Sequence[str] = (),
    upstream: Mapping[str, Sequence[str]] | None = None,
) -> list[BenchPoint]:
    """The points of a preset: per stage, the default point then each knob value.

    Args:
        preset: ``{"stages": {stage: {"experiment": str, "budget": {"max_steps": int,
            "max_minutes": float | None}, "overrides": [str], "knobs": {knob: [values]}}}}``
            (``configs/bench/<preset>.yaml``; a stage left out is not run). ``overrides`` go
            to the training and the evaluation command of every point of the stage.
        common: overrides for every command of every stage (e.g. the data root).
        upstream: per stage, extra overrides of its train and eval commands naming files it
            reads (e.g. ``stage.tokenizer_ckpt=PATH``); the paths are fingerprinted.

    Returns:
        Points in run order.

    Raises:
        ValueError: an unknown stage, stage key or knob (the message names the key), a missing
            or bad budget, an empty preset.
        TypeError: a knob value of the wrong type.
    """
    if not isinstance(preset, Mapping):
        raise TypeError(f"preset: expected a mapping, got {type(preset).__name__}")
    stages = preset.get("stages")
    if not isinstance(stages, Mapping) or not stages:
        raise ValueError(f"bench.stages: expected a non-empty mapping of stages, got {stages!r}")
    upstream = dict(upstream or {})
    points: list[BenchPoint] = []
    for stage, spec in stages.items():
        where = f"bench.stages.{stage}"
        if stage not in KNOBS:
            raise ValueError(f"{where}: unknown stage {stage!r}; expected one of {sorted(KNOBS)}")
        if not isinstance(spec, Mapping):
            raise TypeError(f"{where}: expected a mapping, got {type(spec).__name__}")
        extra = set(spec) - _STAGE_KEYS
        if extra:
            raise ValueError(
                f"{where}.{sorted(extra)[0]}: unknown key; expected {sorted(_STAGE_KEYS)}"
            )
        experiment = spec.get("experiment")
        if not isinstance(experiment, str) or not experiment:
            raise ValueError(f"{where}.experiment: expected an experiment name, got {experiment!r}")
        budget = _budget(spec.get("budget"), f"{where}.budget")
        shared = tuple(str(o) for o in (spec.get("overrides") or ()))
        ups = tuple(str(o) for o in upstream.get(stage, ()))
        files = tuple(o.split("=", 1)[1] for o in ups)
        base = (*common, *ups, *shared, *budget)
        evals = (*common, *ups, *shared)  # eval builds the same model and data
        points.append(BenchPoint(stage, DEFAULT, None, experiment, base, evals, files))
        knobs = spec.get("knobs") or {}
        if not isinstance(knobs, Mapping):
            raise TypeError(f"{where}.knobs: expected a mapping, got {type(knobs).__name__}")
        for name, values in knobs.items():
            if name not in KNOBS[stage]:
                raise ValueError(
                    f"{where}.knobs.{name}: unknown knob for stage {stage!r}; expected one of "
                    f"{sorted(KNOBS[stage])}"
                )
            if not isinstance(values, Sequence) or isinstance(values, str) or not values:
                raise ValueError(f"{where}.knobs.{name}: expected a non-empty list of values")
            knob = KNOBS[stage][name]
            for value in values:
                ov = _override(knob, name, value, f"{where}.knobs.{name}")
                # Last, so it wins over the shared overrides; eval builds the same model.
                points.append(
                    BenchPoint(stage, name, value, experiment, (*base, ov), (*evals, ov), files)
                )
    ids = [p.point_id for p in points]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise ValueError(f"bench.stages: the point {dup[0]!r} is listed twice")
    return points


def _budget(budget: Any, where: str) -> tuple[str, ...]:
    if not isinstance(budget, Mapping):
        raise ValueError(
            f"{where}: expected {{max_steps: int, max_minutes: number}}, got {budget!r}"
        )
    extra = set(budget) - {"max_steps", "max_minutes"}
    if extra:
        raise ValueError(
            f"{where}.{sorted(extra)[0]}: unknown key; expected max_steps, max_minutes"
        )
    steps, minutes = budget.get("max_steps"), budget.get("max_minutes")
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise ValueError(f"{where}.max_steps: expected an int >= 1, got {steps!r}")
    if minutes is not None and (
        not isinstance(minutes, (int, float)) or isinstance(minutes, bool) or minutes <= 0
    ):
        raise ValueError(f"{where}.max_minutes: expected a number > 0 or null, got {minutes!r}")
    cap = "null" if minutes is None else repr(float(minutes))
    out = [f"trainer.max_steps={steps}", f"trainer.max_minutes={cap}"]
    # Validate and checkpoint once, at the end: the budget buys training steps only.
    out += ["trainer.val_every=0", "trainer.ckpt_every=0", "trainer.progress_bar=false"]
    out += ["trainer.tensorboard=false", "trainer.num_threads=1"]
    return tuple(out)


def _point_fields(point: BenchPoint, infer_frames: int) -> dict[str, Any]:
    """What defines a point's measurement: written into its spec and hashed into its fingerprint."""
    return {
        "stage": point.stage,
        "knob": point.knob,
        "value": point.value,
        "experiment": point.experiment,
        "overrides": list(point.overrides),
        "eval_overrides": list(point.eval_overrides),
        "infer_frames": int(infer_frames),
    }


def point_fingerprint(point: BenchPoint, infer_frames: int) -> str:
    """sha256 (16 hex) of everything that determines a point's result.

    Stage, knob, experiment, every override (so the budget and data root too), the inference
    sample count and the size + mtime of each upstream file.
    """
    ups = []
    for path in point.upstream:
        p = Path(path)
        st = p.stat() if p.is_file() else None
        ups.append([str(p.resolve()), st.st_size if st else None, st.st_mtime_ns if st else None])
    blob = json.dumps(
        {**_point_fields(point, infer_frames), "upstream": ups, "version": 1}, sort_keys=True
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def run_point(
    point: BenchPoint, point_dir: Path, infer_frames: int, repo: Path, timeout_s: float | None
) -> dict[str, Any]:
    """Run one point in a fresh subprocess (1 torch thread) and return its ``result.json``.

    The previous contents of ``point_dir`` are removed first (an interrupted point restarts).

    Raises:
        RuntimeError: the subprocess failed or wrote no result; the message ends with its log.
    """
    if point_dir.exists():
        shutil.rmtree(point_dir)
    point_dir.mkdir(parents=True)
    spec = {
        **_point_fields(point, infer_frames),
        "config_dir": str((repo / "configs").resolve()),
        "point_dir": str(point_dir.resolve()),
    }
    (point_dir / "spec.json").write_text(json.dumps(spec, indent=2) + "\n")
    env = dict(os.environ)
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(repo), env.get("PYTHONPATH")]))
    cmd = [sys.executable, "-m", "renderworld.bench.point", str(point_dir / "spec.json")]
    log = point_dir / "log.txt"
    with log.open("w") as fh:
        try:
            proc = subprocess.run(
                cmd, cwd=repo, stdout=fh, stderr=subprocess.STDOUT, env=env, timeout=timeout_s
            )
            rc = proc.returncode
        except subprocess.TimeoutExpired:
            rc = "timeout"
    result = point_dir / "result.json"
    if rc != 0 or not result.is_file():
        tail = "\n".join(log.read_text(errors="replace").splitlines()[-25:])
        raise RuntimeError(f"bench point {point.point_id} failed (exit {rc}); log {log}:\n{tail}")
    return json.loads(result.read_text())


def run_sweep(
    points: Sequence[BenchPoint],
    out: Path,
    infer_frames: int = 5,
    overwrite: bool = False,
    repo: Path | None = None,
    runner: Callable[..., dict[str, Any]] = run_point,
    timeout_s: float | None = None,
    echo: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
    """Run (or reuse) every point, one at a time, and return their results in order.

    Args:
        points: from :func:`expand_points`.
        out: output folder; point ``i`` runs in ``<out>/points/<point_id>/``.
        infer_frames: validation samples timed per point (median reported).
        overwrite: re-run points whose stored result has the same fingerprint.
        repo: repository root (``configs/`` and the package); default: this checkout.
        runner: the function running one point (``run_point``; tests pass a fake).
        timeout_s: per-point wall-clock cap (None: none).
        echo: progress output.

    Returns:
        One dict per point: the point's ``result.json`` plus ``fingerprint``, ``reused``.
    """
    if not isinstance(infer_frames, int) or isinstance(infer_frames, bool) or infer_frames < 1:
        raise ValueError(f"infer_frames: expected an int >= 1, got {infer_frames!r}")
    repo = Path(repo) if repo is not None else Path(__file__).resolve().parents[2]
    out = Path(out)
    results = []
    t_sweep = time.perf_counter()
    for i, point in enumerate(points, 1):
        fp = point_fingerprint(point, infer_frames)
        pdir = out / "points" / point.point_id
        stored = pdir / "result.json"
        head = f"[{i}/{len(points)}] {point.point_id}"
        if not overwrite and stored.is_file():
            res = json.loads(stored.read_text())
            if res.get("fingerprint") == fp:
                echo(f"{head}: reused ({_summary(res)})")
                results.append({**res, "reused": True})
                continue
        echo(f"{head}: running ...")
        t0 = time.perf_counter()
        res = runner(point, pdir, infer_frames, repo, timeout_s)
        res = {**res, "fingerprint": fp, "point_wall_s": time.perf_counter() - t0}
        stored.write_text(json.dumps(res, indent=2) + "\n")
        echo(f"{head}: {res['point_wall_s']:.0f} s ({_summary(res)})")
        results.append({**res, "reused": False})
    echo(f"sweep: {len(points)} points in {time.perf_counter() - t_sweep:.0f} s")
    return results


def _summary(res: Mapping[str, Any]) -> str:
    name = STAGE_METRICS[res["stage"]]["metric"][0]
    m = res.get("metrics", {}).get(name)
    mtxt = f"{name}={100 * m:.2f}" if isinstance(m, (int, float)) else f"{name}=?"
    return (
        f"{mtxt}, train {res.get('train_s', float('nan')):.0f} s, "
        f"infer {res.get('infer_ms', float('nan')):.1f} ms, "
        f"peak {res.get('peak_rss_mib', float('nan')):.0f} MiB"
    )
