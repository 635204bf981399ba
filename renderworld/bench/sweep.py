"""Accuracy-vs-time sweep (``tools/bench.py``): expand a preset into points.

A point is ``(stage, knob, value, seed)``: the stage's mini experiment (``configs/experiment/``)
with the preset's budget (the same ``trainer.max_steps`` / ``trainer.max_minutes`` for every
point of a stage), ONE knob changed from the stage default and the training seed; the point
``knob = "default"`` changes nothing and is the reference of every comparison. Every point runs
once per seed of its stage (``seeds``, two by default: the table shows their mean and spread).
A stage's ``ranking`` section adds the default and a few knob points again at the main job's
step count, so that the report can check whether the order at the budget is the order there.
The ``planner`` stage trains nothing: its points time the main job's planner
(``renderworld.bench.planner_latency``). ``renderworld.bench.run`` runs each point in its own
subprocess and leaves ``<out>/points/<id>/result.json``. A point whose ``result.json`` carries
the same fingerprint (stage, experiment, every override, the budget, the seed, the data root and
the upstream files' size and mtime) is reused unless ``overwrite``; the package's code is not
fingerprinted (after changing a model, re-measure with ``overwrite``).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from renderworld.bench.knobs import DEFAULT, KNOBS, format_value, knob_override

__all__ = [
    "BenchPoint",
    "expand_points",
    "point_fingerprint",
    "point_spec",
    "RANKING",
]

#: ``BenchPoint.phase`` of the points run again at the main job's step count.
RANKING = "ranking"


@dataclass(frozen=True)
class BenchPoint:
    """One measurement: the stage's experiment with one knob changed, one seed.

    Attributes:
        stage: ``img2occ`` | ``tokenizer`` | ``world_model`` | ``planner``.
        knob: a key of ``KNOBS[stage]`` or ``"default"``.
        value: the knob's value as written in the preset (None for the default point).
        experiment: Hydra experiment (``configs/experiment/<name>.yaml``; "" for the planner).
        overrides: every override of the training command (planner: of its options), in order
            (common, upstream, stage, budget, seed, knob).
        eval_overrides: the evaluation command's overrides (all but the budget and the seed).
        upstream: files the point reads besides the data (fingerprinted by size and mtime).
        seed: the training seed (``seed=`` override).
        phase: ``""`` (the preset's budget) or ``"ranking"`` (the ranking budget).
        claimed: whether the stage's budget is one whose ranking the preset claims is stable.
    """

    stage: str
    knob: str
    value: Any
    experiment: str
    overrides: tuple[str, ...]
    eval_overrides: tuple[str, ...]
    upstream: tuple[str, ...] = field(default=())
    seed: int = 0
    phase: str = ""
    claimed: bool = True

    @property
    def config_id(self) -> str:
        """The point without its seed, e.g. ``img2occ__views_per_step-1``."""
        if self.knob == DEFAULT:
            return f"{self.stage}__default"
        return f"{self.stage}__{self.knob}-{format_value(self.value)}"

    @property
    def point_id(self) -> str:
        """Folder-safe id, e.g. ``img2occ__views_per_step-1__s0`` (``__ranking`` appended for
        a ranking point)."""
        return f"{self.config_id}__s{self.seed}" + (f"__{self.phase}" if self.phase else "")


_STAGE_KEYS = {"experiment", "budget", "overrides", "knobs", "seeds", "ranking", "claim_ranking"}
_PLANNER_KEYS = {"knobs", "windows", "seeds"}


def _seeds(value: Any, where: str) -> tuple[int, ...]:
    if value is None:
        return (0, 1)
    ok = isinstance(value, Sequence) and not isinstance(value, str) and value
    if not ok or not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        raise ValueError(f"{where}: expected a non-empty list of int seeds, got {value!r}")
    if len(set(value)) != len(value):
        raise ValueError(f"{where}: a seed is listed twice in {value!r}")
    return tuple(value)


def _knob_points(stage: str, knobs: Any, where: str, library: str | None):
    """(knob, value, override) of each knob value of a stage, in preset order."""
    if not isinstance(knobs, Mapping):
        raise TypeError(f"{where}.knobs: expected a mapping, got {type(knobs).__name__}")
    out = []
    for name, values in knobs.items():
        if name not in KNOBS[stage]:
            raise ValueError(
                f"{where}.knobs.{name}: unknown knob for stage {stage!r}; expected one of "
                f"{sorted(KNOBS[stage])}"
            )
        if not isinstance(values, Sequence) or isinstance(values, str) or not values:
            raise ValueError(f"{where}.knobs.{name}: expected a non-empty list of values")
        for value in values:
            ov = knob_override(KNOBS[stage][name], name, value, f"{where}.knobs.{name}", library)
            out.append((name, value, ov))
    return out


def expand_points(
    preset: Mapping[str, Any],
    common: Sequence[str] = (),
    upstream: Mapping[str, Sequence[str]] | None = None,
    library: str | None = None,
) -> list[BenchPoint]:
    """The points of a preset: per stage and seed, the default point then each knob value;
    then the stage's ranking points.

    Args:
        preset: ``{"stages": {stage: spec}}`` (``configs/bench/<preset>.yaml``; a stage left
            out is not run). A training stage's spec: ``experiment`` (str), ``budget``
            (``{"max_steps": int, "max_minutes": float | None}``), ``seeds`` (list of ints,
            default ``[0, 1]``), ``overrides`` (to the training and the evaluation command of
            every point of the stage), ``knobs`` (``{knob: [values]}``), ``claim_ranking``
            (bool, default true: false marks a budget below the stable one) and ``ranking``
            (``{"budget": {...}, "points": ["default", "<knob>-<value>", ...]}``: those points
            again at that budget, same seeds). The planner's spec: ``windows`` (validation
            windows timed, default 7), ``seeds`` (default ``[0]``) and ``knobs``.
        common: overrides for every command of every stage (e.g. the data root).
        upstream: per stage, extra overrides naming files it reads (e.g.
            ``stage.tokenizer_ckpt=PATH``); the paths are fingerprinted.
        library: the scenario library's folder for ``scenario_library`` knobs (None: none).

    Returns:
        Points in run order.

    Raises:
        ValueError: an unknown stage, stage key or knob (the message names the key), a missing
            or bad budget, bad seeds, a ranking point that is not a point of the stage, an
            empty preset.
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
        allowed = _PLANNER_KEYS if stage == "planner" else _STAGE_KEYS
        extra = set(spec) - allowed
        if extra:
            raise ValueError(f"{where}.{sorted(extra)[0]}: unknown key; expected {sorted(allowed)}")
        ups = tuple(str(o) for o in upstream.get(stage, ()))
        files = tuple(o.split("=", 1)[1] for o in ups)
        knobs = _knob_points(stage, spec.get("knobs") or {}, where, library)
        if stage == "planner":
            seeds = _seeds(spec.get("seeds", [0]), f"{where}.seeds")
            windows = spec.get("windows", 7)
            if not isinstance(windows, int) or isinstance(windows, bool) or windows < 1:
                raise ValueError(f"{where}.windows: expected an int >= 1, got {windows!r}")
            base = (*common, *ups, f"windows={windows}")
            for seed in seeds:
                points.append(BenchPoint(stage, DEFAULT, None, "", base, base, files, seed))
                points += [
                    BenchPoint(stage, k, v, "", (*base, ov), (*base, ov), files, seed)
                    for k, v, ov in knobs
                ]
            continue
        experiment = spec.get("experiment")
        if not isinstance(experiment, str) or not experiment:
            raise ValueError(f"{where}.experiment: expected an experiment name, got {experiment!r}")
        seeds = _seeds(spec.get("seeds"), f"{where}.seeds")
        claimed = spec.get("claim_ranking", True)
        if not isinstance(claimed, bool):
            raise ValueError(f"{where}.claim_ranking: expected true or false, got {claimed!r}")
        shared = tuple(str(o) for o in (spec.get("overrides") or ()))
        evals = (*common, *ups, *shared)  # eval builds the same model and data

        make = partial(_train_point, stage, experiment, evals, files, claimed)
        budget = _budget(spec.get("budget"), f"{where}.budget")
        all_knobs = [(DEFAULT, None, None), *knobs]
        for seed in seeds:
            points += [make(k, v, ov, seed, budget, "") for k, v, ov in all_knobs]
        ranking = spec.get("ranking")
        if ranking is not None:
            points += _ranking_points(ranking, f"{where}.ranking", all_knobs, seeds, make, stage)
    ids = [p.point_id for p in points]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise ValueError(f"bench.stages: the point {dup[0]!r} is listed twice")
    return points


