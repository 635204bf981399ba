"""Build tiny, valid nuScenes-format datasets in a folder, for reader tests.

Deliberately hand-written and minimal (one log, one scene, LIDAR_TOP + CAM_FRONT), so each
malformed-dataset test can break exactly one thing. Realistic data comes from the simulator.
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


def build_tiny_dataset(root: Path, num_samples: int = 3, num_points: int = 50) -> dict:
    """Write a valid dataset with one scene of ``num_samples`` keyframes.

    Returns:
        dict with ``tables`` (the records written) and handy tokens.
    """
    rng = np.random.default_rng(0)
    root.mkdir(parents=True, exist_ok=True)
    categories = [
        {"token": _tok("cat", i), "name": n, "description": n, "index": i}
        for i, n in enumerate(LIDARSEG_CLASSES)
    ]
    sensors = [
        {"token": _tok("sen", 0), "channel": "LIDAR_TOP", "modality": "lidar"},
        {"token": _tok("sen", 1), "channel": "CAM_FRONT", "modality": "camera"},
    ]
    calib = [
        {"token": _tok("cs", 0), "sensor_token": sensors[0]["token"], "translation": LIDAR_T,
         "rotation": LIDAR_Q, "camera_intrinsic": []},
        {"token": _tok("cs", 1), "sensor_token": sensors[1]["token"], "translation": CAM_T,
         "rotation": CAM_Q, "camera_intrinsic": K},
    ]  # fmt: skip
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
    for i in range(num_samples):
        ts = 1532402927647951 + i * 500000
        s_tok = _tok("smp", i)
        samples.append({"token": s_tok, "timestamp": ts, "scene_token": _tok("scn", 0),
                        "prev": _tok("smp", i - 1) if i else "",
                        "next": _tok("smp", i + 1) if i < num_samples - 1 else ""})  # fmt: skip
        for c, (channel, ext) in enumerate([("LIDAR_TOP", "pcd.bin"), ("CAM_FRONT", "jpg")]):
            sd_tok = _tok(f"sd{c}", i)
            sd_ts = ts + 10000 * c
            fname = f"samples/{channel}/n015__{channel}__{sd_ts}.{ext}"
            ego_poses.append({"token": sd_tok, "translation": [100.0 + 5 * i, 50.0, 0.0],
                              "rotation": [1.0, 0.0, 0.0, 0.0], "timestamp": sd_ts})  # fmt: skip
            sample_data.append({
                "token": sd_tok, "sample_token": s_tok, "ego_pose_token": sd_tok,
                "calibrated_sensor_token": calib[c]["token"], "filename": fname,
                "fileformat": ext.split(".")[0], "width": 0 if c == 0 else 408,
                "height": 0 if c == 0 else 245, "timestamp": sd_ts, "is_key_frame": True,
                "prev": _tok(f"sd{c}", i - 1) if i else "",
                "next": _tok(f"sd{c}", i + 1) if i < num_samples - 1 else "",
            })  # fmt: skip
            (root / "samples" / channel).mkdir(parents=True, exist_ok=True)
            if c == 0:
                pts = rng.normal(size=(num_points, 5)).astype("<f4")
                pts.tofile(root / fname)
                lfile = f"lidarseg/{VERSION}/{sd_tok}_lidarseg.bin"
                (root / "lidarseg" / VERSION).mkdir(parents=True, exist_ok=True)
                labels = rng.integers(0, 32, num_points).astype(np.uint8)
                labels[:3] = [17, 24, 30]  # car, driveable_surface, vegetation
                labels.tofile(root / lfile)
                lidarseg.append({"token": sd_tok, "sample_data_token": sd_tok, "filename": lfile})
            else:
                Image.fromarray(np.zeros((245, 408, 3), np.uint8)).save(root / fname)
        anns.append({
            "token": _tok("ann", i), "sample_token": s_tok, "instance_token": _tok("ins", 0),
            "attribute_tokens": [attribute[0]["token"]], "visibility_token": "1",
            "translation": [110.0 + 5 * i, 52.0, 1.0], "size": [1.9, 4.5, 1.6],
            "rotation": [np.cos(0.25), 0.0, 0.0, np.sin(0.25)], "num_lidar_pts": 10,
            "num_radar_pts": 0, "prev": _tok("ann", i - 1) if i else "",
            "next": _tok("ann", i + 1) if i < num_samples - 1 else "",
        })  # fmt: skip
        sem = np.full((200, 200, 16), 17, np.uint8)
        sem[:, :, 0] = 11
        save_occ3d_labels(root / "gts" / "scene-0061" / s_tok / "labels.npz", sem,
                          np.ones_like(sem), np.ones_like(sem))  # fmt: skip
    instance = [{"token": _tok("ins", 0), "category_token": categories[17]["token"],
                 "nbr_annotations": num_samples, "first_annotation_token": anns[0]["token"],
                 "last_annotation_token": anns[-1]["token"]}]  # fmt: skip
    scene = [{"token": _tok("scn", 0), "name": "scene-0061", "description": "tiny",
              "log_token": log[0]["token"], "nbr_samples": num_samples,
              "first_sample_token": samples[0]["token"],
              "last_sample_token": samples[-1]["token"]}]  # fmt: skip
    tables = {
        "category": categories, "attribute": attribute, "visibility": visibility,
        "instance": instance, "sensor": sensors, "calibrated_sensor": calib,
        "ego_pose": ego_poses, "log": log, "scene": scene, "sample": samples,
        "sample_data": sample_data, "sample_annotation": anns, "map": maps,
        "lidarseg": lidarseg,
    }  # fmt: skip
    write_tables(root, tables)
    return {"tables": tables, "root": root}
