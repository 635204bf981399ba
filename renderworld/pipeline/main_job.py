"""The main job's steps (``tools/run_pipeline.py``, ``make demo``); its report: ``job_report``.

Steps run as subprocesses of the package's own tools, so each is also a command a user can run
by hand; ``renderworld.pipeline.runner`` skips the ones whose inputs did not change.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from renderworld.constants import REPORTED_CHECKPOINT, SIM_VERSION
from renderworld.pipeline.job_report import PLANNER_BUNDLE, main_job_report
from renderworld.pipeline.runner import Step, run_steps
from renderworld.pipeline.scenario_steps import (
    LIBRARY_INFOS,
    ScenarioData,
    closed_loop_step,
    interaction_eval_step,
    scenario_steps,
    simulator_code,
)

__all__ = ["EXPERIMENTS", "EXPORT_DEVICE", "PLANNER_BUNDLE", "main_job_steps", "run_main_job"]

#: The experiment each training step runs, per family (``configs/pipeline.yaml`` experiments):
#: ``mini`` the demo's (simulated mini fixture, CPU), ``paper`` the paper's scale (real
#: nuScenes at the Occ3D grid, one GPU in bf16).
EXPERIMENTS = {
    "mini": {
        "tokenizer": "tokenizer_mini",
        "img2occ": "img2occ_mini",
        "world_model": "world_model_mini",
        "tokenizer_camera": "tokenizer_camera_mini",
        "world_model_camera": "world_model_camera_mini",
    },
    "paper": {
        "tokenizer": "paper_tokenizer",
        "img2occ": "paper_img2occ",
        "world_model": "paper_world_model",
        "tokenizer_camera": "paper_tokenizer",
        "world_model_camera": "paper_camera",
    },
}
#: Whether each family's Camera setting starts from the 3D-Occ tokenizer and world model
#: (``init_from``) and fine-tunes them on the pseudo labels (mini: docs/world_model.md, the
#: Camera setting) or trains both from scratch on the pseudo labels alone (paper).
CAMERA_FROM_3D = {"mini": True, "paper": False}
#: Device of each family's Img2Occ training: its labels are exported on the same device.
EXPORT_DEVICE = {"mini": "cpu", "paper": "cuda"}


def _train_and_eval(
    name: str,
    what: tuple[str, str],
    experiment: str,
    args: tuple[str, ...],
    out: Path,
    depends_on: tuple[str, ...],
    inputs: tuple[Path, ...],
    extra: tuple[str, ...],
    ckpt: str = REPORTED_CHECKPOINT,
    evaluate: bool = True,
    cores: int | None = None,
    eval_extra: tuple[str, ...] = (),
) -> list[Step]:
    """A training step (resumable from its ``last.pt``) and the step evaluating its checkpoint.

    Args:
        name: training step name; the eval step is ``<name>_eval``.
        what: (training description, evaluation description).
        experiment: the Hydra experiment both commands use.
        args: overrides both commands share (data root, upstream checkpoints ...).
        out: the pipeline's output folder; runs go to ``<out>/<name>`` and ``<out>/<name>_eval``.
        depends_on: steps the training reads.
        inputs: code and configs fingerprinted for the training step.
        extra: overrides for the training command only.
        ckpt: the checkpoint file evaluated (``last.pt``: ``best.pt`` is chosen on the split
            the evaluation reports, see ``REPORTED_CHECKPOINT``).
        evaluate: False: the training step only (another step evaluates its checkpoint).
        cores: the training step's ``Step.cores`` (1: it runs beside another one-core step),
            and the evaluation's.
        eval_extra: overrides for the evaluation command only.
    """
    py, run = sys.executable, out / name
    base = (f"experiment={experiment}", *args)
    train = [
        Step(
            name,
            what[0],
            (py, "tools/train.py", *base, f"run_dir={run}", *extra),
            run,
            depends_on=depends_on,
            inputs=inputs,
            resume_args=("resume=true",),
            resume_marker=run / "checkpoints" / "last.pt",
            cores=cores,
        )
    ]
    if not evaluate:
        return train
    return [
        *train,
        Step(
            f"{name}_eval",
            what[1],
            (
                py,
                "tools/eval.py",
                *base,
                f"ckpt={run / 'checkpoints' / ckpt}",
                f"run_dir={out / (name + '_eval')}",
                *eval_extra,
            ),  # fmt: skip
            out / f"{name}_eval",
            depends_on=(name,),
            cores=cores,
        ),
    ]


@dataclass(frozen=True)
class _Paths:
    """Where the main job reads and writes, and what each training step fingerprints."""

    repo: Path
    out: Path
    data: Path
    extra: tuple[str, ...]
    family: str = "mini"
    version: str | None = None  # None: the simulator's, which every mini experiment reads

    @property
    def common(self) -> tuple[str, ...]:
        version = (f"dataset.version={self.version}",) if self.version else ()
        return (f"dataset.data_root={self.data}", *version)

    def experiment(self, step: str) -> str:
        return EXPERIMENTS[self.family][step]

    def code(self, *packages: str) -> tuple[Path, ...]:
        return tuple(self.repo / "renderworld" / p for p in packages)

    def configs(self, stage: str, experiment: str) -> tuple[Path, ...]:
        conf = self.repo / "configs"
        return (conf / "stage" / f"{stage}.yaml", conf / "experiment" / f"{experiment}.yaml")

    @property
    def one_core(self) -> bool:
        """Img2Occ and the Camera setting's trainings run beside the tokenizer, the 3D-Occ
        world model and its interaction-split evaluation, each a one-core step on one thread:
        on a CPU (mini family) two one-thread steps keep two cores busier than either on two
        threads; on a GPU (paper) each runs alone."""
        return self.family == "mini"

    @property
    def one_thread(self) -> tuple[str, ...]:
        """The thread override of the one-core steps (none on a GPU)."""
        return ("trainer.num_threads=1",) if self.one_core else ()

    @property
    def side_cores(self) -> int | None:
        """``Step.cores`` of the one-core steps (None: the whole machine)."""
        return 1 if self.one_core else None

    def ckpt(self, step: str) -> Path:
        # Every checkpoint a later step reads (evaluations, the next stage's training, the
        # pseudo labels, the planner bundle, the viewer) is the run's last.pt: best.pt is
        # picked on mini_val by trainer.monitor, and mini_val is the split the report scores.
        return self.out / step / "checkpoints" / REPORTED_CHECKPOINT


def main_job_steps(cfg: Any, repo: Path) -> list[Step]:
    """The pipeline's steps for a ``configs/pipeline.yaml`` config.

    Raises:
        ValueError: an unknown ``experiments`` family.
    """
    family = str(cfg.get("experiments") or "mini")
    if family not in EXPERIMENTS:
        raise ValueError(f"experiments: expected one of {sorted(EXPERIMENTS)}, got {family!r}")
    p = _Paths(
        repo=repo,
        out=Path(str(cfg.out)).resolve(),
        data=Path(str(cfg.data_root)).resolve(),
        extra=tuple(str(x) for x in cfg.train_overrides),
        family=family,
        version=cfg.get("version"),
    )
    # Img2Occ first, once the fixture is converted: the Camera setting's chain behind it
    # (Img2Occ, its labels, the Camera tokenizer and world model) is the job's longest. On a
    # CPU the one-core scenario simulations, the tokenizer and the world model run beside it.
    steps = [*_data_steps(cfg, p), *_img2occ_steps(p)]
    scen = None
    if cfg.get("scenarios") and family == "mini":
        scen = ScenarioData.beside(p.data, repo)
        steps += scenario_steps(scen, repo)
    steps += _tokenizer_steps(p)
    if (repo / "configs" / "stage" / "world_model.yaml").is_file():
        steps += _world_model_steps(p, scen)
    steps += _viewer_steps(p, {s.name for s in steps})
    return steps


def _data_steps(cfg: Any, p: _Paths) -> list[Step]:
    """Simulate the fixture (unless ``preset`` is null: real data), then convert it (infos,
    trajectories, 2-D labels)."""
    py, conf = sys.executable, p.repo / "configs"
    version = p.version or SIM_VERSION
    convert = Step(
        "infos",
        "convert: infos, ego trajectories, LiDAR-projected 2-D labels",
        (py, "tools/create_data.py", f"data_root={p.data}", f"version={version}"),
        p.data / "renderworld_infos" / version,
        depends_on=("fixtures",) if cfg.preset else (),
        inputs=(p.repo / "data_converters", conf / "create_data.yaml"),
        cores=1,
    )
    if not cfg.preset:
        return [convert]
    return [
        Step(
            "fixtures",
            f"simulate the {cfg.preset} fixture in nuScenes format",
            (
                py,
                "tools/make_fixtures.py",
                f"out={p.data}",
                f"preset={cfg.preset}",
                f"seed={cfg.seed}",
                "overwrite=true",
            ),  # fmt: skip
            p.data,
            inputs=(*simulator_code(p.repo), conf / "sim"),
            cores=1,  # one simulation thread (and its file writer): others run beside it
        ),
        convert,
    ]


def _tokenizer_steps(p: _Paths) -> list[Step]:
    """The tokenizer on GT occupancy and its evaluation."""
    tok_exp = p.experiment("tokenizer")
    return _train_and_eval(
        "tokenizer",
        ("train the AM-VAE tokenizer on GT occupancy",
         "evaluate tokenizer reconstruction on the val split"),  # fmt: skip
        tok_exp, p.common, p.out, ("infos",),
        (*p.code("tokenizer"), *p.configs("tokenizer", tok_exp)), (*p.extra, *p.one_thread),
        cores=p.side_cores, eval_extra=p.one_thread,
    )  # fmt: skip


def _img2occ_steps(p: _Paths) -> list[Step]:
    """Img2Occ, its evaluation and its pseudo labels."""
    i2o_exp = p.experiment("img2occ")
    steps = _train_and_eval(
        "img2occ",
        ("train Img2Occ (semantic Gaussians) from LiDAR-projected 2-D labels",
         "evaluate 3-D occupancy on the val split (Occ3D protocol, camera mask)"),  # fmt: skip
        i2o_exp, p.common, p.out, ("infos",),
        (*p.code("img2occ", "splat"), *p.configs("img2occ", i2o_exp)),
        (*p.extra, *p.one_thread), cores=p.side_cores, eval_extra=p.one_thread,
    )  # fmt: skip
    pseudo = p.out / "pseudo_labels"
    steps.append(
        Step(
            "pseudo_labels",
            "export Img2Occ occupancy as Occ3D-layout pseudo labels",
            (
                sys.executable,
                "tools/export_occ.py",
                f"ckpt={p.ckpt('img2occ')}",
                f"data_root={p.data}",
                f"version={p.version or SIM_VERSION}",
                f"out={pseudo}",
                f"device={EXPORT_DEVICE[p.family]}",  # where Img2Occ trained: same labels
                *(("threads=1",) if p.one_core else ()),
            ),  # fmt: skip
            pseudo,
            depends_on=("img2occ",),
            cores=p.side_cores,
        )
    )
    return steps


def _world_model_steps(p: _Paths, scen: ScenarioData | None = None) -> list[Step]:
    """World models of both settings and the one evaluation that scores them with baselines;
    with scenario data, the 3D-Occ model also trains on the library and is scored on the
    interaction split, open loop and (its planner bundle) in closed loop."""
    pseudo = p.out / "pseudo_labels"
    tok = (f"stage.tokenizer_ckpt={p.ckpt('tokenizer')}",)
    wm_exp, cam_exp, tok_exp = (
        p.experiment("world_model"), p.experiment("world_model_camera"),
        p.experiment("tokenizer_camera"),
    )  # fmt: skip
    wm_inputs = (*p.code("world"), *p.configs("world_model", wm_exp))
    library = (f"stage.extra_train_roots=[{scen.library}]",) if scen else ()
    steps = _train_and_eval(
        "world_model",
        ("train the world model on GT occupancy tokens (3D-Occ setting)"
         + (" and the scenario library" if scen else ""), ""),
        wm_exp, (*p.common, *tok), p.out, ("tokenizer", *((LIBRARY_INFOS,) if scen else ())),
        wm_inputs, (*library, *p.extra, *p.one_thread), evaluate=False, cores=p.side_cores,
    )  # fmt: skip
    if scen:
        # Next in line, so that it uses the core the world model frees while Img2Occ trains.
        tok_wm = (p.ckpt("tokenizer"), p.ckpt("world_model"))
        steps.append(
            interaction_eval_step(scen, wm_exp, *tok_wm, p.out, p.one_thread, p.side_cores)
        )
    # Camera setting: its own tokenizer and world model on the pseudo labels (fine-tuned from
    # the 3D-Occ ones where CAMERA_FROM_3D); world_model_eval scores it in the Camera rows.
    cam_tok, from_3d = p.ckpt("tokenizer_camera"), CAMERA_FROM_3D[p.family]
    init_tok = (f"init_from={p.ckpt('tokenizer')}",) if from_3d else ()
    init_wm = (f"init_from={p.ckpt('world_model')}",) if from_3d else ()
    steps += _train_and_eval(
        "tokenizer_camera",
        ("train the AM-VAE tokenizer on Img2Occ pseudo labels (Camera setting)"
         + (", from the 3D-Occ tokenizer" if from_3d else ""), ""),
        tok_exp, (*p.common, f"stage.occ_root={pseudo}"), p.out,
        ("pseudo_labels", *(("tokenizer",) if from_3d else ())),
        (*p.code("tokenizer"), *p.configs("tokenizer", tok_exp)),
        (*init_tok, *p.extra, *p.one_thread), evaluate=False, cores=p.side_cores,
    )  # fmt: skip
    steps += _train_and_eval(
        "world_model_camera",
        ("train the world model on Img2Occ pseudo labels (Camera setting)"
         + (", from the 3D-Occ world model" if from_3d else ""), ""),
        cam_exp,
        (*p.common, f"stage.tokenizer_ckpt={cam_tok}", f"stage.occ_root={pseudo}"), p.out,
        ("tokenizer_camera", "pseudo_labels", *(("world_model",) if from_3d else ())),
        (*wm_inputs, *p.configs("world_model", cam_exp)), (*init_wm, *p.extra, *p.one_thread),
        evaluate=False, cores=p.side_cores,
    )  # fmt: skip
    # The planners the demo trained: tokenizer + world model in one bundle (load_planner), of
    # each setting (the Camera one drives on its cameras in the closed loop).
    for name, wm, tk, what in (
        ("planner", "world_model", "tokenizer", "the world model and its tokenizer"),
        ("planner_camera", "world_model_camera", "tokenizer_camera",
         "the Camera setting's world model and tokenizer"),
    ):  # fmt: skip
        steps.append(
            Step(
                name,
                f"bundle {what} as a planner (renderworld.planning)",
                (sys.executable, "tools/export_planner.py", f"world_model_ckpt={p.ckpt(wm)}",
                 f"tokenizer_ckpt={p.ckpt(tk)}", f"out={p.out / name / PLANNER_BUNDLE}"),
                p.out / name,
                depends_on=(tk, wm),
                inputs=(*p.code("planning"), p.repo / "renderworld" / "training" / "stages"
                        / "world_model" / "bundle.py"),
            )
        )  # fmt: skip
    # One evaluation, one table: both settings, model and baselines.
    evaluate = (
        sys.executable, "tools/eval.py", f"experiment={wm_exp}", *p.common, *tok,
        f"ckpt={p.ckpt('world_model')}", f"pseudo_labels={pseudo}",
        f"camera_ckpt={p.ckpt('world_model_camera')}", f"camera_tokenizer_ckpt={cam_tok}",
        f"run_dir={p.out / 'world_model_eval'}",
    )  # fmt: skip
    steps.append(
        Step(
            "world_model_eval",
            "forecast and plan on the val split beside the baselines: 3D-Occ and Camera settings",
            evaluate,
            p.out / "world_model_eval",
            depends_on=("world_model", "tokenizer_camera", "world_model_camera", "pseudo_labels"),
            inputs=p.code("planning"),  # its checked-plan rows
        )
    )
    if scen:
        camera = (p.out / "planner_camera" / PLANNER_BUNDLE, p.ckpt("img2occ"))
        steps.append(closed_loop_step(p.out / "planner" / PLANNER_BUNDLE, p.out, p.repo, camera))
    return steps


def _viewer_steps(p: _Paths, names: set[str]) -> list[Step]:
    """One mini_val scene as a Rerun recording with the job's checkpoints (``tools/view.py``);
    none without rerun-sdk (the report then says how to install it)."""
    from renderworld.viewer import rerun_available, view_command
    from renderworld.viewer.job import JOB_RECORDING

    if not rerun_available():
        return []
    readers = ("infos", "img2occ", "tokenizer", "world_model")
    return [
        Step(
            "viewer",
            "write a 3-D Rerun recording of one mini_val scene (data, Gaussians, forecasts)",
            view_command(sys.executable, p.out, p.data, SIM_VERSION),
            p.out / Path(JOB_RECORDING).parent,
            depends_on=tuple(n for n in readers if n in names),
            inputs=(*p.code("viewer"), p.repo / "configs" / "view.yaml"),
        )
    ]


def run_main_job(cfg: Any, repo: Path) -> Path:
    """Run every step (skipping up-to-date ones) and write ``<out>/report.md``."""
    out = Path(str(cfg.out)).resolve()
    t0 = time.perf_counter()
    steps = main_job_steps(cfg, repo)
    print(f"RenderWorld main job: {len(steps)} steps, outputs in {out}")
    cores = cfg.get("cores")
    results = run_steps(steps, out / "logs", cwd=repo, force=list(cfg.force), cores=cores)
    report = main_job_report(cfg, out, results, time.perf_counter() - t0)
    ran = sum(r.status == "ran" for r in results)
    print(f"done in {time.perf_counter() - t0:.0f} s ({ran} steps ran, {len(results) - ran} "
          f"up to date); report: {report}")  # fmt: skip
    return report
