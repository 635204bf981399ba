"""What a simulation run writes: the ``full`` dataset or only what the world model reads.

``SimConfig.mode``:

- ``"full"``: camera JPEGs, LiDAR ``.pcd.bin`` sweeps with ``lidarseg`` labels, Occ3D labels,
  the 13 nuScenes tables and maps.
- ``"occupancy"``: Occ3D labels (``gts/<scene>/<sample>/labels.npz``: semantics, mask_lidar,
  mask_camera), the 13 tables (ego poses, sample_annotation boxes, calibrations, ...) and maps.
  No camera image, LiDAR point file or lidarseg (no ``lidarseg.json``) is written and camera
  images are never shaded. ``sample_data`` records are kept with the filenames the full mode
  would write (the ego_pose chain and ``sample['data']`` need them), but those files do not
  exist. The run report (``sim_report.json``: ``"mode": "occupancy"``, ``"sensor_files":
  false``) and every scene description (:data:`OCCUPANCY_ONLY`) say so.

What stays equal between the modes for the same config and seed (the world model sees the same
world):

- Occ3D semantics, ego poses, sample_data timestamps and every sample_annotation (boxes,
  attributes, instances, tokens).
- The LiDAR-derived fields: the LiDAR sweep is still ray cast (with the same random stream, it
  is the first consumer of the keyframe's generator), only not written. So ``num_lidar_pts``
  counts the simulated returns inside the box and ``visibility_token`` follows from that count
  exactly as in the full mode (``"4"`` for >= 10 points, ``"3"`` >= 5, ``"2"`` >= 1, else
  ``"1"``). ``num_radar_pts`` is 0 in both modes (no radar is simulated).
- ``mask_lidar`` and ``mask_camera``: computed from that sweep's range image and from the
  camera depth ray casts (at ``sensors.mask_camera_scale`` of the image size) as in the full
  mode, so they are identical too. They cost little next to camera shading and file writing
  (per-stage seconds in ``sim_report.json``; figures in ``docs/simulator.md``).

What the occupancy mode drops: camera shading (the ``camera`` stage and the camera effects
rain/fog/night/camera_noise, which touch only images), the moving agents' ray-casting scenes at
the six camera exposure times, and all sensor-file encoding and writing.
"""

from __future__ import annotations

from renderworld.sim.scene import SIM_MODES

__all__ = ["OCCUPANCY_ONLY", "mode_report", "scene_description_suffix", "writes_sensor_files"]

#: Marker in the scene description of an occupancy-only dataset.
OCCUPANCY_ONLY = "occupancy-only (no camera, LiDAR or lidarseg files)"


def writes_sensor_files(mode: str) -> bool:
    """Whether a run in ``mode`` writes camera images, LiDAR point files and lidarseg."""
    if mode not in SIM_MODES:
        raise ValueError(f"mode: expected one of {SIM_MODES}, got {mode!r}")
    return mode == "full"


def mode_report(mode: str) -> dict:
    """The run report's fields describing ``mode`` (merged into ``sim_report.json``)."""
    files = writes_sensor_files(mode)
    return {
        "mode": mode,
        "sensor_files": files,
        "masks": "ray-cast: mask_lidar from the simulated LiDAR sweep, mask_camera from camera "
        "depth ray casts (identical in both modes)",
        "lidar_annotation_fields": "num_lidar_pts and visibility from the simulated LiDAR sweep"
        + ("" if files else " (cast, not written; identical to the full mode)"),
    }


def scene_description_suffix(mode: str) -> str:
    """Text appended to each scene description (``""`` in the full mode)."""
    return "" if writes_sensor_files(mode) else f", {OCCUPANCY_ONLY}"
