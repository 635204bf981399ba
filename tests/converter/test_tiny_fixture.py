"""The converter and datasets on the simulator's ``tiny`` fixture (real sensor layout, turns)."""

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from data_converters import ConvertOptions, create_data
from renderworld.constants import CAMERA_NAMES, COMMANDS
from renderworld.data import Img2OccDataset, OccSequenceDataset, load_infos, load_labels2d
from tests.converter.oracle import as_dict, keyframe_record, load_raw, oracle_labels, quat_to_mat

VERSION = "v1.0-mini"


@pytest.fixture(scope="module")
def converted(tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny_out")
    summary = create_data(tiny_dataset, VERSION, out=out, options=ConvertOptions(progress=False))
    return tiny_dataset, out, summary


def test_summary_and_splits(converted):
    _, _, summary = converted
    assert summary.samples_per_split == {"train": 8, "val": 8}
    assert sum(summary.commands.values()) == 16


def test_stored_labels_equal_the_devkit_chain_oracle(converted):
    root, out, _ = converted
    raw = load_raw(root, VERSION)
    infos = load_infos(out, "train")
    for i in (0, 5):
        row = infos.iloc[i]
        cameras, labels = load_labels2d(out / row["labels2d_path"])
        assert cameras == list(CAMERA_NAMES)
        for c, channel in enumerate(CAMERA_NAMES):
            expect = oracle_labels(
                root, raw, row["sample_token"], channel, (labels[c].height, labels[c].width)
            )
            got = as_dict(labels[c])
            assert got.keys() == expect.keys() and len(got) > 50, channel
            for key, (depth, label) in expect.items():
                assert got[key][0] == pytest.approx(depth, rel=1e-6)
                assert got[key][1] == label


def pose(rec):
    m = np.eye(4)
    m[:3, :3] = quat_to_mat(rec["rotation"])
    m[:3, 3] = rec["translation"]
    return m


@pytest.mark.parametrize("split, scene_cmd", [("train", "left"), ("val", "straight")])
def test_ego_future_matches_ground_truth_poses(converted, split, scene_cmd):
    root, out, _ = converted
    raw = load_raw(root, VERSION)
    infos = load_infos(out, split)
    poses = [
        pose(raw["ego_pose"][keyframe_record(raw, t, "LIDAR_TOP")["ego_pose_token"]])
        for t in infos["sample_token"]
    ]
    for i, row in infos.iterrows():
        fut = np.reshape(row["ego_future"], (6, 2))
        mask = np.asarray(row["ego_future_mask"])
        assert mask.sum() == min(6, len(infos) - 1 - i)
        for k in np.flatnonzero(mask):
            rel = np.linalg.inv(poses[i]) @ poses[i + k + 1]
            assert np.abs(fut[k] - rel[:2, 3]).max() < 0.01
    # The tiny preset: scene-0061 turns left at an intersection, scene-0103 goes straight.
    assert infos["command"].iloc[0] == scene_cmd
    assert set(infos["command"]) <= set(COMMANDS)


def test_datasets_on_tiny(converted):
    root, out, _ = converted
    ds = Img2OccDataset(out / "infos_train.parquet", root, input_size=(64, 112), adjacent_frames=1)
    batch = next(iter(DataLoader(ds, batch_size=2, num_workers=0)))
    assert batch["images"].shape == (2, 6, 3, 64, 112)
    assert batch["depth"].shape == (2, 6, 27, 48) and batch["semantics"].dtype == torch.int64
    assert batch["occ"].shape == (2, 50, 50, 4) and batch["adj_depth"].shape == (2, 12, 27, 48)
    labelled = batch["semantics"] != 255
    assert labelled.sum() > 1000 and (batch["depth"][labelled] > 1).all()
    seq = OccSequenceDataset(out / "infos_train.parquet", root, history=2, future=6)
    assert len(seq) == 1
    item = seq[0]
    assert item["occ"].shape == (8, 50, 50, 4) and item["future_traj"].shape == (6, 2)
    assert COMMANDS[item["command"]] == "left"
