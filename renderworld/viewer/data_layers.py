"""Dataset layers of a recording: ego, cameras, LiDAR, GT occupancy and agent boxes.

Entity layout (``world`` = global frame shifted to the first keyframe, see ``scene.py``)::

    world                               Occ3D class names/colours (static), z up
    world/ego                           ego→world transform per keyframe (LiDAR time)
    world/ego/box                       the ego footprint box
    world/ego/cameras/<CAM>             camera→ego transform, pinhole (frustum) and JPEG image
    world/ego/lidar                     LiDAR→ego transform and points coloured by class
    world/ego/occupancy/gt              Occ3D GT: occupied voxels as boxes
    world/agents                        annotated boxes (world frame) coloured by class

Each ``log_*`` function writes one layer for keyframe ``i`` (the caller sets the time) and
returns how many instances it wrote.
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import CAMERA_NAMES, EGO_LENGTH, EGO_WIDTH, OTHERS_ID
from renderworld.geometry import invert_pose
from renderworld.viewer._rerun import class_annotations, transform
from renderworld.viewer.scene import SceneFrames
from renderworld.viewer.voxels import occupancy_boxes

__all__ = [
    "EGO_HEIGHT",
    "log_static",
    "log_ego",
    "log_cameras",
    "log_lidar",
    "log_gt_occupancy",
    "log_agents",
    "log_voxels",
]

#: Height of the drawn ego box, metres (a nominal car; the metrics use the 2-D footprint only).
EGO_HEIGHT = 1.6


def log_static(rec, rr) -> None:
    """The ``world`` frame's axes (z up) and the Occ3D class annotation context."""
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log("world", class_annotations(rr), static=True)


def log_ego(rec, rr, frames: SceneFrames, i: int) -> int:
    """``world/ego/box``: the EGO_LENGTH x EGO_WIDTH footprint centred at the ego origin (rear
    axle), as the collision metric places it (the ego pose itself is logged for every frame by
    the recording). Returns 1."""
    rec.log(
        "world/ego/box",
        rr.Boxes3D(
            centers=[[0.0, 0.0, EGO_HEIGHT / 2]],
            half_sizes=[[EGO_LENGTH / 2, EGO_WIDTH / 2, EGO_HEIGHT / 2]],
            colors=[[255, 255, 255]],
            labels=["ego"],
        ),
    )
    return 1


def log_cameras(rec, rr, reader, frames: SceneFrames, i: int, image_plane: float = 3.0) -> int:
    """The six keyframe cameras: calibrated pose relative to the keyframe's ego, pinhole
    (intrinsics, resolution; drawn as a frustum ``image_plane`` metres deep) and the JPEG
    itself (stored encoded, not decoded). Returns the number of images (6)."""
    from PIL import Image

    sample, lidar_sd = frames.sample_tokens[i], frames.lidar_tokens[i]
    ego_from_global = invert_pose(reader.ego_to_global(lidar_sd))
    for cam in CAMERA_NAMES:
        sd = reader.sample_data_token(sample, cam)
        # Cameras fire at their own times: their ego pose differs from the LiDAR keyframe's.
        ego_from_cam = ego_from_global @ reader.ego_to_global(sd) @ reader.sensor_to_ego(sd)
        path = reader.image_path(sd)
        with Image.open(path) as im:
            width, height = im.size
        entity = f"world/ego/cameras/{cam}"
        rec.log(entity, transform(rr, ego_from_cam))
        rec.log(
            entity,
            rr.Pinhole(
                image_from_camera=reader.intrinsics(sd).astype(np.float32),
                resolution=[width, height],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=float(image_plane),
            ),
        )
        rec.log(entity, rr.EncodedImage(path=path))
    return len(CAMERA_NAMES)


def log_lidar(rec, rr, reader, frames: SceneFrames, i: int, point_size: float = 1.5) -> int:
    """LIDAR_TOP points in the LiDAR frame (with its →ego transform), coloured by Occ3D class
    (lidarseg mapped to Occ3D; "others" when the dataset has no lidarseg). ``point_size`` is
    in screen points. Returns the number of points."""
    sd = frames.lidar_tokens[i]
    pts = reader.lidar_points(sd)
    if reader.has_lidarseg:
        classes = reader.lidarseg_labels(sd, occ3d=True).astype(np.uint16)
    else:
        classes = np.full(len(pts), OTHERS_ID, dtype=np.uint16)
    rec.log("world/ego/lidar", transform(rr, reader.sensor_to_ego(sd)))
    rec.log(
        "world/ego/lidar",
        rr.Points3D(
            pts[:, :3],
            class_ids=classes,
            radii=rr.Radius.ui_points(point_size),
            show_labels=False,
        ),
    )
    return len(pts)


def log_voxels(
    rec, rr, entity: str, occupancy: np.ndarray, grid=None, mask=None, surface_only=True
) -> int:
    """An occupancy volume [X, Y, Z] (ego frame) as solid boxes for its occupied voxels at
    ``entity`` (only those a viewer can see unless ``surface_only`` is False; see
    :func:`~renderworld.viewer.voxels.occupancy_boxes`). Returns the number of boxes."""
    boxes = occupancy_boxes(occupancy, grid, mask, surface_only=surface_only)
    rec.log(
        entity,
        rr.Boxes3D(
            centers=boxes.centres,
            half_sizes=boxes.half_size[None],
            class_ids=boxes.classes,
            fill_mode=rr.components.FillMode.Solid,
            show_labels=False,
        ),
    )
    return len(boxes.classes)


def log_gt_occupancy(
    rec, rr, reader, frames: SceneFrames, i: int, mask: str = "none", surface_only: bool = True
) -> int:
    """Occ3D ground truth at ``world/ego/occupancy/gt`` (occupied voxels; ``mask`` "camera"
    or "lidar" keeps only voxels observed by that sensor). Returns the number of boxes, or
    -1 when the sample has no Occ3D file."""
    if mask not in ("none", "camera", "lidar"):
        raise ValueError(f"mask: expected 'none', 'camera' or 'lidar', got {mask!r}")
    labels = reader.occ3d(frames.sample_tokens[i])
    if labels is None:
        return -1
    m = None if mask == "none" else getattr(labels, f"mask_{mask}")
    return log_voxels(
        rec, rr, "world/ego/occupancy/gt", labels.semantics, mask=m, surface_only=surface_only
    )


def log_agents(rec, rr, reader, frames: SceneFrames, i: int) -> int:
    """Annotated boxes of keyframe ``i`` at ``world/agents`` (world frame), coloured by the
    Occ3D class of their category. Returns the number of boxes."""
    boxes = reader.sample_boxes(frames.sample_tokens[i])
    if len(boxes) == 0:
        rec.log("world/agents", rr.Clear(recursive=False))
        return 0
    centres = boxes[["center_x", "center_y", "center_z"]].to_numpy(np.float64) - frames.origin
    half = boxes[["length", "width", "height"]].to_numpy(np.float64) / 2
    yaw = boxes["yaw"].to_numpy(np.float64)
    quats = np.zeros((len(boxes), 4), dtype=np.float32)  # x, y, z, w: a rotation about z
    quats[:, 2], quats[:, 3] = np.sin(yaw / 2), np.cos(yaw / 2)
    rec.log(
        "world/agents",
        rr.Boxes3D(
            centers=centres.astype(np.float32),
            half_sizes=half.astype(np.float32),
            quaternions=quats,
            class_ids=boxes["occ3d_class"].to_numpy().astype(np.uint16),
            show_labels=False,
        ),
    )
    return len(boxes)
