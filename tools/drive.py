"""Closed-loop driving in the simulator (Hydra entry point; configs/drive.yaml).

    python tools/drive.py [preset=interactions] [planner=PATH/planner.pt]
        [true_movers=true] [check={KNOB: VALUE}] [behaviours=interactions] [max_scenes=50]
        [scenes=[scene-5059]]
        [camera_planner=PATH/planner.pt img2occ=PATH/last.pt]
        [planners=[log_replay,cv,ctr,rule_based,stop]] [grid=coarse] [out=outputs/drive]
        [record=scene-6000]

Builds the preset's scenes (the same worlds ``tools/make_fixtures.py`` writes for that preset
and seed), lets each planner drive each scene (:mod:`renderworld.sim.closed_loop`), prints the
table and writes ``closed_loop.{md,csv,json}``, ``figures/`` and (``record=<scene>``, needs
rerun-sdk) a Rerun recording of that scene's episodes into ``out``. Exits with an
error when log replay is not perfect on every scene (the runner's self-check).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from renderworld.constants import get_grid  # noqa: E402
from renderworld.planning.candidates import check_config  # noqa: E402
from renderworld.sim import build_worlds  # noqa: E402
from renderworld.sim.closed_loop import (  # noqa: E402
    make_bundle_planners,
    make_planner,
    run_closed_loop,
    self_check,
    summary_markdown,
    write_outputs,
)
from tools.make_fixtures import config_from_preset  # noqa: E402


def drive(cfg: DictConfig) -> dict:
    """Run the config; returns the written paths, the run's seconds and the self-check."""
    t0 = time.perf_counter()
    overrides = {k: cfg[k] for k in ("seed", "num_scenes") if cfg.get(k) is not None}
    sim = config_from_preset(str(cfg.preset), **overrides)
    grid = get_grid(str(cfg.grid)) if cfg.get("grid") else None
    names = [str(n) for n in cfg.planners]
    planners = [make_planner(n) for n in names]
    if cfg.get("planner"):
        true_movers = bool(cfg.get("true_movers", False))
        rows = make_bundle_planners(str(cfg.planner), grid=grid, true_movers=true_movers)
        if cfg.get("check"):
            rows[0].planner.check_config = check_config(cfg.check)
        planners += rows
    if cfg.get("camera_planner"):
        planners.append(camera_planner(cfg, grid))
    if cfg.get("threads"):
        import torch

        torch.set_num_threads(int(cfg.threads))
    t_build = time.perf_counter()
    worlds = select_worlds(build_worlds(sim), cfg.get("behaviours"), cfg.get("max_scenes"),
                           cfg.get("scenes"))  # fmt: skip
    build_s = time.perf_counter() - t_build
    if cfg.get("trace"):  # refused before driving, not after
        if not cfg.get("planner"):
            raise ValueError("trace: traces a checked planner's choices; pass planner=<bundle>")
        if str(cfg.trace) not in {w.name for w in worlds}:
            raise ValueError(f"trace: no scene {str(cfg.trace)!r} among this run's scenes")
    nudge = float(cfg.get("nudge_m") or 0.0)
    run = run_closed_loop(worlds, planners, progress=bool(cfg.progress), nudge_m=nudge)
    check = self_check(run)
    settings = {
        "preset": str(cfg.preset),
        "seed": sim.seed,
        "scenes": [w.name for w in worlds],
        "planners": [p.name for p in planners],
        "planner_bundle": str(cfg.planner) if cfg.get("planner") else None,
        "nudge_m": nudge,
        "build_seconds": round(build_s, 3),
        "seconds": round(time.perf_counter() - t0, 3),
    }
    paths = write_outputs(run, worlds, Path(str(cfg.out)), settings, check)
    if cfg.get("trace"):
        from renderworld.sim.closed_loop.trace import write_trace

        scene = str(cfg.trace)
        world = next(w for w in worlds if w.name == scene)
        paths["trace"] = write_trace(world, planners, Path(str(cfg.out)), nudge_m=nudge)
        print(f"trace of {scene}: {paths['trace']}")
    if cfg.get("record"):
        from renderworld.viewer.closed_loop import write_episode_recording

        scene = str(cfg.record)
        world = next((w for w in worlds if w.name == scene), None)
        if world is None:
            raise ValueError(f"record: no scene {scene!r} in preset {cfg.preset}")
        eps = [e for e in run.episodes if e.scene == scene]
        paths["recording"] = write_episode_recording(
            world, eps, Path(str(cfg.out)) / f"closed_loop_{scene}.rrd"
        )
        print(f"Rerun recording of {scene}: {paths['recording']} (open with: rerun <file>)")
    print(summary_markdown(run))
    print(f"\nscenes built in {build_s:.1f} s; whole run {time.perf_counter() - t0:.1f} s; "
          f"outputs in {paths['md'].parent}")  # fmt: skip
    if "log_replay" in run.planners:
        print("self-check (log replay perfect on every scene): " + ("passed" if not check else
              "FAILED:\n  " + "\n  ".join(check)))  # fmt: skip
    return {"paths": paths, "self_check": check, "run": run}


