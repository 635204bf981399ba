"""The main job's report: ``<out>/report.md`` gathered from the outputs of its steps.

One section per stage whose outputs exist (run table with each training's schedule, data,
tokenizer reconstruction, Img2Occ occupancy, forecasting and planning), then the pictures.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from renderworld.constants import REPORTED_CHECKPOINT, SIM_VERSION
from renderworld.pipeline.report import (
    UnreadableFile,
    load_json,
    metrics_table,
    per_class_table,
    plot_training_curves,
    unreadable_note,
    write_report,
)
from renderworld.training.figures import bev_image
from renderworld.training.schedule import read_schedule
from renderworld.viewer import report_section

__all__ = ["PLANNER_BUNDLE", "main_job_report", "schedule_cell"]

#: File name of the main job's planner bundle, in ``<out>/planner/``.
PLANNER_BUNDLE = "planner.pt"

NA = "–"
ABSENT = (
    "class absent from both GT and prediction on this split (IoU 0/0 is undefined; the class is "
    "left out of the mIoU)"
)


def main_job_report(cfg: Any, out: Path, results: list, seconds: float) -> Path:
    """Write ``<out>/report.md`` from the outputs of the main job's steps.

    Args:
        cfg: the ``configs/pipeline.yaml`` config (``data_root``).
        out: the main job's output folder.
        results: the :class:`~renderworld.pipeline.runner.StepResult` of every step, in order.
        seconds: this run's wall time.

    Returns:
        The report's path. Sections whose outputs are missing are left out.
    """
    sections = [_run_section(out, results, seconds)]
    sections += _data_section(cfg)
    sections += _tokenizer_section(out)
    sections += _img2occ_section(out)
    sections += _world_model_section(out)
    sections += _interaction_section(out)
    sections += _closed_loop_section(out)
    sections += _planner_section(out)
    sections.append(("3-D recording (Rerun)", report_section(out)))
    figures = _pictures(cfg, out)
    if figures:
        sections.append(("Pictures", "\n\n".join(figures)))
    return write_report(out, sections)


def _run_section(out: Path, results: list, seconds: float) -> tuple[str, str]:
    steps = "\n".join(
        ["| step | this run | seconds (when it ran) | schedule |", "|---|---|---|---|"]
        + [f"| {r.name} | {r.status} | {r.seconds:.0f} | {schedule_cell(out / r.name)} |"
           for r in results]
    )  # fmt: skip
    made = sum(r.seconds for r in results)
    text = (
        f"This run: {seconds:.0f} s; making every output took {made:.0f} s in all, the sum of "
        f"the steps' own times (one-core steps may have run side by side).\n\n{steps}"
    )
    return ("Run", text)


def _data_section(cfg: Any) -> list[tuple[str, str]]:
    data = Path(str(cfg.data_root)).resolve()
    lines = []
    for root, what in (
        (data, "Simulated fixture"),
        (data.parent / "sim_scenarios", "Scenario library (world-model training, occupancy only)"),
        (data.parent / "sim_interactions", "Interaction split (held out, occupancy only)"),
    ):
        try:
            sim = load_json(root / "sim_report.json")
        except UnreadableFile as err:
            lines.append(f"{what}: {unreadable_note(err)}")
            continue
        if sim:
            scenes, mib = len(sim.get("scenes", [])), sim.get("bytes", 0) / 2**20
            lines.append(
                f"{what} `{root}`: {scenes} scenes, {sim.get('files', '?')} files, "
                f"{mib:.0f} MiB, generated in {sim.get('seconds', 0):.0f} s."
            )
    return [("Data", "\n\n".join(lines))] if lines else []


def _tokenizer_section(out: Path) -> list[tuple[str, str]]:
    title = "Tokenizer reconstruction (AM-VAE, mini_val, GT occupancy)"
    try:
        tok = load_json(out / "tokenizer_eval" / "eval_metrics.json")
    except UnreadableFile as err:
        return [(title, unreadable_note(err))]
    if not tok:
        return []
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
    return [(title, body)]


def _img2occ_section(out: Path) -> list[tuple[str, str]]:
    table = out / "img2occ_eval" / "occ3d_metrics.md"
    if not table.is_file():
        return []
    body = _demote_headings(table.read_text())
    if NA in body and "absent" not in body:
        body += f"\n\n{NA}: {ABSENT}"
    return [("3-D occupancy from cameras (Img2Occ, mini_val)", body)]


def _world_model_section(out: Path) -> list[tuple[str, str]]:
    from renderworld.training.stages.world_model.report import REPORT_BASENAME

    table = out / "world_model_eval" / f"{REPORT_BASENAME}.md"
    if not table.is_file():
        return []
    return [("Forecasting and planning (mini_val; 3D-Occ and Camera settings)", table.read_text())]


def _interaction_section(out: Path) -> list[tuple[str, str]]:
    from renderworld.training.stages.world_model.report import REPORT_BASENAME

    table = out / "world_model_interactions" / f"{REPORT_BASENAME}.md"
    if not table.is_file():
        return []
    intro = (
        "The 3D-Occ world model and the baselines on the held-out interaction split (lead "
        "vehicle braking, cut-in, pedestrian crossing, oncoming traffic at a turn, overtaking a "
        "parked car; its own seed; docs/scenarios.md): where the ego brakes or swerves for "
        "someone, a trajectory that ignores the scene collides.\n\n"
    )
    return [("Interactions (held-out split; same checkpoints)", intro + table.read_text())]


def _closed_loop_section(out: Path) -> list[tuple[str, str]]:
    from renderworld.pipeline.scenario_steps import CLOSED_LOOP

    run = out / CLOSED_LOOP
    table = run / "closed_loop.md"
    if not table.is_file():
        return []
    intro = (
        "Each planner drives the interaction split's scenes itself (`tools/drive.py`, "
        "docs/closed_loop.md): it plans every 0.5 s from what it sees at the pose it actually "
        "reached, a kinematic model tracks the plan at 10 Hz, the scripted agents replay their "
        "trajectories, and the episode ends at the scene's end, an at-fault collision or leaving "
        "the road. PDMS = NC x DAC x (5 TTC + 5 EP + 2 C) / 12 with NAVSIM's rules. world_model "
        "drives its plan checked against its own forecast, world_model_raw its plan as is, "
        "world_model_true_movers its plan checked against the true future movers (privileged: "
        "what a perfect mover forecast would give), world_model_camera the Camera setting's "
        "checked plan on Img2Occ's occupancy of its "
        "rendered cameras. Privileged planners read the log or the true agent boxes: references, "
        "not competitors.\n\n"
    )
    pictures = []
    for png in sorted((run / "figures").glob("closed_loop_*.png")):
        (out / "figures").mkdir(parents=True, exist_ok=True)
        (out / "figures" / png.name).write_bytes(png.read_bytes())
        behaviour = png.stem.removeprefix("closed_loop_")
        pictures.append(f"![closed loop: {behaviour}](figures/{png.name})")
    body = intro + table.read_text() + ("\n\n" + "\n\n".join(pictures) if pictures else "")
    for rrd in sorted(run.glob("closed_loop_*.rrd")):
        body += (
            f"\n\nRerun recording of {rrd.stem.removeprefix('closed_loop_')}'s episodes (every "
            f"planner, 10 Hz, agents and the logged path): `rerun {rrd}`"
        )
    return [("Closed-loop driving (interaction split)", body)]


def _planner_section(out: Path) -> list[tuple[str, str]]:
    bundle = out / "planner" / PLANNER_BUNDLE
    if not bundle.is_file():
        return []
    text = (
        f"`{bundle}`: the world model of this run with its tokenizer. Plan with it:\n\n"
        "```python\nfrom renderworld.planning import PlanRequest, load_planner\n\n"
        f'planner = load_planner("{bundle}")\n'
        "result = planner.plan(PlanRequest(occupancy, ego_displacements, command, "
        "ego_yaws=yaws))\n```\n\n"
        "Frames, units and streaming (`PlannerSession`): `docs/planner.md`."
    )
    return [("Planner", text)]


#: Each training run of the main job and the validation metric its curves show (its monitor).
_CURVES = {
    "img2occ": "val/cam/miou",
    "tokenizer": "val/miou",
    "tokenizer_camera": "val/miou",
    "world_model": "val/model/miou_avg",
    "world_model_camera": "val/model/miou_avg",
}


def _pictures(cfg: Any, out: Path) -> list[str]:
    """Markdown image lines: training curves, Img2Occ views, BEV and forecast pictures."""
    # Imported here: the main job's own process stays light until it writes the report.
    from renderworld.training.stages.world_model.pictures import BEV_PNG, MOVERS_PNG, TRAJ_PNG

    figures = []
    for run, val_key in _CURVES.items():
        png = plot_training_curves(
            out / run / "metrics.csv", out / "figures" / f"curves_{run}.png",
            keys=("train/loss", "val/loss", val_key),
        )  # fmt: skip
        if png:
            figures.append(f"![{run} training curves](figures/{png.name})")
    bev = _bev_figure(cfg, out)
    copied = [
        (out / "img2occ_eval" / "img2occ_views.png", "Img2Occ renders vs LiDAR-projected targets"),
        ("bev", "BEV GT vs reconstruction"),
        (out / "world_model_eval" / BEV_PNG,
         "BEV occupancy: GT vs Img2Occ pseudo label vs forecasts at +1/2/3 s"),
        (out / "world_model_eval" / MOVERS_PNG,
         "A window where a car moves: model, object-CV warp, GT-pose warp, GT"),
        (out / "world_model_eval" / TRAJ_PNG,
         "Planned vs GT trajectories over the BEV (3D-Occ model, CV baseline)"),
    ]  # fmt: skip
    for png, caption in copied:
        if png == "bev":
            if bev:
                figures.append(f"![{caption}](figures/{bev.name})")
            continue
        if png.is_file():
            (out / "figures").mkdir(parents=True, exist_ok=True)
            (out / "figures" / png.name).write_bytes(png.read_bytes())
            figures.append(f"![{caption}](figures/{png.name})")
    return figures


def _bev_figure(cfg: Any, out: Path) -> Path | None:
    """GT vs tokenizer reconstruction, bird's-eye view, for one mini_val frame."""
    ckpt = out / "tokenizer" / "checkpoints" / REPORTED_CHECKPOINT
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
    version = cfg.get("version") or SIM_VERSION
    frames = OccFrames(load_infos(data / "renderworld_infos" / version, "val"), data, spec)
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
