"""The main job's recording: one mini_val scene with the job's own checkpoints, and the
report paragraph that links it.

``main_job_recording(out, data_root)`` is what a pipeline step calls after training; it never
fails the job for want of Rerun (it says so instead).
"""

from __future__ import annotations

import os
from pathlib import Path

from renderworld.constants import REPORTED_CHECKPOINT
from renderworld.viewer._rerun import INSTALL_HINT, rerun_available

__all__ = [
    "JOB_CHECKPOINTS",
    "JOB_RECORDING",
    "main_job_recording",
    "recording_markdown",
    "report_section",
    "split_scene",
    "view_command",
]

#: Where the main job's recording goes, relative to its output folder (its step's own folder).
JOB_RECORDING = "viewer/scene.rrd"

#: Checkpoints of the main job's runs, relative to its output folder (the ones it reports:
#: ``last.pt``, not the ``best.pt`` chosen on the split it shows).
JOB_CHECKPOINTS = {
    f"{run}_ckpt": f"{run}/checkpoints/{REPORTED_CHECKPOINT}"
    for run in ("img2occ", "tokenizer", "world_model")
}


def split_scene(infos_dir: str | os.PathLike, split: str = "val") -> str | None:
    """The first scene of a converter split (``infos_<split>.parquet``), or None without one."""
    from renderworld.data import load_infos

    try:
        names = load_infos(infos_dir, split)["scene_name"]
    except (ValueError, OSError):  # DatasetError is a ValueError
        return None
    return str(names.iloc[0]) if len(names) else None


def recording_markdown(path: Path, report_dir: Path, summary=None, skipped=()) -> str:
    """The report's paragraph: link, size, layers left out, how to open the file."""
    rel = os.path.relpath(path, report_dir)
    lines = [f"3-D recording of one mini_val scene: [{rel}]({rel})"]
    if summary is not None:
        lines[0] += (
            f" ({summary.bytes / 2**20:.1f} MiB, {summary.frames} keyframes of {summary.scene}, "
            f"written in {summary.seconds:.0f} s)."
        )
    else:
        lines[0] += f" ({Path(path).stat().st_size / 2**20:.1f} MiB)."
    lines.append(
        f"Open it with `rerun {rel}` (desktop viewer) or `rerun --web-viewer {rel}` (browser); "
        f"install the viewer with `{INSTALL_HINT}`."
    )
    lines += [f"Layer left out: {x}." for x in skipped]
    return "\n\n".join(lines)


def view_command(python: str, out: Path, data_root: Path, version: str = "v1.0-mini") -> tuple:
    """The main job's step command: ``tools/view.py`` on the val split's first scene with the
    job's checkpoints (:data:`JOB_CHECKPOINTS`), writing ``<out>/`` :data:`JOB_RECORDING`."""
    ckpts = [f"{k}={Path(out) / v}" for k, v in JOB_CHECKPOINTS.items()]
    return (
        python, "tools/view.py", f"data_root={data_root}", f"version={version}", "split=val",
        f"out={Path(out) / JOB_RECORDING}", *ckpts,
    )  # fmt: skip


def report_section(out: str | os.PathLike) -> str:
    """The report's paragraph for ``<out>/`` :data:`JOB_RECORDING`: a link and how to open it,
    or one line saying why there is none."""
    path = Path(out) / JOB_RECORDING
    if path.is_file():
        return recording_markdown(path, Path(out))
    if not rerun_available():
        return f"No 3-D recording: rerun-sdk is not installed ({INSTALL_HINT})."
    return f"No 3-D recording: {JOB_RECORDING} was not written (see the viewer step's log)."


def main_job_recording(
    out: str | os.PathLike,
    data_root: str | os.PathLike,
    version: str = "v1.0-mini",
    scene: str | None = None,
    filename: str = JOB_RECORDING,
    infos_dir: str | os.PathLike | None = None,
    device: str = "cpu",
    log=print,
) -> str:
    """Write ``<out>/<filename>`` for a mini_val scene with the job's checkpoints.

    Args:
        out: the main job's output folder (holding ``img2occ/``, ``tokenizer/``,
            ``world_model/`` runs; :data:`JOB_CHECKPOINTS`) where the report is written.
        data_root: the dataset the job ran on.
        version: dataset version.
        scene: scene to record (default: the first scene of the ``val`` split).
        filename: the recording's name inside ``out``.
        infos_dir: the converter's infos (default ``<data_root>/renderworld_infos/<version>``).
        device: where the models run.
        log: receives progress and skip lines.

    Returns:
        The report paragraph (markdown): a link and how to open it, or one line saying why
        no recording was written (rerun-sdk not installed).
    """
    out, data_root = Path(out), Path(data_root)
    if not rerun_available():
        return f"No 3-D recording: rerun-sdk is not installed ({INSTALL_HINT})."
    from renderworld.viewer.checkpoints import load_viewer_models
    from renderworld.viewer.recording import write_scene_recording

    infos_dir = Path(infos_dir or data_root / "renderworld_infos" / version)
    scene = scene or split_scene(infos_dir, "val")
    paths = {k: out / v for k, v in JOB_CHECKPOINTS.items()}
    models = load_viewer_models(**paths, device=device)
    summary = write_scene_recording(
        data_root, out / filename, scene=scene, version=version, infos_dir=infos_dir,
        reasons=models.reasons, device=device, log=log, **models,
    )  # fmt: skip
    return recording_markdown(summary.path, out, summary, summary.skipped)
