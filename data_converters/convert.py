"""``create_data``: a nuScenes-format dataset -> infos parquet files + sparse 2-D labels.

Output folder (default ``<data_root>/renderworld_infos/<version>/``)::

    infos_<split>.parquet          one row per keyframe (renderworld.data.infos)
    labels2d/<scene>/<token>.npz   sparse LiDAR-projected labels (renderworld.data.labels2d)
    manifest.json                  fingerprint of what the infos were made from

Re-running skips finished work: a labels file is kept when it is newer than all its inputs
(point clouds, lidarseg files, calibration/pose tables) and was made with the same settings;
the infos are kept when the fingerprint (tables, splits.json, Occ3D files present, settings) is
unchanged. ``overwrite=True`` redoes everything. Every file is written atomically.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

from tqdm import tqdm

from data_converters.fast_index import TableIndex
from data_converters.labels import label_inputs, make_labels
from data_converters.projection import label_size_for
from data_converters.sample_infos import (
    SceneFrames,
    camera_views,
    info_rows,
    occ_path,
    scene_frames,
)
from data_converters.splits import assign_splits
from renderworld.constants import COMMANDS, LIDAR_NAME
from renderworld.data import DatasetError, NuScenesReader
from renderworld.data.infos import (
    INFOS_SCHEMA_VERSION,
    infos_file,
    infos_schema,
    load_infos,
    write_infos,
)
from renderworld.data.labels2d import read_labels2d_params, save_labels2d
from renderworld.data.occupancy_only import SIM_REPORT_NAME
from renderworld.geometry import DEVKIT_MIN_DEPTH

__all__ = ["ConvertOptions", "ConvertSummary", "create_data", "default_out_dir"]

log = logging.getLogger(__name__)
_MANIFEST = "manifest.json"


@dataclass(frozen=True)
class ConvertOptions:
    """Settings of a conversion.

    Attributes:
        label_scale: label resolution as a scale of each stored image (e.g. 0.25 -> 225x400
            for 900x1600); ignored when ``label_size`` is set.
        label_size: explicit (H, W) label resolution for every camera.
        sweeps: LiDAR sweeps taken on each side of the keyframe (depth only, label 255).
        multiframe: neighbouring keyframes on each side whose static-class points are added.
        min_depth: keep points with camera depth > this (metres; the devkit uses 1.0).
        labels: make the 2-D label files (False: infos only).
        strict_splits: fail when a scene is in no split instead of assigning it to train.
        overwrite: redo finished work.
        workers: processes for the 2-D labels (0: in this process).
        progress: show a tqdm progress bar.
    """

    label_scale: float | None = 0.25
    label_size: tuple[int, int] | None = None
    sweeps: int = 0
    multiframe: int = 0
    min_depth: float = DEVKIT_MIN_DEPTH
    labels: bool = True
    strict_splits: bool = False
    overwrite: bool = False
    workers: int = 0
    progress: bool = True

    def __post_init__(self):
        for name in ("sweeps", "multiframe", "workers"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 0:
                raise ValueError(f"{name}: expected an integer >= 0, got {value!r}")
        if self.label_size is not None:
            object.__setattr__(self, "label_size", tuple(int(x) for x in self.label_size))
            if len(self.label_size) != 2:
                raise ValueError(f"label_size: expected (H, W), got {self.label_size}")
        elif self.label_scale is None or not self.label_scale > 0:
            raise ValueError(f"label_scale: expected > 0 (or a label_size), got {self.label_scale}")
        if not self.min_depth >= 0:
            raise ValueError(f"min_depth: expected >= 0 metres, got {self.min_depth}")

    def label_params(self) -> dict:
        """The settings a labels file depends on (stored in it, compared on re-runs)."""
        size = list(self.label_size) if self.label_size else None
        return {
            "label_scale": None if size else float(self.label_scale),
            "label_size": size,
            "sweeps": self.sweeps,
            "multiframe": self.multiframe,
            "min_depth": float(self.min_depth),
            "schema_version": INFOS_SCHEMA_VERSION,
        }

    def label_size_fn(self, image_size: tuple[int, int]) -> tuple[int, int]:
        """(H, W) image -> (H_label, W_label)."""
        if self.label_size is not None:
            return label_size_for(image_size, None, self.label_size)
        return label_size_for(image_size, self.label_scale)


@dataclass
class ConvertSummary:
    """What a conversion did."""

    out_dir: Path
    samples_per_split: dict[str, int] = field(default_factory=dict)
    commands: dict[str, int] = field(default_factory=dict)
    labels_written: int = 0
    labels_skipped: int = 0
    infos_written: bool = False
    seconds: float = 0.0

    def __str__(self) -> str:
        splits = ", ".join(f"{k}: {v}" for k, v in sorted(self.samples_per_split.items()))
        cmds = ", ".join(f"{k}: {self.commands.get(k, 0)}" for k in COMMANDS)
        infos = "written" if self.infos_written else "unchanged (skipped)"
        return (
            f"create_data -> {self.out_dir}\n"
            f"  samples per split: {splits}\n"
            f"  commands: {cmds}\n"
            f"  2-D labels: {self.labels_written} written, {self.labels_skipped} up to date\n"
            f"  infos: {infos}\n"
            f"  time: {self.seconds:.1f} s"
        )


def default_out_dir(data_root: str | os.PathLike, version: str) -> Path:
    """``<data_root>/renderworld_infos/<version>``."""
    return Path(data_root) / "renderworld_infos" / version


def _labels_relpath(scene: str, token: str) -> str:
    return f"labels2d/{scene}/{token}.npz"


def _label_up_to_date(path: Path, inputs: list[Path], params: dict) -> bool:
    if not path.is_file():
        return False
    mtime = path.stat().st_mtime_ns
    if any(p.stat().st_mtime_ns >= mtime for p in inputs if p.exists()):
        return False
    try:
        return read_labels2d_params(path) == params
    except ValueError:  # DatasetError: unreadable -> remake
        return False


def _fingerprint(tables: TableIndex, scenes: list[SceneFrames], opts, splits) -> str:
    h = hashlib.sha256()
    for p in sorted(tables.reader.version_dir.glob("*.json")):
        st = p.stat()
        h.update(f"{p.name}:{st.st_size}:{st.st_mtime_ns};".encode())
    occ = [occ_path(tables, s.name, t) for s in scenes for t in s.tokens]
    h.update(json.dumps([opts.label_params(), splits, occ, opts.labels], sort_keys=True).encode())
    # Infos written by another schema (columns added or changed) are stale too.
    h.update(f"{INFOS_SCHEMA_VERSION}:{infos_schema()}".encode())
    return h.hexdigest()


# Worker state, inherited through fork (the reader's tables are not re-read per sample).
_STATE: dict = {}


def _labels_task(task) -> tuple[str, bool]:
    tables, scenes, opts = _STATE["tables"], _STATE["scenes"], _STATE["opts"]
    scene_i, frame_i, views, out_path = task
    frames = scenes[scene_i]
    params = opts.label_params()
    inputs = label_inputs(tables, frames, frame_i, opts.sweeps, opts.multiframe)
    if not opts.overwrite and _label_up_to_date(out_path, inputs, params):
        return str(out_path), False
    cameras, labels = make_labels(
        tables, frames, frame_i, views, opts.sweeps, opts.multiframe, opts.min_depth
    )
    save_labels2d(out_path, cameras, labels, params)
    return str(out_path), True


def create_data(
    data_root: str | os.PathLike,
    version: str = "v1.0-mini",
    out: str | os.PathLike | None = None,
    options: ConvertOptions | None = None,
) -> ConvertSummary:
    """Convert a nuScenes-format dataset into infos + 2-D labels.

    Args:
        data_root: dataset folder (holding ``<version>/``, ``samples/``, ``lidarseg/``, ``gts/``).
        version: dataset version, e.g. ``"v1.0-mini"``.
        out: output folder; default :func:`default_out_dir`.
        options: :class:`ConvertOptions`.

    Returns:
        :class:`ConvertSummary`.

    An occupancy-only simulated dataset (``mode=occupancy``: no images, LiDAR or lidarseg)
    converts with ``labels=False``; its infos hold the camera records' paths and sizes, though
    those files do not exist, and serve the tokenizer and world model.

    Raises:
        DatasetError: naming the file or record when the dataset is malformed, and with
            ``options.labels`` on an occupancy-only dataset (before anything is written).
    """
    start = time.perf_counter()
    opts = options or ConvertOptions()
    reader = NuScenesReader(data_root, version)
    if opts.labels and reader.occupancy_only:
        _refuse_labels_without_sensor_files(reader)
    out_dir = Path(out) if out is not None else default_out_dir(data_root, version)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = reader.scene_names()
    splits = assign_splits(names, reader.version_dir, strict=opts.strict_splits)
    tables = TableIndex(reader)
    scenes = [scene_frames(tables, name, i) for i, name in enumerate(names)]
    summary = ConvertSummary(out_dir=out_dir)

    cams = _all_camera_views(tables, scenes, opts)
    if opts.labels:
        _write_all_labels(tables, scenes, cams, out_dir, opts, summary)
    commands = _write_infos_if_stale(
        tables, scenes, cams, splits, out_dir, data_root, version, opts, summary
    )
    summary.commands = {c: commands.get(c, 0) for c in COMMANDS}
    summary.seconds = time.perf_counter() - start
    return summary


def _refuse_labels_without_sensor_files(reader: NuScenesReader) -> None:
    """The 2-D labels project LiDAR points into the camera images: neither exists here."""
    sd = reader.table("sample_data")
    lidar = sd["filename"][sd["filename"].str.startswith(f"samples/{LIDAR_NAME}/")]
    example = f"{reader.path(lidar.iloc[0])} does not exist; " if len(lidar) else ""
    raise DatasetError(
        f"labels: {reader.dataroot} is an occupancy-only dataset ({example}"
        f"{reader.dataroot / SIM_REPORT_NAME} says mode 'occupancy'): it has no camera images, "
        "LiDAR point files or lidarseg to make 2-D labels from; run with labels=false (infos "
        "for the tokenizer and world model) or simulate it with mode=full"
    )


def _all_camera_views(tables: TableIndex, scenes: list, opts: ConvertOptions) -> list[list]:
    """Cameras of every keyframe, per scene (checks images exist and match their records)."""
    total = sum(len(s) for s in scenes)
    bar = tqdm(total=total, desc="cameras", disable=not opts.progress, unit="kf")
    cams = []
    for frames in scenes:
        cams.append([camera_views(tables, t, opts.label_size_fn) for t in frames.tokens])
        bar.update(len(frames))
    bar.close()
    return cams


def _write_all_labels(tables, scenes, cams, out_dir: Path, opts, summary) -> None:
    """2-D depth / semantic labels of every keyframe's cameras (skipping up-to-date files)."""
    tasks = [
        (si, fi, cams[si][fi][1], out_dir / _labels_relpath(frames.name, tok))
        for si, frames in enumerate(scenes)
        for fi, tok in enumerate(frames.tokens)
    ]
    _STATE.update(tables=tables, scenes=scenes, opts=opts)
    bar = tqdm(total=len(tasks), desc="2-D labels", disable=not opts.progress, unit="kf")
    try:
        if opts.workers > 0 and len(tasks) > 1:
            ctx = get_context("fork")
            with ProcessPoolExecutor(opts.workers, mp_context=ctx) as pool:
                results = pool.map(_labels_task, tasks, chunksize=4)
                for _, wrote in results:
                    summary.labels_written += wrote
                    summary.labels_skipped += not wrote
                    bar.update()
        else:
            for task in tasks:
                _, wrote = _labels_task(task)
                summary.labels_written += wrote
                summary.labels_skipped += not wrote
                bar.update()
    finally:
        _STATE.clear()
        bar.close()


