"""Every kind of point of every shipped preset runs end to end, for two steps, on the tiny fixture.

A point kind is a (stage, knob) of a preset in ``configs/bench/`` (the default point is the knob
``default``). Each runs through the sweep's own path (``bench_points`` -> ``run_sweep`` ->
``python -m renderworld.bench.point``) with the preset's overrides, its value of the knob, the
step count cut to 2 and tiny models, so that a stage whose model or API changes cannot silently
break the sweep (a world-model point once stopped at ``PoseWarpWorldModel.rollout``).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from data_converters import ConvertOptions, create_data
from renderworld.bench.knobs import DEFAULT, KNOBS, STAGE_METRICS, format_value
from renderworld.bench.main import bench_points
from renderworld.bench.run import run_sweep
from renderworld.bench.sweep import BenchPoint, point_spec
from renderworld.training.api import train
from tests.training.conftest import compose_cfg

REPO = Path(__file__).resolve().parents[2]
PRESETS = ("quick", "standard", "full")
QUIET = ["trainer.progress_bar=false", "trainer.tensorboard=false"]
TINY_TOKENIZER = [
    "stage.model.latent_channels=8", "stage.model.codebook_size=32",
    "stage.model.base_channels=8", "stage.model.num_res_blocks=1", "stage.model.attention=false",
]  # fmt: skip
#: Appended to every point of a stage before its knob (the knob wins): tiny models, windows
#: that fit the fixture's 8 keyframes (history up to 6 + 2 future frames).
TINY = {
    "tokenizer": ["trainer.batch_size=2", *TINY_TOKENIZER],
    "img2occ": [
        "stage.threshold.max_samples=2",
        "stage.threshold.per_class=false",
        "stage.threshold.class_offsets=false",
        "stage.threshold.candidates=[0.5]",
        "stage.adjacent_frames=0",
        "stage.model.mirror_readout=false",
        "stage.input_size=[32,56]",
        "stage.render_size=[14,25]",
        "stage.model.depth_bins=8",
        "stage.cache_samples=false",
    ],
    "world_model": [
        "stage.history=3",
        "stage.future=2",
        "stage.model.embed_dim=16",
        "stage.model.num_heads=2",
        "stage.pose_warmup_steps=2",
        "stage.mover_fit_steps=2",
        "stage.mover_batch=8",
        "trainer.batch_size=2",
    ],  # fmt: skip
    "planner": ["windows=2", "repeats=1", "warmup=0"],
}


def _preset_specs() -> dict[str, dict]:
    return {
        p: OmegaConf.to_container(OmegaConf.load(REPO / "configs" / "bench" / f"{p}.yaml"))
        for p in PRESETS
    }


def _kinds() -> list[tuple[str, str, str]]:
    """(stage, knob, first preset naming it) of every shipped preset, the default included."""
    out: dict[tuple[str, str], str] = {}
    for preset, spec in _preset_specs().items():
        for stage, s in spec["stages"].items():
            for knob in (DEFAULT, *(s.get("knobs") or {})):
                out.setdefault((stage, knob), preset)
    return [(stage, knob, preset) for (stage, knob), preset in out.items()]


KINDS = _kinds()


def test_the_presets_cover_every_stage_and_the_asked_for_knobs():
    specs = _preset_specs()
    for preset, spec in specs.items():
        assert set(spec["stages"]) == {"img2occ", "tokenizer", "world_model", "planner"}, preset
    std = specs["standard"]["stages"]
    assert std["world_model"]["budget"]["max_steps"] >= 400
    assert {"forecaster", "scenario_library"} <= set(std["world_model"]["knobs"])
    full = specs["full"]["stages"]
    assert {"history", "steps", "width"} <= set(full["world_model"]["knobs"])
    assert {"grid", "views_per_step", "prune_opacity"} <= set(full["img2occ"]["knobs"])
    assert {"forecast", "precision", "threads", "grid"} <= set(std["planner"]["knobs"])
    for preset, spec in specs.items():
        for stage, s in spec["stages"].items():
            if stage != "planner":
                assert len(s["seeds"]) == 2, (preset, stage)
    assert all(not s.get("claim_ranking", True) for s in specs["quick"]["stages"].values()
               if "claim_ranking" in s)  # fmt: skip


@pytest.fixture(scope="module")
def bench_data(tiny_dataset, tmp_path_factory):
    """A data root (the tiny fixture with its infos), a scenario library (the same scenes), a
    tiny tokenizer and a tiny pose-warp world model trained for 2 steps."""
    base = tmp_path_factory.mktemp("bench_presets")
    infos = base / "infos"
    create_data(tiny_dataset, "v1.0-mini", out=infos, options=ConvertOptions(progress=False))
    roots = {}
    for name in ("root", "library"):
        root = base / name
        root.mkdir()
        for child in tiny_dataset.iterdir():
            if child.name != "renderworld_infos":
                (root / child.name).symlink_to(child)
        (root / "renderworld_infos").mkdir()
        (root / "renderworld_infos" / "v1.0-mini").symlink_to(infos)
        roots[name] = root
    data = ["grid=coarse", "trainer=cpu", f"dataset.data_root={roots['root']}", *QUIET,
            "trainer.max_steps=2", "trainer.val_every=0"]  # fmt: skip
    train(compose_cfg(["experiment=tokenizer_mini", *data, f"run_dir={base / 'tok'}",
                       "trainer.batch_size=2", *TINY_TOKENIZER]))  # fmt: skip
    tok = base / "tok" / "checkpoints" / "last.pt"
    train(compose_cfg(["experiment=world_model_mini", *data, f"run_dir={base / 'wm'}",
                       f"stage.tokenizer_ckpt={tok}", *TINY["world_model"]]))  # fmt: skip
    return {**roots, "tok": tok, "wm": base / "wm" / "checkpoints" / "last.pt"}


def _tiny(point: BenchPoint) -> BenchPoint:
    """The point with 2 training steps and the stage's tiny overrides before its knob."""
    ovs = ["trainer.max_steps=2" if o.startswith("trainer.max_steps=") else o
           for o in point.overrides]  # fmt: skip
    evs = list(point.eval_overrides)
    if point.knob != DEFAULT:
        ovs, evs = (
            [*ovs[:-1], *TINY[point.stage], ovs[-1]],
            [*evs[:-1], *TINY[point.stage], evs[-1]],
        )
    else:
        ovs, evs = [*ovs, *TINY[point.stage]], [*evs, *TINY[point.stage]]
    return BenchPoint(point.stage, point.knob, point.value, point.experiment, tuple(ovs),
                      tuple(evs), point.upstream, point.seed, point.phase)  # fmt: skip


