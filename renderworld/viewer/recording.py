"""``write_scene_recording``: one scene, every available layer, one ``.rrd`` file.

Open the file with ``rerun FILE`` (desktop viewer) or ``rerun --web-viewer FILE`` (browser).
Timelines: ``frame`` (keyframe index in the scene) and ``time`` (the keyframe's timestamp).
"""

from __future__ import annotations

import os
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from renderworld.viewer import data_layers as dl
from renderworld.viewer._rerun import require_rerun, transform
from renderworld.viewer.blueprint import scene_blueprint
from renderworld.viewer.model_layers import (
    GAUSSIAN_MODES,
    ForecastLayer,
    Img2OccLayer,
    TokenizerLayer,
    scene_infos,
)
from renderworld.viewer.scene import scene_frames

__all__ = ["DATA_LAYERS", "MODEL_LAYERS", "LAYERS", "RecordingSummary", "write_scene_recording"]

#: Layers read from the dataset.
DATA_LAYERS = ("ego", "cameras", "lidar", "gt_occupancy", "agents")
#: Layers computed by a model (each needs its model and the converter's infos).
MODEL_LAYERS = ("img2occ", "tokenizer", "forecast")
LAYERS = DATA_LAYERS + MODEL_LAYERS


@dataclass
class RecordingSummary:
    """What :func:`write_scene_recording` wrote.

    Attributes:
        path: the ``.rrd`` file.
        scene: scene name.
        frames: keyframes written (length of the ``frame`` timeline).
        bytes: file size.
        seconds: wall time of the whole write (models included).
        instances: {entity: instances summed over keyframes} (points, boxes, Gaussians ...).
        skipped: one line per layer left out, saying why.
    """

    path: Path
    scene: str
    frames: int
    bytes: int
    seconds: float
    instances: dict[str, int] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)

    def describe(self) -> str:
        """One line: file, size, time, frames."""
        return (
            f"{self.path} ({self.bytes / 2**20:.1f} MiB, {self.frames} keyframes of "
            f"{self.scene}, written in {self.seconds:.1f} s)"
        )


def _check_layers(layers) -> tuple[str, ...]:
    if isinstance(layers, str) or not isinstance(layers, Sequence):
        raise TypeError(f"layers: expected a list of layer names, got {type(layers).__name__}")
    unknown = [x for x in layers if x not in LAYERS]
    if unknown:
        raise ValueError(f"layers: unknown {unknown}; expected names from {list(LAYERS)}")
    return tuple(layers)


