"""Malformed datasets fail with messages naming the table, token or file at fault."""

import json
import shutil

import numpy as np
import pytest

from renderworld.data import DatasetError, NuScenesReader, load_occ3d_labels
from tests.data.builder import VERSION, build_tiny_dataset, read_tables, write_tables


@pytest.fixture()
def root(tmp_path):
    build_tiny_dataset(tmp_path / "ds")
    return tmp_path / "ds"


def edit(root, table, fn):
    tables = read_tables(root)
    fn(tables[table])
    write_tables(root, {table: tables[table]})
    return tables


def first_lidar(reader):
    return reader.sample_data_token(reader.scene_samples("scene-0061")[0], "LIDAR_TOP")


def test_missing_dataroot(tmp_path):
    with pytest.raises(DatasetError, match="dataroot: folder .*nope does not exist"):
        NuScenesReader(tmp_path / "nope")


def test_missing_version_folder(root):
    with pytest.raises(DatasetError, match=r"version: folder .*v1.0-trainval does not exist"):
        NuScenesReader(root, "v1.0-trainval")


def test_missing_table(root):
    (root / VERSION / "ego_pose.json").unlink()
    with pytest.raises(DatasetError, match=r"missing table\(s\) ego_pose.json"):
        NuScenesReader(root, VERSION)


def test_invalid_json(root):
    (root / VERSION / "sensor.json").write_text("[{")
    with pytest.raises(DatasetError, match=r"sensor.json: not valid JSON"):
        NuScenesReader(root, VERSION).table("sensor")


def test_record_missing_field(root):
    edit(root, "ego_pose", lambda recs: recs[1].pop("timestamp"))
    with pytest.raises(DatasetError, match=r"ego_pose.json: record 1 .* lacks field 'timestamp'"):
        NuScenesReader(root, VERSION).table("ego_pose")


def test_duplicate_token(root):
    edit(root, "sensor", lambda recs: recs.append(dict(recs[0])))
    with pytest.raises(DatasetError, match=r"sensor.json: token '.*' appears more than once"):
        NuScenesReader(root, VERSION).table("sensor")


def test_dangling_token(root):
    def fn(recs):
        recs[2]["ego_pose_token"] = "deadbeef"

    edit(root, "sample_data", fn)
    with pytest.raises(
        DatasetError,
        match=r"sample_data.json: record '.*' has ego_pose_token='deadbeef', which is not a "
        r"token of ego_pose.json",
    ):
        NuScenesReader(root, VERSION).table("sample_data")


def test_broken_prev_next_chain(root):
    def fn(recs):
        recs[1]["prev"] = ""

    edit(root, "sample", fn)
    with pytest.raises(DatasetError, match=r"sample.json: broken prev/next chain: record"):
        NuScenesReader(root, VERSION).table("sample")


def test_scene_sample_count_mismatch(root):
    def fn(recs):
        recs[0]["nbr_samples"] = 7

    edit(root, "scene", fn)
    with pytest.raises(DatasetError, match=r"scene-0061 lists nbr_samples=7 .* chain has 3"):
        NuScenesReader(root, VERSION).scene_samples("scene-0061")


def test_sample_without_lidar_keyframe(root):
    def fn(recs):
        for r in recs:
            if r["filename"].startswith("samples/LIDAR_TOP") and r["sample_token"].startswith(
                "smp0001"
            ):
                r["is_key_frame"] = False

    edit(root, "sample_data", fn)
    reader = NuScenesReader(root, VERSION)
    with pytest.raises(DatasetError, match=r"sample 'smp0001.*' has no LIDAR_TOP keyframe"):
        reader.sample_data_token(reader.scene_samples("scene-0061")[0], "LIDAR_TOP")


def test_point_cloud_size_not_multiple_of_five(root):
    reader = NuScenesReader(root, VERSION)
    sd = first_lidar(reader)
    path = reader.path(reader.table("sample_data").at[sd, "filename"])
    with open(path, "ab") as f:
        f.write(b"\0" * 8)
    with pytest.raises(DatasetError, match=r"pcd.bin: 1008 bytes is not a multiple of 5 float32"):
        reader.lidar_points(sd)