def _in_process(point, point_dir, infer_frames, repo, timeout_s):
    """``run_point`` without the subprocess (the tokenizer end-to-end test covers that path)."""
    from renderworld.bench.planner_point import run as run_planner
    from renderworld.bench.point import run as run_training

    point_dir.mkdir(parents=True)
    spec = point_spec(point, point_dir, infer_frames, repo)
    return (run_planner if point.stage == "planner" else run_training)(spec)


def _bench_cfg(bench_data, preset, out):
    return compose_cfg(
        [f"bench={preset}", f"data_root={bench_data['root']}", "bench.ranking=true",
         f"tokenizer_ckpt={bench_data['tok']}", f"world_model_ckpt={bench_data['wm']}",
         f"scenario_library={bench_data['library']}", f"heldout_root={bench_data['root']}",
         f"out={out}"],
        config_name="bench",
    )  # fmt: skip


def test_every_point_of_every_preset_composes_and_builds_its_model(bench_data, tmp_path):
    """Each (stage, knob, value) of each preset: its train and eval configs compose, and its
    stage builds the model (the knob's value reaches a model that can be constructed)."""
    from renderworld.bench.planner_point import planner_options
    from renderworld.training.registry import get_stage

    built = set()
    for preset in PRESETS:
        points = bench_points(_bench_cfg(bench_data, preset, tmp_path))
        # standard and full: ranking points at the main job's step count (or twice it)
        assert any(p.phase for p in points) == (preset != "quick")
        for p in points:
            key = (p.stage, p.config_id)
            if key in built:
                continue
            built.add(key)
            if p.stage == "planner":
                planner_options(list(p.overrides))
                continue
            tiny = _tiny(p)
            ovs = [o for o in tiny.overrides if not o.startswith("bench.")]
            cfg = compose_cfg([f"experiment={p.experiment}", *ovs, f"run_dir={tmp_path / 'r'}"])
            stage = get_stage(p.stage, cfg.stage.get("_target_module_"))(cfg)
            assert sum(t.numel() for t in stage.build_model(cfg).parameters()) > 0
    listed = {
        (stage, f"{stage}__{knob}-{format_value(v)}")
        for spec in _preset_specs().values()
        for stage, st in spec["stages"].items()
        for knob, values in (st.get("knobs") or {}).items()
        for v in values
    }
    assert built == listed | {(s, f"{s}__default") for s in KNOBS}  # none left out


#: Run by default: each stage's default point, both world-model forecasters, the scenario
#: library knob and the planner's cheap options; every other kind is marked slow (one training
#: point is 10-25 CPU seconds: all of them take several minutes; ``-m slow`` runs them).
FAST_KINDS = {
    ("tokenizer", DEFAULT), ("img2occ", DEFAULT), ("world_model", DEFAULT),
    ("world_model", "forecaster"), ("world_model", "scenario_library"), ("planner", DEFAULT),
    ("planner", "forecast"), ("planner", "precision"),
}  # fmt: skip
PARAMS = [
    pytest.param(*k, id=f"{k[0]}-{k[1]}",
                 marks=[] if k[:2] in FAST_KINDS else [pytest.mark.slow])
    for k in KINDS
]  # fmt: skip


@pytest.mark.parametrize("stage, knob, preset", PARAMS)
def test_one_point_of_each_kind_runs(bench_data, preset, stage, knob, tmp_path):
    cfg = _bench_cfg(bench_data, preset, tmp_path)
    points = [p for p in bench_points(cfg) if p.stage == stage and p.knob == knob and not p.phase]
    assert {p.seed for p in points} == ({0} if stage == "planner" else {0, 1})  # two seeds
    point = _tiny(points[0])
    (res,) = run_sweep([point], tmp_path, infer_frames=2, runner=_in_process, echo=lambda s: None)
    name = STAGE_METRICS[stage]["metric"][0]
    assert name in res["metrics"] and res["infer_ms"] > 0 and res["peak_rss_mib"] > 50
    if stage == "planner":
        if point.value != "occ3d":
            assert math.isfinite(res["metrics"][name])  # L2 of the plans on the fixture
        return
    assert res["steps"] == 2 and res["seed"] == 0 and 0.0 <= res["metrics"][name] <= 1.0
    if knob not in (DEFAULT, "steps"):  # the knob's value reached the trained model's config
        if knob == "scenario_library":
            assert res["knob_value"] == ("on" if point.value else "off")
        else:
            assert res["knob_value"] == format_value(point.value)
    if stage == "world_model":  # scored on the held-out root too
        assert 0.0 <= res["metrics"]["heldout/val/model/miou_avg"] <= 1.0
