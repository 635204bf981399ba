"""Img2OccDataset and OccSequenceDataset: shapes/dtypes, geometry, windows, errors."""

import numpy as np
import pandas as pd
import pytest
import torch
from PIL import Image
from torch.utils.data import DataLoader

from data_converters import ConvertOptions, create_data
from renderworld.constants import COMMANDS, FREE_ID, GRIDS, GridSpec
from renderworld.data import (
    DatasetError,
    Img2OccDataset,
    OccSequenceDataset,
    downsample_mask,
    downsample_occupancy,
    load_infos,
    load_labels2d,
    load_occ3d_labels,
    save_occ3d_labels,
)
from renderworld.data.infos import stack_column
from renderworld.geometry import invert_pose, project_points
from renderworld.world.ego import displacements_from_poses, frame_poses_from_poses
from tests.converter.datasets_for_tests import VERSION, build, build_and_convert

C = 6


@pytest.fixture(scope="module")
def train(left_turn):
    root, out = left_turn
    return root, out / "infos_train.parquet"


def test_img2occ_item_shapes_and_dtypes(train):
    root, infos = train
    ds = Img2OccDataset(infos, root, input_size=(64, 96))
    assert len(ds) == 8
    item = ds[2]
    expect = {
        "images": ((C, 3, 64, 96), torch.float32),
        "intrinsics": ((C, 3, 3), torch.float32),
        "render_intrinsics": ((C, 3, 3), torch.float32),
        "cam_to_ego": ((C, 4, 4), torch.float32),
        "depth": ((C, 61, 102), torch.float32),
        "semantics": ((C, 61, 102), torch.int64),
        "occ": ((50, 50, 4), torch.uint8),
        "mask_camera": ((50, 50, 4), torch.bool),
        "mask_lidar": ((50, 50, 4), torch.bool),
    }
    for key, (shape, dtype) in expect.items():
        assert tuple(item[key].shape) == shape and item[key].dtype == dtype, key
    assert item["images"].min() >= 0 and item["images"].max() <= 1
    sem, depth = item["semantics"], item["depth"]
    assert ((sem == 255) == (depth == 0)).all()  # keyframe points all carry a label
    assert set(sem.unique().tolist()) <= set(range(17)) | {255}
    assert item["meta"] == {"sample_token": ds.infos.at[2, "sample_token"], "scene": "scene-0061"}


def test_img2occ_geometry(train):
    root, infos_path = train
    ds = Img2OccDataset(infos_path, root, input_size=(64, 96))
    infos = load_infos(infos_path)
    item = ds[3]
    row = infos.iloc[3]
    for c in range(C):
        k = np.reshape(row[f"cam{c}_intrinsics"], (3, 3))
        s = np.reshape(row[f"cam{c}_sensor2ego"], (4, 4))
        e_cam = np.reshape(row[f"cam{c}_ego2global"], (4, 4))
        e_lidar = np.reshape(row["ego2global"], (4, 4))
        np.testing.assert_allclose(
            item["cam_to_ego"][c].numpy(), np.linalg.inv(e_lidar) @ e_cam @ s, atol=1e-5
        )
        sx, sy = 96 / 408, 64 / 245
        np.testing.assert_allclose(
            item["intrinsics"][c].numpy(), np.diag([sx, sy, 1.0]) @ k, rtol=1e-6
        )
        np.testing.assert_allclose(
            item["render_intrinsics"][c].numpy(), np.diag([102 / 408, 61 / 245, 1.0]) @ k, rtol=1e-6
        )
    # Dense maps are the stored sparse labels.
    _, labels = load_labels2d(ds.labels_root / row["labels2d_path"])
    for c, lab in enumerate(labels):
        np.testing.assert_array_equal(item["depth"][c, lab.v, lab.u].numpy(), lab.depth)
        np.testing.assert_array_equal(item["semantics"][c, lab.v, lab.u].numpy(), lab.label)
        assert (item["depth"][c] > 0).sum() == len(lab)