def _train_point(stage, experiment, evals, files, claimed, knob, value, ov, seed, budget, phase):
    """A training stage's point; the knob's override last, so it wins over the shared ones."""
    knob_ov = (ov,) if ov else ()
    train = (*evals, *budget, f"seed={seed}", *knob_ov)
    return BenchPoint(stage, knob, value, experiment, train, (*evals, *knob_ov), files, seed,
                      phase, claimed)  # fmt: skip


def _ranking_points(ranking, where, all_knobs, seeds, make, stage) -> list[BenchPoint]:
    if not isinstance(ranking, Mapping) or set(ranking) != {"budget", "points"}:
        raise ValueError(f"{where}: expected {{budget: {{...}}, points: [...]}}, got {ranking!r}")
    budget = _budget(ranking["budget"], f"{where}.budget")
    by_id = {}
    for k, v, ov in all_knobs:
        name = DEFAULT if k == DEFAULT else f"{k}-{format_value(v)}"
        by_id[name] = (k, v, ov)
    wanted = ranking["points"]
    if not isinstance(wanted, Sequence) or isinstance(wanted, str) or len(wanted) < 3:
        raise ValueError(f"{where}.points: expected at least 3 point names, got {wanted!r}")
    for name in wanted:
        if name not in by_id:
            raise ValueError(
                f"{where}.points: {name!r} is not a point of stage {stage!r}; expected one of "
                f"{sorted(by_id)}"
            )
    return [make(*by_id[name], seed, budget, RANKING) for seed in seeds for name in wanted]


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
        "seed": point.seed,
        "phase": point.phase,
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
        {**_point_fields(point, infer_frames), "upstream": ups, "version": 2}, sort_keys=True
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def point_spec(point: BenchPoint, point_dir: Path, infer_frames: int, repo: Path) -> dict[str, Any]:
    """The ``spec.json`` of a point: what ``python -m renderworld.bench.point`` reads."""
    return {
        **_point_fields(point, infer_frames),
        "config_dir": str((Path(repo) / "configs").resolve()),
        "point_dir": str(Path(point_dir).resolve()),
    }
