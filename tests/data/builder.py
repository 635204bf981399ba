"""Build tiny, valid nuScenes-format datasets in a folder, for reader tests.

Deliberately hand-written and minimal (one log, one scene, LIDAR_TOP + CAM_FRONT), so each
malformed-dataset test can break exactly one thing. Realistic data comes from the simulator.

Optional arguments (defaults keep the minimal dataset byte for byte): all six cameras, several
scenes, a continuous ego path (straight / left / right turn, poses evaluated at each sensor's
own timestamp), LiDAR sweeps between keyframes and points spread around the car.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

from renderworld.constants import LIDARSEG_CLASSES
from renderworld.data import save_occ3d_labels

VERSION = "v1.0-mini"
CAM_T = [1.7008, 0.0160, 1.5110]
CAM_Q = [0.49980, -0.50303, 0.49978, -0.49737]
LIDAR_T = [0.9437, 0.0, 1.8402]
LIDAR_Q = [0.70780, -0.00649, 0.01065, -0.70631]
K = [[316.6, 0.0, 204.1], [0.0, 316.6, 122.9], [0.0, 0.0, 1.0]]
IMAGE_W, IMAGE_H = 408, 245
#: Camera calibrations of vehicle n015 (docs/formats.md#sensors-and-calibration): translation,
#: rotation, (fx, cx, cy) at 1600x900, scaled by 1/4 for the builder's 408x245 images.
CAMERA_CALIB = {
    "CAM_FRONT": (CAM_T, CAM_Q, None),
    "CAM_FRONT_RIGHT": ([1.5509, -0.4934, 1.4958], [0.20603, -0.20269, 0.68245, -0.67136],
                        (1260.8, 808.0, 495.3)),
    "CAM_FRONT_LEFT": ([1.5239, 0.4946, 1.5093], [0.67573, -0.67363, 0.21214, -0.21123],
                       (1272.6, 826.6, 479.8)),
    "CAM_BACK": ([0.0283, 0.0035, 1.5791], [0.50379, -0.49740, -0.49419, 0.50455],
                 (809.2, 829.2, 481.8)),
    "CAM_BACK_LEFT": ([1.0357, 0.4848, 1.5910], [0.69242, -0.70316, -0.11648, 0.11203],
                      (1256.7, 792.1, 492.8)),
    "CAM_BACK_RIGHT": ([1.0149, -0.4806, 1.5624], [0.12281, -0.13240, -0.70043, 0.69050],
                       (1259.5, 807.3, 501.2)),
}  # fmt: skip
START_TS = 1532402927647951
EGO_SPEED = 10.0  # m/s along ego_path
TURN_RADIUS = 20.0  # m, for ego_path "left" / "right"


def _tok(kind: str, i: int) -> str:
    return f"{kind}{i:04d}".ljust(32, "0")


def write_tables(root: Path, tables: dict[str, list]) -> None:
    """Write each table as ``<root>/<VERSION>/<name>.json``."""
    vdir = root / VERSION
    vdir.mkdir(parents=True, exist_ok=True)
    for name, records in tables.items():
        (vdir / f"{name}.json").write_text(json.dumps(records, indent=1))


def read_tables(root: Path) -> dict[str, list]:
    """Read every table back (for tests that edit one)."""
    return {p.stem: json.loads(p.read_text()) for p in (root / VERSION).glob("*.json")}


def _intrinsics(channel: str) -> list[list[float]]:
    fx_cx_cy = CAMERA_CALIB[channel][2]
    if fx_cx_cy is None:
        return K
    fx, cx, cy = (v / 4 for v in fx_cx_cy)
    return [[fx, 0.0, cx], [0.0, fx, cy], [0.0, 0.0, 1.0]]


def ego_pose_at(ego_path: str, seconds: float) -> tuple[list[float], list[float]]:
    """(translation, rotation [w, x, y, z]) of the ego ``seconds`` after the path starts.

    Paths start at (100, 50, 0) heading +x at ``EGO_SPEED``; "left"/"right" turn on a circle of
    ``TURN_RADIUS`` to the left (+y) or right.
    """
    s = EGO_SPEED * seconds
    if ego_path == "straight":
        x, y, yaw = 100.0 + s, 50.0, 0.0
    elif ego_path in ("left", "right"):
        sign = 1.0 if ego_path == "left" else -1.0
        yaw = sign * s / TURN_RADIUS
        x = 100.0 + TURN_RADIUS * np.sin(abs(yaw))
        y = 50.0 + sign * TURN_RADIUS * (1.0 - np.cos(yaw))
    else:
        raise ValueError(f"ego_path: expected 'straight', 'left' or 'right', got {ego_path!r}")
    return [float(x), float(y), 0.0], [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))]


def _points(rng, num_points: int, point_range) -> np.ndarray:
    if point_range is None:
        return rng.normal(size=(num_points, 5)).astype("<f4")
    az = rng.uniform(-np.pi, np.pi, num_points)
    el = rng.uniform(np.radians(-25), np.radians(10), num_points)
    r = rng.uniform(point_range[0], point_range[1], num_points)
    pts = np.zeros((num_points, 5), "<f4")
    pts[:, 0] = r * np.cos(el) * np.cos(az)
    pts[:, 1] = r * np.cos(el) * np.sin(az)
    pts[:, 2] = r * np.sin(el)
    pts[:, 3] = rng.uniform(0, 255, num_points)
    pts[:, 4] = rng.integers(0, 32, num_points)
    return pts


def build_tiny_dataset(
    root: Path,
    num_samples: int = 3,
    num_points: int = 50,
    cameras: tuple[str, ...] = ("CAM_FRONT",),
    scene_names: tuple[str, ...] = ("scene-0061",),
    ego_path: str | None = None,
    sweeps: int = 0,
    point_range: tuple[float, float] | None = None,
) -> dict:
    """Write a valid dataset with ``num_samples`` keyframes per scene.

    Args:
        root: dataset folder.
        num_samples: keyframes per scene.
        num_points: LiDAR points per sweep.
        cameras: camera channels (e.g. ``renderworld.constants.CAMERA_NAMES`` for all six).
        scene_names: one scene per name.
        ego_path: None (default: keyframe i at (100 + 5 i, 50), every sensor of a keyframe at
            the same pose), or "straight" / "left" / "right": a continuous path at
            ``EGO_SPEED`` sampled at each sensor's own timestamp (see :func:`ego_pose_at`).
        sweeps: non-keyframe LiDAR sweeps after each keyframe (20 Hz, in ``sweeps/``).
        point_range: None (points ~ N(0, 1)) or (r_min, r_max) metres: points spread around
            the LiDAR at elevations -25..10 degrees.

    Returns:
        dict with ``tables`` (the records written) and handy tokens.
    """
    rng = np.random.default_rng(0)
    root.mkdir(parents=True, exist_ok=True)
    categories = [
        {"token": _tok("cat", i), "name": n, "description": n, "index": i}
        for i, n in enumerate(LIDARSEG_CLASSES)
    ]
    channels = [("LIDAR_TOP", "pcd.bin"), *[(c, "jpg") for c in cameras]]
    sensors = [
        {"token": _tok("sen", c), "channel": ch, "modality": "lidar" if c == 0 else "camera"}
        for c, (ch, _) in enumerate(channels)
    ]
    calib = [{"token": _tok("cs", 0), "sensor_token": sensors[0]["token"], "translation": LIDAR_T,
              "rotation": LIDAR_Q, "camera_intrinsic": []}]  # fmt: skip
    for c, ch in enumerate(cameras, start=1):
        calib.append({"token": _tok("cs", c), "sensor_token": sensors[c]["token"],
                      "translation": CAMERA_CALIB[ch][0], "rotation": CAMERA_CALIB[ch][1],
                      "camera_intrinsic": _intrinsics(ch)})  # fmt: skip
    log = [
        {
            "token": _tok("log", 0),
            "logfile": "n015-2018-07-24-11-22-45+0800",
            "vehicle": "n015",
            "date_captured": "2018-07-24",
            "location": "singapore-onenorth",
        }
    ]
    maps = [{"token": _tok("map", 0), "log_tokens": [log[0]["token"]], "category": "semantic_prior",
             "filename": f"maps/{_tok('map', 0)}.png"}]  # fmt: skip
    (root / "maps").mkdir(exist_ok=True)
    Image.fromarray(np.full((8, 8), 255, np.uint8)).save(root / maps[0]["filename"])
    visibility = [{"token": "1", "level": "v0-40", "description": "visibility 0-40%"}]
    attribute = [{"token": _tok("att", 0), "name": "vehicle.moving", "description": "moving"}]
    samples, sample_data, ego_poses, lidarseg, anns = [], [], [], [], []
    instance, scene = [], []
    sweep_records = []
    for s_idx, scene_name in enumerate(scene_names):
        first = s_idx * num_samples
        last = first + num_samples - 1
        t0 = START_TS + first * 500000
        for i in range(first, last + 1):
            ts = START_TS + i * 500000
            s_tok = _tok("smp", i)
            samples.append({"token": s_tok, "timestamp": ts, "scene_token": _tok("scn", s_idx),
                            "prev": _tok("smp", i - 1) if i > first else "",
                            "next": _tok("smp", i + 1) if i < last else ""})  # fmt: skip
            for c, (channel, ext) in enumerate(channels):
                sd_tok = _tok(f"sd{c}", i)
                sd_ts = ts + 10000 * c
                fname = f"samples/{channel}/n015__{channel}__{sd_ts}.{ext}"
                if ego_path is None:
                    trans, rot = [100.0 + 5 * i, 50.0, 0.0], [1.0, 0.0, 0.0, 0.0]
                else:
                    trans, rot = ego_pose_at(ego_path, (sd_ts - t0) * 1e-6)
                ego_poses.append({"token": sd_tok, "translation": trans,
                                  "rotation": rot, "timestamp": sd_ts})  # fmt: skip
                prev = _tok(f"sd{c}", i - 1) if i > first else ""
                nxt = _tok(f"sd{c}", i + 1) if i < last else ""
                if c == 0 and sweeps:
                    prev = _tok("sw", (i - 1) * sweeps + sweeps - 1) if i > first else ""
                    nxt = _tok("sw", i * sweeps) if i < last else ""
                sample_data.append({
                    "token": sd_tok, "sample_token": s_tok, "ego_pose_token": sd_tok,
                    "calibrated_sensor_token": calib[c]["token"], "filename": fname,
                    "fileformat": ext.split(".")[0], "width": 0 if c == 0 else IMAGE_W,
                    "height": 0 if c == 0 else IMAGE_H, "timestamp": sd_ts, "is_key_frame": True,
                    "prev": prev, "next": nxt,
                })  # fmt: skip
                (root / "samples" / channel).mkdir(parents=True, exist_ok=True)
                if c == 0:
                    pts = _points(rng, num_points, point_range)
                    pts.tofile(root / fname)
                    lfile = f"lidarseg/{VERSION}/{sd_tok}_lidarseg.bin"
                    (root / "lidarseg" / VERSION).mkdir(parents=True, exist_ok=True)
                    labels = rng.integers(0, 32, num_points).astype(np.uint8)
                    labels[:3] = [17, 24, 30]  # car, driveable_surface, vegetation
                    labels.tofile(root / lfile)
                    lidarseg.append(
                        {"token": sd_tok, "sample_data_token": sd_tok, "filename": lfile}
                    )
                else:
                    Image.fromarray(np.zeros((IMAGE_H, IMAGE_W, 3), np.uint8)).save(root / fname)
            if sweeps and i < last:
                for j in range(sweeps):
                    w_tok = _tok("sw", i * sweeps + j)
                    w_ts = ts + 50000 * (j + 1)
                    w_file = f"sweeps/LIDAR_TOP/n015__LIDAR_TOP__{w_ts}.pcd.bin"
                    (root / "sweeps" / "LIDAR_TOP").mkdir(parents=True, exist_ok=True)
                    _points(rng, num_points, point_range).tofile(root / w_file)
                    trans, rot = ego_pose_at(ego_path or "straight", (w_ts - t0) * 1e-6)
                    ego_poses.append({"token": w_tok, "translation": trans, "rotation": rot,
                                      "timestamp": w_ts})  # fmt: skip
                    sweep_records.append({
                        "token": w_tok, "sample_token": s_tok,
                        "ego_pose_token": w_tok, "calibrated_sensor_token": calib[0]["token"],
                        "filename": w_file, "fileformat": "pcd", "width": 0, "height": 0,
                        "timestamp": w_ts, "is_key_frame": False,
                        "prev": _tok("sd0", i) if j == 0 else _tok("sw", i * sweeps + j - 1),
                        "next": _tok("sd0", i + 1) if j == sweeps - 1
                        else _tok("sw", i * sweeps + j + 1),
                    })  # fmt: skip
            anns.append({
                "token": _tok("ann", i), "sample_token": s_tok,
                "instance_token": _tok("ins", s_idx),
                "attribute_tokens": [attribute[0]["token"]], "visibility_token": "1",
                "translation": [110.0 + 5 * i, 52.0, 1.0], "size": [1.9, 4.5, 1.6],
                "rotation": [np.cos(0.25), 0.0, 0.0, np.sin(0.25)], "num_lidar_pts": 10,
                "num_radar_pts": 0, "prev": _tok("ann", i - 1) if i > first else "",
                "next": _tok("ann", i + 1) if i < last else "",
            })  # fmt: skip
            sem = np.full((200, 200, 16), 17, np.uint8)
            sem[:, :, 0] = 11
            save_occ3d_labels(root / "gts" / scene_name / s_tok / "labels.npz", sem,
                              np.ones_like(sem), np.ones_like(sem))  # fmt: skip
        instance.append({"token": _tok("ins", s_idx), "category_token": categories[17]["token"],
                         "nbr_annotations": num_samples,
                         "first_annotation_token": _tok("ann", first),
                         "last_annotation_token": _tok("ann", last)})  # fmt: skip
        scene.append({"token": _tok("scn", s_idx), "name": scene_name, "description": "tiny",
                      "log_token": log[0]["token"], "nbr_samples": num_samples,
                      "first_sample_token": _tok("smp", first),
                      "last_sample_token": _tok("smp", last)})  # fmt: skip
    sample_data += sweep_records
    tables = {
        "category": categories, "attribute": attribute, "visibility": visibility,
        "instance": instance, "sensor": sensors, "calibrated_sensor": calib,
        "ego_pose": ego_poses, "log": log, "scene": scene, "sample": samples,
        "sample_data": sample_data, "sample_annotation": anns, "map": maps,
        "lidarseg": lidarseg,
    }  # fmt: skip
    write_tables(root, tables)
    return {"tables": tables, "root": root}
