"""Plain-numpy readers of a simulated dataset (independent of renderworld.data)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from renderworld.constants import LIDARSEG_TO_OCC3D
from renderworld.geometry import pose_matrix

VERSION = "v1.0-mini"
OCC_LUT = np.array([LIDARSEG_TO_OCC3D[i] for i in range(32)], dtype=np.uint8)


def tables(root: Path) -> dict[str, list[dict]]:
    """Every JSON table of the dataset by name."""
    return {p.stem: json.loads(p.read_text()) for p in sorted((root / VERSION).glob("*.json"))}


def by_token(records: list[dict]) -> dict[str, dict]:
    return {r["token"]: r for r in records}


def lidar_keyframes(root: Path):
    """Yield (sample, lidar sample_data, points [N,5], labels [N], lidar->ego [4,4], scene name)."""
    t = tables(root)
    samples, cs = by_token(t["sample"]), by_token(t["calibrated_sensor"])
    scenes = {s["token"]: s["name"] for s in t["scene"]}
    for sd in t["sample_data"]:
        if not sd["filename"].startswith("samples/LIDAR_TOP/"):
            continue
        pts = np.fromfile(root / sd["filename"], dtype="<f4").reshape(-1, 5)
        labels = np.fromfile(root / "lidarseg" / VERSION / f"{sd['token']}_lidarseg.bin", np.uint8)
        c = cs[sd["calibrated_sensor_token"]]
        sample = samples[sd["sample_token"]]
        yield (
            sample,
            sd,
            pts,
            labels,
            pose_matrix(c["translation"], c["rotation"]),
            scenes[sample["scene_token"]],
        )