def write_scene_recording(
    data_root: str | os.PathLike,
    out: str | os.PathLike,
    *,
    scene: str | None = None,
    version: str = "v1.0-mini",
    infos_dir: str | os.PathLike | None = None,
    img2occ=None,
    tokenizer=None,
    planner=None,
    layers: Sequence[str] = LAYERS,
    start: int = 0,
    max_frames: int | None = None,
    occ_mask: str = "none",
    voxels: str = "surface",
    gaussians: str = "splats",
    min_opacity: float = 0.05,
    forecast_steps: int | None = None,
    occ_root: str | os.PathLike | None = None,
    device: str = "cpu",
    reasons: dict[str, str] | None = None,
    first_view: str = "data",
    reader=None,
    log: Callable[[str], None] | None = print,
) -> RecordingSummary:
    """Write a Rerun recording of one scene with every requested layer that has its inputs.

    A model layer without its model (None) or without infos is skipped with one line through
    ``log`` saying so (also listed in the summary); so is GT occupancy when the dataset has no
    Occ3D file for any keyframe (a few missing files are reported, not listed as skipped).

    Args:
        data_root: nuScenes-format dataset folder.
        out: the ``.rrd`` file to write (atomically: temp file + rename; parents created).
        scene: scene name (default the dataset's first scene).
        version: dataset version folder.
        infos_dir: the converter's infos folder (default
            ``<data_root>/renderworld_infos/<version>``); needed by the model layers.
        img2occ: an ``Img2Occ`` in eval mode, or None.
        tokenizer: a ``SceneTokenizer`` (``encode``/``decode``, ``.cfg.grid_shape``), or None.
        planner: a :class:`renderworld.planning.Planner`, or None.
        layers: names from :data:`LAYERS` to write.
        start: first keyframe; max_frames: how many (None: to the scene's end).
        occ_mask: GT occupancy shown: ``"none"`` (all occupied voxels), ``"camera"``, ``"lidar"``.
        voxels: ``"surface"``: every voxel layer leaves out the occupied voxels whose six
            neighbours are occupied (no viewpoint shows them; about half of a full Occ3D frame);
            ``"all"``: every occupied voxel.
        gaussians: how Img2Occ's Gaussians are drawn, one of :data:`GAUSSIAN_MODES`.
        min_opacity: Gaussians below this opacity are not drawn.
        forecast_steps: forecasts drawn per keyframe (None: all of the planner's, 6 = 3 s).
        occ_root: exported labels laid out like ``gts/`` as the tokenizer's and planner's input
            (the Camera setting); default the Occ3D GT.
        device: where the models run.
        reasons: {layer: why its model is None} (e.g. a checkpoint file that does not exist),
            printed instead of the generic skip line.
        first_view: the 3-D tab the viewer opens on: ``"data"``, ``"img2occ"``, ``"tokenizer"``
            or ``"forecast"`` (one that is written; else ValueError).
        reader: an open :class:`~renderworld.data.NuScenesReader` of ``data_root`` (optional).
        log: receives the skip lines and progress (None: silent).

    Returns:
        :class:`RecordingSummary`.

    Raises:
        ImportError: rerun-sdk is not installed (``pip install 'renderworld[viz]'``).
        ValueError / TypeError: bad arguments (named), unknown scene.
    """
    rr = require_rerun()
    import rerun.blueprint as rrb

    from renderworld.data import NuScenesReader

    t0 = time.perf_counter()
    say = log or (lambda _msg: None)
    wanted, out = _check_options(layers, gaussians, voxels, occ_mask, out)
    surface = voxels == "surface"
    reader = reader or NuScenesReader(data_root, version)
    scene = scene or reader.scene_names()[0]
    frames = scene_frames(reader, scene, start=start, max_frames=max_frames)
    skipped: list[str] = []

    def skip(layer: str, why: str) -> None:
        skipped.append(f"{layer}: {why}")
        say(f"viewer: skipping layer {layer!r}: {why}")

    models = _model_layers(
        wanted, skip, frames.scene, data_root, version, infos_dir,
        dict(img2occ=img2occ, tokenizer=tokenizer, forecast=planner), reasons or {},
        dict(gaussians=gaussians, min_opacity=min_opacity, forecast_steps=forecast_steps,
             occ_root=occ_root, device=device, surface_only=surface),
    )  # fmt: skip
    if "lidar" in wanted and not reader.has_lidarseg:
        say("viewer: no lidarseg in this dataset: LiDAR points are drawn as class 'others'")

    shown = models["forecast"].steps if "forecast" in models else 0
    blueprint = scene_blueprint(rrb, list(models), first=first_view, forecast_shown=shown)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.{uuid.uuid4().hex[:8]}.tmp.rrd"
    rec = rr.RecordingStream("renderworld", recording_id=f"{frames.scene}-{uuid.uuid4().hex[:8]}")
    try:
        rec.save(tmp, default_blueprint=blueprint)
        rec.log("/", rr.TextDocument(f"RenderWorld scene {frames.scene}"), static=True)
        dl.log_static(rec, rr)
        instances, missing = _log_frames(
            rec, rr, reader, frames, wanted, models, occ_mask, surface, say
        )
        rec.flush()
        rec.disconnect()
        os.replace(tmp, out)
        for n in missing.values():  # only GT occupancy reports missing files
            if n == len(frames):
                skip("gt_occupancy", "no Occ3D GT file for any keyframe of the scene")
            else:
                say(f"viewer: gt_occupancy: no Occ3D GT file for {n} of {len(frames)} keyframes")
    except BaseException:
        rec.disconnect()
        tmp.unlink(missing_ok=True)
        raise
    return RecordingSummary(
        path=out,
        scene=frames.scene,
        frames=len(frames),
        bytes=out.stat().st_size,
        seconds=time.perf_counter() - t0,
        instances=instances,
        skipped=skipped,
    )