def test_occ_on_the_configured_grid(train):
    root, infos = train
    full = Img2OccDataset(infos, root, input_size=(32, 48), grid="occ3d")[0]
    gt = load_occ3d_labels(root / load_infos(infos)["occ_path"].iloc[0])
    np.testing.assert_array_equal(full["occ"].numpy(), gt.semantics)
    quarter = Img2OccDataset(infos, root, input_size=(32, 48), grid=GRIDS["quarter"])[0]
    np.testing.assert_array_equal(
        quarter["occ"].numpy(), downsample_occupancy(gt.semantics, (4, 4, 2))
    )
    np.testing.assert_array_equal(
        quarter["mask_camera"].numpy(), downsample_mask(gt.mask_camera, (4, 4, 2))
    )
    assert (quarter["occ"][:, :, 0] == 11).all() and (quarter["occ"][:, :, 1:] == FREE_ID).all()


def test_dataloader_collates_batches_of_two(train):
    root, infos = train
    ds = Img2OccDataset(infos, root, input_size=(32, 48), adjacent_frames=1)
    batch = next(iter(DataLoader(ds, batch_size=2, num_workers=0)))
    assert batch["images"].shape == (2, C, 3, 32, 48)
    assert batch["adj_depth"].shape == (2, 2 * C, 61, 102)
    assert batch["occ"].shape == (2, 50, 50, 4)
    assert len(batch["meta"]["sample_token"]) == 2
    seq = OccSequenceDataset(infos, root, history=3, future=2)
    sb = next(iter(DataLoader(seq, batch_size=2, num_workers=0)))
    assert sb["occ"].shape == (2, 5, 50, 50, 4) and sb["command"].shape == (2,)
    assert sb["future_boxes"].shape[:2] == (2, 2)


def test_adjacent_frames_are_clamped_and_in_the_current_ego_frame(train):
    root, infos_path = train
    ds = Img2OccDataset(infos_path, root, input_size=(32, 48), adjacent_frames=2)
    first = ds[0]
    assert first["adj_cam_to_ego"].shape == (4 * C, 4, 4)
    # Frame 0: offsets -2, -1 clamp to frame 0 itself.
    for j in range(2):
        np.testing.assert_allclose(
            first["adj_cam_to_ego"][j * C : (j + 1) * C], first["cam_to_ego"], atol=1e-6
        )
        assert torch.equal(first["adj_depth"][j * C : (j + 1) * C], first["depth"])
    # Frame 4: offset +1 (block 2) is frame 5's cameras, expressed in frame 4's ego frame.
    infos = load_infos(infos_path)
    item, nxt = ds[4], ds[5]
    e4 = stack_column(infos, "ego2global", (4, 4))[4]
    e5 = stack_column(infos, "ego2global", (4, 4))[5]
    expect = invert_pose(e4) @ e5 @ nxt["cam_to_ego"].double().numpy()
    np.testing.assert_allclose(item["adj_cam_to_ego"][2 * C : 3 * C].numpy(), expect, atol=1e-4)
    assert torch.equal(item["adj_semantics"][2 * C : 3 * C], nxt["semantics"])


def test_resized_image_and_scaled_intrinsics_agree(tmp_path):
    root = build(tmp_path / "ds", num_samples=2, num_points=50)
    out = create_data(root, VERSION, options=ConvertOptions(progress=False)).out_dir
    infos = load_infos(out, "train")
    k = np.reshape(infos["cam0_intrinsics"].iloc[0], (3, 3))
    point = np.array([[1.2, 0.4, 10.0]])  # camera frame of CAM_FRONT
    uv, _, _ = project_points(point, k)
    u, v = uv[0]
    # Paint a bright 7x7 square centred on the projected pixel.
    img = np.zeros((245, 408, 3), np.uint8)
    iu, iv = int(np.floor(u)), int(np.floor(v))
    img[iv - 3 : iv + 4, iu - 3 : iu + 4] = 255
    Image.fromarray(img).save(root / infos["cam0_path"].iloc[0], format="PNG")
    ds = Img2OccDataset(infos, root, input_size=(98, 204), labels_root=out)
    item = ds[0]
    uv_in, _, _ = project_points(point, item["intrinsics"][0].double().numpy())
    np.testing.assert_allclose(uv_in[0] / [204, 98], [u / 408, v / 245], rtol=1e-6)
    bright = item["images"][0].mean(0).numpy()
    ys, xs = np.nonzero(bright > 0.5)
    centre = np.array([xs.mean() + 0.5, ys.mean() + 0.5])  # pixel centres at i + 0.5
    np.testing.assert_allclose(centre, [(iu + 0.5) * 0.5, (iv + 0.5) * 0.4], atol=0.6)