def test_lidarseg_count_differs(root):
    reader = NuScenesReader(root, VERSION)
    sd = first_lidar(reader)
    path = root / f"lidarseg/{VERSION}/{sd}_lidarseg.bin"
    np.zeros(49, np.uint8).tofile(path)
    with pytest.raises(DatasetError, match=r"_lidarseg.bin: 49 labels but the point cloud has 50"):
        reader.lidarseg_labels(sd)


def test_lidarseg_label_out_of_range(root):
    reader = NuScenesReader(root, VERSION)
    sd = first_lidar(reader)
    np.full(50, 40, np.uint8).tofile(root / f"lidarseg/{VERSION}/{sd}_lidarseg.bin")
    with pytest.raises(DatasetError, match=r"label 40 is not a lidarseg class 0..31"):
        reader.lidarseg_labels(sd)


def test_filename_escaping_the_data_root(root):
    (root.parent / "secret.pcd.bin").write_bytes(b"\0" * 20)

    def fn(recs):
        recs[0]["filename"] = "../secret.pcd.bin"

    edit(root, "sample_data", fn)
    reader = NuScenesReader(root, VERSION)
    with pytest.raises(DatasetError, match=r"filename '../secret.pcd.bin' escapes the data root"):
        reader.lidar_points(reader.table("sample_data").index[0])
    with pytest.raises(DatasetError, match=r"filename '/etc/passwd' is absolute"):
        reader.path("/etc/passwd")


def test_missing_image_file(root):
    reader = NuScenesReader(root, VERSION)
    cam = reader.sample_data_token(reader.scene_samples("scene-0061")[0], "CAM_FRONT")
    reader.image_path(cam).unlink()
    with pytest.raises(DatasetError, match=r"CAM_FRONT__.*\.jpg: image file is missing"):
        reader.image_path(cam)


def test_malformed_occ3d_labels(root, tmp_path):
    reader = NuScenesReader(root, VERSION)
    s = reader.scene_samples("scene-0061")[0]
    path = reader.occ3d_path(s)
    np.savez_compressed(path, semantics=np.zeros((200, 200, 16), np.uint8))
    with pytest.raises(
        DatasetError, match=r"labels.npz: Occ3D labels lack key\(s\) \['mask_lidar'"
    ):
        reader.occ3d(s)
    bad_shape = tmp_path / "shape.npz"
    z = np.zeros((200, 200, 8), np.uint8)
    np.savez_compressed(bad_shape, semantics=z, mask_lidar=z, mask_camera=z)
    with pytest.raises(DatasetError, match=r"shape.npz: 'semantics' has shape \(200, 200, 8\)"):
        load_occ3d_labels(bad_shape, expected_shape=(200, 200, 16))
    bad_class = tmp_path / "cls.npz"
    np.savez_compressed(bad_class, semantics=z + 30, mask_lidar=z, mask_camera=z)
    with pytest.raises(DatasetError, match=r"cls.npz: 'semantics' holds class 30"):
        load_occ3d_labels(bad_class)
    not_npz = tmp_path / "junk.npz"
    not_npz.write_text("not a zip")
    with pytest.raises(DatasetError, match=r"junk.npz: not a readable .npz file"):
        load_occ3d_labels(not_npz)


def test_failed_load_does_not_modify_the_dataset(root):
    edit(root, "sample_data", lambda recs: recs[0].update(sample_token="nope"))
    before = {p: p.read_bytes() for p in sorted((root / VERSION).glob("*.json"))}
    with pytest.raises(DatasetError):
        NuScenesReader(root, VERSION).load_all()
    assert {p: p.read_bytes() for p in sorted((root / VERSION).glob("*.json"))} == before
    shutil.rmtree(root)


def test_table_name_is_checked(root):
    with pytest.raises(ValueError, match="name: unknown table 'samples'"):
        NuScenesReader(root, VERSION).table("samples")


def test_json_table_not_a_list(root):
    (root / VERSION / "log.json").write_text(json.dumps({"token": "x"}))
    with pytest.raises(DatasetError, match=r"log.json: expected a JSON list of records, got dict"):
        NuScenesReader(root, VERSION).table("log")