def _model_layers(wanted, skip, scene, data_root, version, infos_dir, models, reasons, opts):
    """The model layers to write, built once per scene; the others reported through ``skip``."""
    todo = [m for m in MODEL_LAYERS if m in wanted]
    if not todo:
        return {}
    names = {
        "img2occ": "no Img2Occ model given (img2occ_ckpt)",
        "tokenizer": "no tokenizer given (tokenizer_ckpt)",
        "forecast": "no planner given (world_model_ckpt with tokenizer_ckpt, or planner_bundle)",
    }
    for m in [m for m in todo if models[m] is None]:
        skip(m, reasons.get(m, names[m]))
    todo = [m for m in todo if models[m] is not None]
    if not todo:
        return {}
    infos_dir = Path(infos_dir or Path(data_root) / "renderworld_infos" / version)
    try:
        infos = scene_infos(infos_dir, scene)
    except (ValueError, OSError) as err:
        for m in todo:
            skip(m, f"no converter infos for this scene ({err})")
        return {}
    dev, surface, occ_root = opts["device"], opts["surface_only"], opts["occ_root"]
    makers = {
        "img2occ": lambda: Img2OccLayer(
            models["img2occ"], infos, data_root, opts["gaussians"], opts["min_opacity"], dev,
            surface,
        ),
        "tokenizer": lambda: TokenizerLayer(
            models["tokenizer"], infos, data_root, occ_root, dev, surface
        ),
        "forecast": lambda: ForecastLayer(
            models["forecast"], infos, data_root, occ_root, opts["forecast_steps"], surface
        ),
    }  # fmt: skip
    built: dict = {}
    for m in todo:
        try:
            built[m] = makers[m]()
        except ValueError as err:  # missing inputs: 2-D labels, GT files, a too short scene
            skip(m, str(err))
    return built


def _check_options(layers, gaussians: str, voxels: str, occ_mask: str, out) -> tuple[list, Path]:
    """The wanted layers and the output path; ValueError naming a bad argument."""
    wanted = _check_layers(layers)
    if gaussians not in GAUSSIAN_MODES:
        raise ValueError(f"gaussians: expected one of {GAUSSIAN_MODES}, got {gaussians!r}")
    if voxels not in ("surface", "all"):
        raise ValueError(f"voxels: expected 'surface' or 'all', got {voxels!r}")
    if occ_mask not in ("none", "camera", "lidar"):
        raise ValueError(f"occ_mask: expected 'none', 'camera' or 'lidar', got {occ_mask!r}")
    out = Path(out)
    if out.suffix != ".rrd":
        raise ValueError(f"out: expected a .rrd file name, got {str(out)!r}")
    return wanted, out


def _log_frames(rec, rr, reader, frames, wanted, models, occ_mask, surface, say):
    """Log every keyframe's data and model layers; (instances per entity, keyframes missing).

    Returns:
        ``({entity: instances over all keyframes}, {entity: keyframes without an input file})``.
    """
    instances: dict[str, int] = {}
    missing: dict[str, int] = {}
    data_fns = {
        "ego": lambda i: {"world/ego/box": dl.log_ego(rec, rr, frames, i)},
        "cameras": lambda i: {"world/ego/cameras": dl.log_cameras(rec, rr, reader, frames, i)},
        "lidar": lambda i: {"world/ego/lidar": dl.log_lidar(rec, rr, reader, frames, i)},
        "gt_occupancy": lambda i: {
            "world/ego/occupancy/gt": dl.log_gt_occupancy(
                rec, rr, reader, frames, i, occ_mask, surface
            )
        },
        "agents": lambda i: {"world/agents": dl.log_agents(rec, rr, reader, frames, i)},
    }
    for i in range(len(frames)):
        rec.set_time("frame", sequence=frames.first_index + i)
        rec.set_time("time", timestamp=float(frames.timestamps_us[i]) * 1e-6)
        # Every ego-frame layer hangs below the ego pose, so it is logged whatever is shown.
        rec.log("world/ego", transform(rr, frames.ego_to_world[i]))
        counts: dict[str, int] = {}
        for name in wanted:
            if name in data_fns:
                counts.update(data_fns[name](i))
        for layer in models.values():
            counts.update(layer.log(rec, rr, frames, i))
        for k, v in counts.items():
            if v >= 0:
                instances[k] = instances.get(k, 0) + v
            else:  # -1: the keyframe has no input file for this layer (Occ3D GT)
                missing[k] = missing.get(k, 0) + 1
        say(f"viewer: keyframe {i + 1}/{len(frames)} of {frames.scene}")
    return instances, missing
