"""The main job's steps and report (``tools/run_pipeline.py``, ``make demo``).

Steps run as subprocesses of the package's own tools, so each is also a command a user can run
by hand; ``renderworld.pipeline.runner`` skips the ones whose inputs did not change.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

from renderworld.pipeline.report import (
    load_json,
    metrics_table,
    per_class_table,
    plot_training_curves,
    write_report,
)
from renderworld.pipeline.runner import Step, run_steps
from renderworld.training.figures import bev_image
from renderworld.training.schedule import read_schedule

__all__ = ["main_job_steps", "run_main_job"]

NA = "–"
ABSENT = (
    "class absent from both GT and prediction on this split (IoU 0/0 is undefined; the class is "
    "left out of the mIoU)"
)

VERSION = "v1.0-mini"


def _train_and_eval(
    name: str,
    what: tuple[str, str],
    experiment: str,
    args: tuple[str, ...],
    out: Path,
    depends_on: tuple[str, ...],
    inputs: tuple[Path, ...],
    extra: tuple[str, ...],
    ckpt: str = "best.pt",
    evaluate: bool = True,
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
        ckpt: the checkpoint file evaluated.
        evaluate: False: the training step only (another step evaluates its checkpoint).
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
            ),  # fmt: skip
            out / f"{name}_eval",
            depends_on=(name,),
        ),
    ]


def main_job_steps(cfg: Any, repo: Path) -> list[Step]:
    """The pipeline's steps for a ``configs/pipeline.yaml`` config."""
    py = sys.executable
    out = Path(str(cfg.out)).resolve()
    data = Path(str(cfg.data_root)).resolve()
    infos = data / "renderworld_infos" / VERSION
    extra = tuple(str(x) for x in cfg.train_overrides)
    pkg, conf = repo / "renderworld", repo / "configs"
    common = (f"dataset.data_root={data}",)

    def configs(stage: str, experiment: str) -> tuple[Path, ...]:
        return (conf / "stage" / f"{stage}.yaml", conf / "experiment" / f"{experiment}.yaml")

    steps = [
        Step(
            "fixtures",
            f"simulate the {cfg.preset} fixture in nuScenes format",
            (
                py,
                "tools/make_fixtures.py",
                f"out={data}",
                f"preset={cfg.preset}",
                f"seed={cfg.seed}",
                "overwrite=true",
            ),  # fmt: skip
            data,
            inputs=(pkg / "sim", conf / "sim"),
        ),
        Step(
            "infos",
            "convert: infos, ego trajectories, LiDAR-projected 2-D labels",
            (py, "tools/create_data.py", f"data_root={data}", f"version={VERSION}"),
            infos,
            depends_on=("fixtures",),
            inputs=(repo / "data_converters", conf / "create_data.yaml"),
        ),
    ]
    steps += _train_and_eval(
        "tokenizer",
        ("train the AM-VAE tokenizer on GT occupancy",
         "evaluate tokenizer reconstruction on mini_val"),  # fmt: skip
        "tokenizer_mini", common, out, ("infos",),
        (pkg / "tokenizer", *configs("tokenizer", "tokenizer_mini")), extra,
    )  # fmt: skip
    i2o = out / "img2occ" / "checkpoints" / "best.pt"
    pseudo = out / "pseudo_labels"
    steps += _train_and_eval(
        "img2occ",
        ("train Img2Occ (semantic Gaussians) from LiDAR-projected 2-D labels",
         "evaluate 3-D occupancy on mini_val (Occ3D protocol, camera mask)"),  # fmt: skip
        "img2occ_mini", common, out, ("infos",),
        (pkg / "img2occ", pkg / "splat", *configs("img2occ", "img2occ_mini")), extra,
    )  # fmt: skip
    steps.append(
        Step(
            "pseudo_labels",
            "export Img2Occ occupancy as Occ3D-layout pseudo labels",
            (py, "tools/export_occ.py", f"ckpt={i2o}", f"data_root={data}", f"out={pseudo}"),
            pseudo,
            depends_on=("img2occ",),
        )
    )
    if (conf / "stage" / "world_model.yaml").is_file():
        tok = (f"stage.tokenizer_ckpt={out / 'tokenizer' / 'checkpoints' / 'best.pt'}",)
        wm_inputs = (pkg / "world", *configs("world_model", "world_model_mini"))
        steps += _train_and_eval(
            "world_model",
            ("train the world model on GT occupancy tokens (3D-Occ setting)", ""),
            "world_model_mini", (*common, *tok), out, ("tokenizer",), wm_inputs, extra,
            evaluate=False,
        )  # fmt: skip
        # Camera setting (paper): its own tokenizer, trained on the pseudo labels; the world
        # model_eval step scores it in the Camera rows (camera_tokenizer_ckpt).
        cam_tok = out / "tokenizer_camera" / "checkpoints" / "best.pt"
        steps += _train_and_eval(
            "tokenizer_camera",
            ("train the AM-VAE tokenizer on Img2Occ pseudo labels (Camera setting)", ""),
            "tokenizer_mini", (*common, f"stage.occ_root={pseudo}"), out, ("pseudo_labels",),
            (pkg / "tokenizer", *configs("tokenizer", "tokenizer_mini")), extra, evaluate=False,
        )  # fmt: skip
        steps += _train_and_eval(
            "world_model_camera",
            ("train the world model on Img2Occ pseudo labels (Camera setting)", ""),
            "world_model_mini",
            (*common, f"stage.tokenizer_ckpt={cam_tok}", f"stage.occ_root={pseudo}"), out,
            ("tokenizer_camera", "pseudo_labels"), wm_inputs, extra, evaluate=False,
        )  # fmt: skip
        # One evaluation, one table: both settings, model and baselines (issue 9 item 4).
        steps.append(
            Step(
                "world_model_eval",
                "forecast and plan on mini_val beside the baselines: 3D-Occ and Camera settings",
                (
                    py,
                    "tools/eval.py",
                    "experiment=world_model_mini",
                    *common,
                    *tok,
                    f"ckpt={out / 'world_model' / 'checkpoints' / 'best.pt'}",
                    f"pseudo_labels={pseudo}",
                    f"camera_ckpt={out / 'world_model_camera' / 'checkpoints' / 'best.pt'}",
                    f"camera_tokenizer_ckpt={cam_tok}",
                    f"run_dir={out / 'world_model_eval'}",
                ),  # fmt: skip
                out / "world_model_eval",
                depends_on=(
                    "world_model",
                    "tokenizer_camera",
                    "world_model_camera",
                    "pseudo_labels",
                ),  # fmt: skip
            )
        )
    return steps