def _write_infos_if_stale(
    tables, scenes, cams, splits, out_dir: Path, data_root, version: str, opts, summary
) -> Counter:
    """Write the per-split infos unless the manifest's fingerprint says they are up to date.

    Returns:
        Keyframe count per driving command over all splits.
    """
    fingerprint = _fingerprint(tables, scenes, opts, splits)
    manifest_path = out_dir / _MANIFEST
    split_names = sorted(set(splits.values()))
    old = json.loads(manifest_path.read_text()) if manifest_path.is_file() else {}
    fresh = (
        not opts.overwrite
        and old.get("fingerprint") == fingerprint
        and all(infos_file(out_dir, s).is_file() for s in old.get("splits", []))
        and set(old.get("splits", [])) == set(split_names)
    )
    commands: Counter = Counter()
    if fresh:
        for s in split_names:
            df = load_infos(out_dir, s)
            summary.samples_per_split[s] = len(df)
            commands.update(df["command"].tolist())
        return commands
    by_split: dict[str, list[dict]] = {s: [] for s in split_names}
    for si, frames in enumerate(scenes):
        rel = [_labels_relpath(frames.name, t) if opts.labels else "" for t in frames.tokens]
        split = splits[frames.name]
        by_split[split] += info_rows(tables, frames, split, cams[si], rel)
    meta = {
        "data_root": str(Path(data_root).resolve()),
        "version": version,
        "label_params": opts.label_params(),
    }
    for s, rows in by_split.items():
        write_infos(rows, infos_file(out_dir, s), metadata=meta)
        summary.samples_per_split[s] = len(rows)
        commands.update(r["command"] for r in rows)
    for stale in set(old.get("splits", [])) - set(split_names):
        infos_file(out_dir, stale).unlink(missing_ok=True)
    _write_json(manifest_path, {"fingerprint": fingerprint, "splits": split_names})
    summary.infos_written = True
    return commands


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)
