"""The tiny fixture is a complete, self-consistent nuScenes-format dataset."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from renderworld.constants import (
    CAMERA_NAMES,
    FREE_ID,
    LIDARSEG_CLASSES,
    MINI_TRAIN_SCENES,
    MINI_VAL_SCENES,
    NUSCENES_TABLES,
    OCC3D_GRID,
)
from renderworld.geometry import VoxelGrid, pose_matrix, transform_points
from tests.sim.helpers import OCC_LUT, by_token, lidar_keyframes, tables

FIELDS = {
    "attribute": "token name description",
    "calibrated_sensor": "token sensor_token translation rotation camera_intrinsic",
    "category": "token name description index",
    "ego_pose": "token translation rotation timestamp",
    "instance": "token category_token nbr_annotations first_annotation_token last_annotation_token",
    "log": "token logfile vehicle date_captured location",
    "map": "token log_tokens category filename",
    "sample": "token timestamp scene_token prev next",
    "sample_annotation": "token sample_token instance_token attribute_tokens visibility_token "
    "translation size rotation num_lidar_pts num_radar_pts prev next",
    "sample_data": "token sample_token ego_pose_token calibrated_sensor_token filename "
    "fileformat width height timestamp is_key_frame prev next",
    "scene": "token name description log_token nbr_samples first_sample_token last_sample_token",
    "sensor": "token channel modality",
    "visibility": "token level description",
    "lidarseg": "token sample_data_token filename",
}


@pytest.fixture(scope="module")
def t(tiny_dataset):
    return tables(tiny_dataset)


def test_every_table_and_field_present(tiny_dataset, t):
    assert set(NUSCENES_TABLES) | {"lidarseg"} == set(t)
    for name, fields in FIELDS.items():
        assert t[name], f"{name} is empty"
        for rec in t[name]:
            assert set(fields.split()) == set(rec), (name, rec)
    assert [c["name"] for c in sorted(t["category"], key=lambda c: c["index"])] == list(
        LIDARSEG_CLASSES
    )
    for m in t["map"]:
        assert (tiny_dataset / m["filename"]).exists()
    assert {s["name"] for s in t["scene"]} == {MINI_TRAIN_SCENES[0], MINI_VAL_SCENES[0]}
    report = json.loads((tiny_dataset / "sim_report.json").read_text())
    assert report["files"] > 0 and report["keyframes_per_scene"] == 8


def test_sample_data_files_sizes_and_timestamps(tiny_dataset, t):
    sd_by_sample: dict[str, dict] = {}
    for sd in t["sample_data"]:
        sd_by_sample.setdefault(sd["sample_token"], {})[sd["filename"].split("/")[1]] = sd
    poses = by_token(t["ego_pose"])
    moved = 0
    for s in t["sample"]:
        sds = sd_by_sample[s["token"]]
        assert set(sds) == {"LIDAR_TOP", *CAMERA_NAMES}
        lidar = sds["LIDAR_TOP"]
        assert s["timestamp"] == lidar["timestamp"] == poses[lidar["ego_pose_token"]]["timestamp"]
        for ch in CAMERA_NAMES:
            cam = sds[ch]
            dt = cam["timestamp"] - lidar["timestamp"]
            assert 0 < dt <= 50_000, (ch, dt)  # cameras fire as the sweep passes them
            pose = poses[cam["ego_pose_token"]]
            assert pose["timestamp"] == cam["timestamp"] and pose["translation"][2] == 0.0
            moved += pose["translation"] != poses[lidar["ego_pose_token"]]["translation"]
            with Image.open(tiny_dataset / cam["filename"]) as im:
                assert im.size == (cam["width"], cam["height"]) == (192, 108)
    assert moved > 0, "a moving ego must have distinct poses at camera times"


def test_lidar_points_format_and_labels(tiny_dataset):
    for _, _sd, pts, labels, _, _ in lidar_keyframes(tiny_dataset):
        assert 15_000 < len(pts) < 40_000 and labels.shape == (len(pts),)
        assert pts[:, 3].min() >= 0 and pts[:, 3].max() <= 255
        assert set(np.unique(pts[:, 4]).astype(int)) <= set(range(32))
        assert labels.max() < 32
        present = set(np.unique(labels).tolist())
        assert {24, 27, 28} <= present, present  # road, terrain, buildings in every sweep


def test_lidar_hits_agree_with_occ3d_semantics(tiny_dataset):
    grid = VoxelGrid(OCC3D_GRID)
    classes_seen = set()
    for sample, _, pts, labels, l2e, scene in lidar_keyframes(tiny_dataset):
        with np.load(tiny_dataset / "gts" / scene / sample["token"] / "labels.npz") as z:
            sem, m_lidar, m_cam = z["semantics"], z["mask_lidar"], z["mask_camera"]
        assert sem.shape == m_lidar.shape == m_cam.shape == (200, 200, 16)
        assert sem.dtype == m_lidar.dtype == m_cam.dtype == np.uint8
        idx, inside = grid.points_to_index(transform_points(l2e, pts[:, :3].astype(np.float64)))
        idx = idx[inside]
        got = sem[idx[:, 0], idx[:, 1], idx[:, 2]]
        agree = (got == OCC_LUT[labels[inside]]).mean()
        assert agree >= 0.95, f"{scene}/{sample['token']}: only {agree:.3f} agree"
        assert m_lidar[idx[:, 0], idx[:, 1], idx[:, 2]].all(), "hit voxels must be observed"
        assert not (m_cam & ~m_lidar).any(), "mask_camera must be a subset of mask_lidar"
        assert 0 < m_cam.sum() < m_lidar.sum() < sem.size
        assert (sem != FREE_ID).sum() > 30_000  # ground layer + solids
        classes_seen |= set(np.unique(sem).tolist())
    assert {1, 4, 7, 8, 11, 13, 14, 15, 16, FREE_ID} <= classes_seen, classes_seen


def test_annotations_chain_and_count_lidar_points(tiny_dataset, t):
    anns = by_token(t["sample_annotation"])
    for inst in t["instance"]:
        chain, tok = [], inst["first_annotation_token"]
        while tok:
            chain.append(anns[tok])
            tok = anns[tok]["next"]
        assert (
            len(chain) == inst["nbr_annotations"]
            and chain[-1]["token"] == inst["last_annotation_token"]
        )
        assert all(a["instance_token"] == inst["token"] for a in chain)
    # Recount num_lidar_pts for one keyframe from the files.
    sample, sd, pts, _, l2e, _ = next(iter(lidar_keyframes(tiny_dataset)))
    pose = by_token(t["ego_pose"])[sd["ego_pose_token"]]
    g = transform_points(pose_matrix(pose["translation"], pose["rotation"]) @ l2e,
                         pts[:, :3].astype(np.float64))  # fmt: skip
    boxes = [a for a in t["sample_annotation"] if a["sample_token"] == sample["token"]]
    assert len(boxes) > 5 and sum(b["num_lidar_pts"] > 0 for b in boxes) > 3
    for b in boxes:
        w, ln, h = b["size"]
        inv = np.linalg.inv(pose_matrix(b["translation"], b["rotation"]))
        local = transform_points(inv, g)
        inside = (np.abs(local) <= np.array([ln / 2, w / 2, h / 2])).all(1)
        assert abs(int(inside.sum()) - b["num_lidar_pts"]) <= 2, b["token"]


def test_scene_and_sample_chains(t):
    samples = by_token(t["sample"])
    for scene in t["scene"]:
        tok, n = scene["first_sample_token"], 0
        while tok:
            n += 1
            last, tok = tok, samples[tok]["next"]
        assert n == scene["nbr_samples"] == 8 and last == scene["last_sample_token"]