def test_render_size_rebinning_equals_projecting_at_that_size(tmp_path):
    root = build(tmp_path / "ds", num_samples=2, num_points=2000)
    big = create_data(
        root,
        VERSION,
        out=tmp_path / "big",
        options=ConvertOptions(progress=False, label_size=(240, 400)),
    ).out_dir
    small = create_data(
        root,
        VERSION,
        out=tmp_path / "small",
        options=ConvertOptions(progress=False, label_size=(120, 200)),
    ).out_dir
    rebinned = Img2OccDataset(
        big / "infos_train.parquet", root, input_size=(32, 48), render_size=(120, 200)
    )[1]
    direct = Img2OccDataset(small / "infos_train.parquet", root, input_size=(32, 48))[1]
    assert torch.equal(rebinned["semantics"], direct["semantics"])
    assert torch.equal(rebinned["depth"], direct["depth"])
    assert torch.allclose(rebinned["render_intrinsics"], direct["render_intrinsics"])


def test_missing_files_name_the_file(tmp_path):
    root = tmp_path / "ds"
    out = build_and_convert(root, num_samples=2, num_points=50)
    infos = load_infos(out, "train")
    ds = Img2OccDataset(infos, root, input_size=(32, 48))
    gt = root / infos["occ_path"].iloc[1]
    gt.unlink()
    with pytest.raises(DatasetError, match=rf"{infos['sample_token'].iloc[1]}/labels.npz: Occ3D"):
        ds[1]
    image = root / infos["cam4_path"].iloc[0]
    image.unlink()
    with pytest.raises(DatasetError, match=rf"{image.name}: image file is missing"):
        ds[0]
    labels = out / infos["labels2d_path"].iloc[1]
    labels.write_bytes(b"junk")
    with pytest.raises(DatasetError, match=rf"{labels.name}: not a readable .npz"):
        Img2OccDataset(infos, root, load_occ=False)[1]


def test_sequence_items_and_windows(train, left_turn):
    root, out = left_turn
    both = pd.concat([load_infos(out, "train"), load_infos(out, "val")], ignore_index=True)
    both.attrs["infos_dir"] = str(out)
    seq = OccSequenceDataset(both, root, history=3, future=3)
    assert len(seq) == 2 * (8 - 6 + 1)  # windows of 6 in two scenes of 8
    for i in range(len(seq)):
        tokens = seq[i]["meta"]["sample_tokens"]
        scenes = set(both.set_index("sample_token").loc[tokens, "scene_name"])
        assert len(scenes) == 1  # never across scenes
    item = seq[1]
    assert item["occ"].shape == (6, 50, 50, 4) and item["occ"].dtype == torch.uint8
    assert item["mask_camera"].dtype == torch.bool
    assert item["ego_displacements"].shape == (5, 2) and item["future_traj"].shape == (3, 2)
    assert item["future_mask"].tolist() == [True] * 3
    rows = both.set_index("sample_token").loc[item["meta"]["sample_tokens"]]
    poses = stack_column(rows, "ego2global", (4, 4))
    disp = item["ego_displacements"].numpy()
    np.testing.assert_allclose(disp, displacements_from_poses(poses, current=2), atol=1e-5)
    np.testing.assert_allclose(np.cumsum(disp[2:], axis=0), item["future_traj"].numpy(), atol=1e-5)
    hist = item["history_poses"].numpy()
    assert hist.shape == (3, 3)
    np.testing.assert_allclose(hist, frame_poses_from_poses(poses, current=2)[:3], atol=1e-5)
    assert hist[:2, 2].max() < 0  # a left turn: earlier headings lie to the right (yaw < 0)
    # The future frames' poses (where each future occupancy lies): the same rule's other rows.
    fut = item["future_poses"].numpy()
    np.testing.assert_allclose(fut, frame_poses_from_poses(poses, current=2)[3:], atol=1e-5)
    np.testing.assert_array_equal(fut[:, :2], item["future_traj"].numpy())
    assert fut[:, 2].min() > 0  # still turning left: later headings lie to the left
    last = rows.iloc[2]
    np.testing.assert_allclose(
        item["future_traj"].numpy(), np.reshape(last["ego_future"], (6, 2))[:3], atol=1e-5
    )
    assert COMMANDS[item["command"]] == last["command"]
    boxes = np.asarray([list(f[0]) for f in last["future_boxes"][1:4]])
    np.testing.assert_allclose(item["future_boxes"][:, 0].numpy(), boxes, rtol=1e-6, atol=1e-5)
    assert item["future_boxes_mask"].all()
    # The current frame's boxes, and one road user's instance index in every frame.
    np.testing.assert_allclose(
        item["current_boxes"][0].numpy(), list(last["future_boxes"][0][0]), rtol=1e-6, atol=1e-5
    )
    assert item["current_boxes_mask"][0]
    assert (item["future_boxes"][:, 0, 6] == item["current_boxes"][0, 6]).all()