def _bev_figure(cfg: Any, out: Path) -> Path | None:
    """GT vs tokenizer reconstruction, bird's-eye view, for one mini_val frame."""
    ckpt = out / "tokenizer" / "checkpoints" / "best.pt"
    if not ckpt.is_file():
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    from renderworld.data import load_infos
    from renderworld.training.stages.tokenizer import OccFrames, load_tokenizer

    data = Path(str(cfg.data_root)).resolve()
    tok = load_tokenizer(ckpt)
    grid = tuple(tok.cfg.grid_shape)
    from renderworld.constants import GRIDS

    spec = next(g for g in GRIDS.values() if tuple(g.shape) == grid)
    frames = OccFrames(load_infos(data / "renderworld_infos" / VERSION, "val"), data, spec)
    occ = frames[len(frames) // 2]["occ"][None]
    with torch.no_grad():
        rec = tok.decode(tok.encode(occ))[0].numpy()
    fig, axes = plt.subplots(1, 2, figsize=(7, 3.6))
    for ax, img, title in zip(
        axes,
        (bev_image(occ[0].numpy()), bev_image(rec)),
        ("GT occupancy", "AM-VAE recon."),
        strict=True,
    ):
        ax.imshow(img)
        ax.set_title(title)
        ax.axis("off")
    fig.tight_layout()
    path = out / "figures" / "bev_tokenizer.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _demote_headings(md: str, levels: int = 2) -> str:
    """Markdown with every heading ``levels`` deeper (a stage's own file inside a section)."""
    return "\n".join("#" * levels + line if line.startswith("#") else line
                     for line in md.splitlines())  # fmt: skip


def schedule_cell(run_dir: Path) -> str:
    """The run table's schedule cell of a training step: steps done, or where the guard stopped it.

    Args:
        run_dir: the step's output folder; a training run holds ``schedule.json``.

    Returns:
        ``"2700 of 2700 steps"``, ``"**stopped at step 1795 of 2700** (time guard 11.25 min)"``,
        or ``"–"`` for a step that does not train.
    """
    record = read_schedule(run_dir)
    if not record:
        return NA
    done, total = int(record["step"]), int(record["max_steps"])
    if record.get("stopped_early"):
        return f"**stopped at step {done} of {total}** (time guard {record['max_minutes']:g} min)"
    return f"{done} of {total} steps"


def _report(cfg: Any, out: Path, results, seconds: float) -> Path:
    # Imported here: the main job's own process stays light until it writes the report.
    from renderworld.training.stages.world_model_pictures import BEV_PNG, TRAJ_PNG
    from renderworld.training.stages.world_model_report import REPORT_BASENAME

    data = Path(str(cfg.data_root)).resolve()
    sim = load_json(data / "sim_report.json")
    sections = []
    steps = "\n".join(
        ["| step | this run | seconds (when it ran) | schedule |", "|---|---|---|---|"]
        + [f"| {r.name} | {r.status} | {r.seconds:.0f} | {schedule_cell(out / r.name)} |"
           for r in results]
    )  # fmt: skip
    made = sum(r.seconds for r in results)
    sections.append(
        (
            "Run",
            f"This run: {seconds:.0f} s; making every output took {made:.0f} s in all.\n\n{steps}",
        )  # fmt: skip
    )
    if sim:
        sections.append(
            (
                "Data",
                f"Simulated fixture `{data}`: {sim.get('files', '?')} files, "
                f"{sim.get('bytes', 0) / 2**20:.0f} MiB, generated in "
                f"{sim.get('seconds', 0):.0f} s.",
            )  # fmt: skip
        )
    tok = load_json(out / "tokenizer_eval" / "eval_metrics.json")
    if tok:
        body = metrics_table(
            tok,
            [
                ("mIoU (classes 0..16, full volume, OccWorld protocol)", "val/miou"),
                ("IoU occupied vs free (full volume)", "val/iou"),
                ("mIoU inside the camera mask", "val/cam/miou"),
                ("IoU inside the camera mask", "val/cam/iou"),
            ],  # fmt: skip
        )
        classes = per_class_table(tok, "val/")
        body += "\n\nPer-class IoU (%, full volume):\n\n" + classes
        legend = [f"{NA}: {ABSENT}"] if NA in classes else []
        if "n/a" in body:
            legend.append(
                "n/a: not in this evaluation's metrics, or undefined (0/0: nothing occupied in "
                "GT or reconstruction in that region)"
            )
        body += "".join(f"\n\n{x}" for x in legend)
        sections.append(("Tokenizer reconstruction (AM-VAE, mini_val, GT occupancy)", body))
    i2o_table = out / "img2occ_eval" / "occ3d_metrics.md"
    if i2o_table.is_file():
        body = _demote_headings(i2o_table.read_text())
        if NA in body and "absent" not in body:
            body += f"\n\n{NA}: {ABSENT}"
        sections.append(("3-D occupancy from cameras (Img2Occ, mini_val)", body))
    wm_table = out / "world_model_eval" / f"{REPORT_BASENAME}.md"
    if wm_table.is_file():
        sections.append(
            (
                "Forecasting and planning (mini_val; 3D-Occ and Camera settings)",
                wm_table.read_text(),
            )
        )
    figures = []
    runs = ("img2occ", "tokenizer", "tokenizer_camera", "world_model", "world_model_camera")
    for run in runs:
        png = plot_training_curves(
            out / run / "metrics.csv", out / "figures" / f"curves_{run}.png",
            keys=("train/loss", "val/"),
        )  # fmt: skip
        if png:
            figures.append(f"![{run} training curves](figures/{png.name})")
    views = out / "img2occ_eval" / "img2occ_views.png"
    if views.is_file():
        (out / "figures").mkdir(parents=True, exist_ok=True)
        (out / "figures" / views.name).write_bytes(views.read_bytes())
        figures.append(f"![Img2Occ renders vs LiDAR-projected targets](figures/{views.name})")
    bev = _bev_figure(cfg, out)
    if bev:
        figures.append(f"![BEV GT vs reconstruction](figures/{bev.name})")
    for name, caption in (
        (BEV_PNG, "BEV occupancy: GT vs Img2Occ pseudo label vs forecasts at +1/2/3 s"),
        (TRAJ_PNG, "Planned vs GT trajectories over the BEV (3D-Occ model, CV baseline)"),
    ):
        png = out / "world_model_eval" / name
        if png.is_file():
            (out / "figures").mkdir(parents=True, exist_ok=True)
            (out / "figures" / name).write_bytes(png.read_bytes())
            figures.append(f"![{caption}](figures/{name})")
    if figures:
        sections.append(("Pictures", "\n\n".join(figures)))
    return write_report(out, sections)


def run_main_job(cfg: Any, repo: Path) -> Path:
    """Run every step (skipping up-to-date ones) and write ``<out>/report.md``."""
    out = Path(str(cfg.out)).resolve()
    t0 = time.perf_counter()
    steps = main_job_steps(cfg, repo)
    print(f"RenderWorld main job: {len(steps)} steps, outputs in {out}")
    results = run_steps(steps, out / "logs", cwd=repo, force=list(cfg.force))
    report = _report(cfg, out, results, time.perf_counter() - t0)
    ran = sum(r.status == "ran" for r in results)
    print(f"done in {time.perf_counter() - t0:.0f} s ({ran} steps ran, {len(results) - ran} "
          f"up to date); report: {report}")  # fmt: skip
    return report