def select_worlds(worlds: list, behaviours=None, max_scenes=None, scenes=None) -> list:
    """The scenes of the listed behaviours (``"interactions"``: the five interaction ones), in
    preset order, at most ``max_scenes`` of them (None: all); with ``scenes``, only those named.

    Raises:
        ValueError: naming ``behaviours`` for a behaviour no scene of the preset has, or
            ``scenes`` for a name no scene of the preset has.
    """
    from renderworld.sim.scene import INTERACTIONS

    if scenes:
        wanted = [str(n) for n in ([scenes] if isinstance(scenes, str) else scenes)]
        missing = sorted(set(wanted) - {w.name for w in worlds})
        if missing:
            raise ValueError(f"scenes: {missing} not in this preset ({len(worlds)} scenes, e.g. "
                             f"{worlds[0].name if worlds else 'none'})")  # fmt: skip
        worlds = [w for w in worlds if w.name in set(wanted)]

    if behaviours:
        names = list(INTERACTIONS) if behaviours == "interactions" else [str(b) for b in behaviours]
        known = {w.spec.behaviour for w in worlds}
        unknown = sorted(set(names) - known)
        if unknown:
            raise ValueError(f"behaviours: {unknown} not in this preset's {sorted(known)}")
        worlds = [w for w in worlds if w.spec.behaviour in set(names)]
    return worlds if max_scenes is None else worlds[: int(max_scenes)]


def camera_planner(cfg: DictConfig, grid):
    """The Camera setting's row: its bundle's checked plan on Img2Occ's occupancy of the
    cameras rendered at the ego's actual pose (renderworld.sim.closed_loop.cameras)."""
    from renderworld.planning import load_planner
    from renderworld.sim.closed_loop import BundlePlanner
    from renderworld.sim.closed_loop.cameras import CameraObserver
    from renderworld.training.stages.img2occ.builders import load_img2occ

    if not cfg.get("img2occ"):
        raise ValueError("img2occ: camera_planner needs the Img2Occ checkpoint its occupancy is "
                         "read out of (img2occ=<run>/checkpoints/last.pt)")  # fmt: skip
    bundle = load_planner(Path(str(cfg.camera_planner)))
    model, _ = load_img2occ(str(cfg.img2occ))
    size = cfg.get("camera_image_size")
    observer = CameraObserver(model, bundle.grid, None if size is None else tuple(size))
    return BundlePlanner(bundle, "world_model_camera", grid, check=True, observer=observer)


@hydra.main(version_base=None, config_path="../configs", config_name="drive")
def main(cfg: DictConfig) -> None:
    OmegaConf.set_readonly(cfg, True)
    result = drive(cfg)
    if cfg.self_check and result["self_check"]:
        sys.exit(1)


if __name__ == "__main__":
    main()