def test_sequence_reads_exported_pseudo_labels(train, tmp_path):
    root, infos_path = train
    infos = load_infos(infos_path)
    export = tmp_path / "export" / "gts"
    for scene, token in zip(infos["scene_name"], infos["sample_token"]):
        sem = np.full((50, 50, 4), FREE_ID, np.uint8)
        sem[0, 0, 0] = 7
        save_occ3d_labels(
            export / scene / token / "labels.npz", sem, np.ones_like(sem), np.zeros_like(sem)
        )
    for occ_root in (export, export.parent):  # the gts folder itself or its parent
        item = OccSequenceDataset(infos, root, history=2, future=1, occ_root=occ_root)[0]
        assert (item["occ"][:, 0, 0, 0] == 7).all() and (item["occ"] != 7).sum() > 0
        assert not item["mask_camera"].any()
    with pytest.raises(DatasetError, match=r"is not an integer down-sampling"):
        OccSequenceDataset(infos, root, history=2, future=1, occ_root=export, grid="occ3d")[0]


def test_validation_messages(train):
    root, infos = train
    with pytest.raises(ValueError, match=r"history/future: windows of 11 keyframes need a scene"):
        OccSequenceDataset(infos, root)  # default 5 + 6 frames; scenes have 8
    with pytest.raises(ValueError, match=r"future: expected an integer in 0..6, got 7"):
        OccSequenceDataset(infos, root, history=1, future=7)
    with pytest.raises(ValueError, match=r"input_size: expected \(H, W\)"):
        Img2OccDataset(infos, root, input_size=64)
    with pytest.raises(ValueError, match=r"adjacent_frames: expected an integer >= 0"):
        Img2OccDataset(infos, root, adjacent_frames=-1)
    other = GridSpec("x", (-50.0, -50.0, -1.0), (50.0, 50.0, 5.4), (50, 50, 4))
    with pytest.raises(ValueError, match=r"grid: x range .* differs from Occ3D's"):
        Img2OccDataset(infos, root, grid=other)
    with pytest.raises(ValueError, match=r"grid: unknown grid 'tiny'"):
        Img2OccDataset(infos, root, grid="tiny")
    with pytest.raises(TypeError, match=r"infos: expected a parquet path or a DataFrame"):
        Img2OccDataset(42, root)
    with pytest.raises(DatasetError, match=r"infos file not found"):
        Img2OccDataset(root / "nope.parquet", root)
    with pytest.raises(IndexError, match="index 8 out of range"):
        Img2OccDataset(infos, root)[8]


def test_jpeg_draft_decoding_keeps_the_pixel_mapping(tmp_path):
    root = tmp_path / "ds"
    out = build_and_convert(root, num_samples=2, num_points=50)
    infos = load_infos(out, "train")
    # Replace CAM_FRONT by an 800x448 JPEG (divisible by 8) with a bright square at (300, 200).
    img = np.full((448, 800, 3), 20, np.uint8)
    img[192:208, 292:308] = 250
    path = root / infos["cam0_path"].iloc[0]
    Image.fromarray(img).save(path, format="JPEG", quality=95)
    infos.loc[0, ["cam0_width", "cam0_height"]] = [800, 448]
    ds = Img2OccDataset(infos, root, input_size=(112, 200))  # draft decodes at 1/4 (200x112)
    got = ds[0]["images"][0].mean(0).numpy()
    with Image.open(path) as im:
        ref = np.asarray(im.convert("RGB").resize((200, 112), Image.Resampling.BILINEAR))
    assert np.abs(got - ref.mean(-1) / 255).mean() < 0.02
    ys, xs = np.nonzero(got > 0.5)
    np.testing.assert_allclose([xs.mean() + 0.5, ys.mean() + 0.5], [300 / 4, 200 / 4], atol=0.3)
    k = ds[0]["intrinsics"][0].numpy()
    k0 = np.reshape(infos["cam0_intrinsics"].iloc[0], (3, 3))
    np.testing.assert_allclose(k[0], k0[0] / 4, rtol=1e-6)
