"""The main job's scenario data: a library the world model trains on, a held-out interaction
split it is scored on (``configs/sim/preset/scenarios.yaml`` and ``interactions.yaml``).

Both are simulated in the occupancy-only mode (Occ3D occupancy, poses, boxes, commands; no
camera images, no LiDAR) and converted without 2-D labels; each is one step skipped when up to
date, like the fixture. The world model adds the library's windows to its training
(``stage.extra_train_roots``); validation and the headline table stay the mini fixture's val
split. The interaction split (its own seed) is evaluated with the same checkpoints, where the
collision metric has something to find (docs/scenarios.md).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from renderworld.pipeline.runner import Step

__all__ = [
    "CLOSED_LOOP",
    "CLOSED_LOOP_RECORDED",
    "ScenarioData",
    "closed_loop_step",
    "interaction_eval_step",
    "preset_version",
    "scenario_steps",
]

#: Step names of the scenario data (the world-model training depends on the library's).
LIBRARY_INFOS = "scenario_infos"
INTERACTION_INFOS = "interaction_infos"
#: Step (and output folder) of the closed-loop evaluation on the interaction split.
CLOSED_LOOP = "closed_loop"


def preset_version(repo: Path, preset: str) -> str:
    """The dataset version a simulator preset writes (its ``version:`` key).

    Raises:
        FileNotFoundError: no ``configs/sim/preset/<preset>.yaml``.
        ValueError: the preset names no version.
    """
    from omegaconf import OmegaConf

    path = repo / "configs" / "sim" / "preset" / f"{preset}.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"scenarios: simulator preset {path} does not exist")
    version = OmegaConf.load(path).get("version")
    if not version:
        raise ValueError(f"scenarios: {path} names no dataset version (its `version:` key)")
    return str(version)


@dataclass(frozen=True)
class ScenarioData:
    """Where the scenario data lives: ``library`` (training) and ``interactions`` (held out)."""

    library: Path
    library_version: str
    interactions: Path
    interactions_version: str

    @classmethod
    def beside(cls, data_root: Path, repo: Path) -> ScenarioData:
        """Folders ``sim_scenarios`` and ``sim_interactions`` beside the fixture's root."""
        return cls(
            library=data_root.parent / "sim_scenarios",
            library_version=preset_version(repo, "scenarios"),
            interactions=data_root.parent / "sim_interactions",
            interactions_version=preset_version(repo, "interactions"),
        )


def simulator_code(repo: Path) -> tuple[Path, ...]:
    """The simulator's code a fixture depends on: ``renderworld/sim`` without the closed loop
    (driving planners through scenes changes no simulated data)."""
    sim = repo / "renderworld" / "sim"
    return tuple(sorted(q for q in sim.iterdir() if q.name not in ("closed_loop", "__pycache__")))


def scenario_steps(data: ScenarioData, repo: Path) -> list[Step]:
    """Simulate (occupancy only) and convert (infos, no 2-D labels) both scenario datasets."""
    py, conf = sys.executable, repo / "configs"
    sim_inputs = (*simulator_code(repo), conf / "sim")
    steps = []
    for name, preset, root, version, infos_name, what in (
        ("scenario_data", "scenarios", data.library, data.library_version, LIBRARY_INFOS,
         "the scenario library (turns and interactions) the world model trains on"),
        ("interaction_data", "interactions", data.interactions, data.interactions_version,
         INTERACTION_INFOS, "the held-out interaction split (its own seed)"),
    ):  # fmt: skip
        steps.append(
            Step(
                name,
                f"simulate {what}, occupancy only",
                (
                    py,
                    "tools/make_fixtures.py",
                    f"out={root}",
                    f"preset={preset}",
                    "mode=occupancy",
                    "overwrite=true",
                ),  # fmt: skip
                root,
                inputs=sim_inputs,
                cores=1,
            )
        )
        steps.append(
            Step(
                infos_name,
                f"convert {what}: infos and ego trajectories (no 2-D labels)",
                (
                    py,
                    "tools/create_data.py",
                    f"data_root={root}",
                    f"version={version}",
                    "labels=false",
                ),  # fmt: skip
                root / "renderworld_infos" / version,
                depends_on=(name,),
                inputs=(repo / "data_converters", conf / "create_data.yaml"),
                cores=1,
            )
        )
    return steps


def interaction_eval_step(
    data: ScenarioData,
    experiment: str,
    tokenizer_ckpt: Path,
    ckpt: Path,
    out: Path,
    extra: tuple[str, ...] = (),
    cores: int | None = None,
) -> Step:
    """Score the world model (and the baselines) on the interaction split; ``extra``
    overrides and ``cores`` as for a training step (``main_job``)."""
    run = out / "world_model_interactions"
    return Step(
        "world_model_interactions",
        "forecast and plan on the held-out interaction split (collisions with counts)",
        (
            sys.executable,
            "tools/eval.py",
            f"experiment={experiment}",
            f"dataset.data_root={data.interactions}",
            f"dataset.version={data.interactions_version}",
            f"stage.tokenizer_ckpt={tokenizer_ckpt}",
            f"ckpt={ckpt}",
            f"run_dir={run}",
            *extra,
        ),  # fmt: skip
        run,
        depends_on=("world_model", INTERACTION_INFOS),
        inputs=(Path(__file__).resolve().parents[1] / "planning",),  # its checked-plan rows
        cores=cores,
    )


#: The interaction scene recorded for the viewer (a lead_brake scene).
CLOSED_LOOP_RECORDED = "scene-6000"


def closed_loop_step(
    bundle: Path, out: Path, repo: Path, camera: tuple[Path, Path] | None = None
) -> Step:
    """Drive the interaction split's scenes in closed loop: the reference planners, the main
    job's planner bundle (its checked and its raw plan) and, with ``camera`` = (the Camera
    setting's bundle, Img2Occ's checkpoint), the Camera setting on rendered cameras
    (``tools/drive.py``; the preset's worlds, rebuilt from its seed); with rerun-sdk installed,
    one scene's episodes are also written as a Rerun recording."""
    from renderworld.viewer import rerun_available

    conf = repo / "configs"
    record = (f"record={CLOSED_LOOP_RECORDED}",) if rerun_available() else ()
    cams = (f"camera_planner={camera[0]}", f"img2occ={camera[1]}") if camera else ()
    return Step(
        CLOSED_LOOP,
        "drive the interaction split in closed loop: log replay, CV, CTR, rule-based, stop, the "
        "world model (checked and raw plans, and checked against the true movers)"
        + (", the Camera setting on its cameras" if camera else ""),  # fmt: skip
        (
            sys.executable,
            "tools/drive.py",
            "preset=interactions",
            "planners=[log_replay,cv,ctr,rule_based,stop]",
            f"planner={bundle}",
            "true_movers=true",
            *cams,
            f"out={out / CLOSED_LOOP}",
            *record,
        ),  # fmt: skip
        out / CLOSED_LOOP,
        depends_on=("planner", *(("planner_camera", "img2occ") if camera else ())),
        inputs=(
            repo / "renderworld" / "sim",
            conf / "sim",
            conf / "drive.yaml",
            repo / "tools" / "drive.py",
            repo / "renderworld" / "viewer" / "closed_loop.py",
        ),
    )
