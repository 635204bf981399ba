"""create_data end to end: infos columns, labels files, re-runs, splits, corrupt inputs, CLI."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from data_converters import ConvertOptions, create_data
from renderworld.constants import CAMERA_NAMES
from renderworld.data import (
    DatasetError,
    Img2OccDataset,
    NuScenesReader,
    load_infos,
    load_labels2d,
)
from renderworld.data.infos import infos_schema, stack_column
from tests.converter.datasets_for_tests import VERSION, build
from tests.data.builder import read_tables, write_tables

REPO = Path(__file__).resolve().parents[2]
QUIET = ConvertOptions(progress=False)


@pytest.fixture()
def small(tmp_path):
    return build(tmp_path / "ds", num_samples=3, num_points=300, ego_path="left")


def test_infos_schema_and_values(left_turn):
    root, out = left_turn
    train, val = load_infos(out, "train"), load_infos(out, "val")
    assert (len(train), len(val)) == (8, 8)
    assert set(train["scene_name"]) == {"scene-0061"} and set(val["scene_name"]) == {"scene-0103"}
    assert set(train["split"]) == {"train"} and set(val["split"]) == {"val"}
    assert pq.read_schema(out / "infos_train.parquet").names == infos_schema().names
    assert train["frame_index"].tolist() == list(range(8))
    assert train["scene_index"].tolist() == [0] * 8 and val["scene_index"].tolist() == [1] * 8
    reader = NuScenesReader(root, VERSION)
    row = train.iloc[3]
    token = row["sample_token"]
    assert row["timestamp"] == reader.table("sample").at[token, "timestamp"]
    lidar = reader.sample_data_token(token, "LIDAR_TOP")
    assert row["lidar_token"] == lidar and (root / row["lidar_path"]).is_file()
    np.testing.assert_array_equal(
        stack_column(train, "ego2global", (4, 4))[3], reader.ego_to_global(lidar)
    )
    np.testing.assert_array_equal(np.reshape(row["lidar2ego"], (4, 4)), reader.sensor_to_ego(lidar))
    for c, cam in enumerate(CAMERA_NAMES):
        sd = reader.sample_data_token(token, cam)
        assert row[f"cam{c}_path"] == reader.table("sample_data").at[sd, "filename"]
        assert (root / row[f"cam{c}_path"]).is_file()
        assert (row[f"cam{c}_width"], row[f"cam{c}_height"]) == (408, 245)
        assert row[f"cam{c}_timestamp"] == reader.timestamp(sd) != row["timestamp"]
        np.testing.assert_array_equal(
            np.reshape(row[f"cam{c}_intrinsics"], (3, 3)), reader.intrinsics(sd)
        )
        np.testing.assert_array_equal(
            np.reshape(row[f"cam{c}_sensor2ego"], (4, 4)), reader.sensor_to_ego(sd)
        )
        # The camera's own ego pose (it moved since the LiDAR timestamp).
        cam_pose = np.reshape(row[f"cam{c}_ego2global"], (4, 4))
        np.testing.assert_array_equal(cam_pose, reader.ego_to_global(sd))
        assert np.abs(cam_pose[:3, 3] - reader.ego_to_global(lidar)[:3, 3]).max() > 0.05
    assert row["occ_path"] == f"gts/scene-0061/{token}/labels.npz"
    assert row["labels2d_path"] == f"labels2d/scene-0061/{token}.npz"
    cameras, labels = load_labels2d(out / row["labels2d_path"])
    assert cameras == list(CAMERA_NAMES)
    # Default label scale 0.25 of 245x408 -> round -> 61x102.
    assert {(lab.height, lab.width) for lab in labels} == {(61, 102)}
    assert sum(len(lab) for lab in labels) > 100
    assert all(set(np.unique(lab.label)) <= set(range(17)) for lab in labels)


def mtimes(out):
    return {p: p.stat().st_mtime_ns for p in sorted(out.rglob("*")) if p.is_file()}


def test_rerun_skips_and_overwrite_rewrites(small):
    first = create_data(small, VERSION, options=QUIET)
    out = first.out_dir
    assert first.labels_written == 3 and first.infos_written
    before = mtimes(out)
    again = create_data(small, VERSION, options=QUIET)
    assert (again.labels_written, again.labels_skipped, again.infos_written) == (0, 3, False)
    assert again.samples_per_split == first.samples_per_split
    assert again.commands == first.commands
    assert mtimes(out) == before
    # Touch one input point cloud: only that keyframe's labels are remade.
    lidar = small / load_infos(out, "train")["lidar_path"].iloc[1]
    os.utime(lidar, ns=(lidar.stat().st_atime_ns, max(before.values()) + 10**9))
    third = create_data(small, VERSION, options=QUIET)
    assert (third.labels_written, third.labels_skipped) == (1, 2)
    changed = [p for p, t in mtimes(out).items() if before.get(p) != t]
    token = load_infos(out, "train")["sample_token"].iloc[1]
    assert [p.name for p in changed] == [f"{token}.npz"]
    # overwrite=true rewrites every file.
    before = mtimes(out)
    create_data(small, VERSION, options=ConvertOptions(progress=False, overwrite=True))
    after = mtimes(out)
    assert after.keys() == before.keys() and all(after[p] != before[p] for p in before)


def test_infos_of_another_schema_are_rewritten(small, monkeypatch):
    import pyarrow as pa

    import data_converters.convert as convert

    create_data(small, VERSION, options=QUIET)
    schema = convert.infos_schema()
    older = pa.schema([f for f in schema if f.name != "scene_description"])
    monkeypatch.setattr(convert, "infos_schema", lambda: older)  # as if an older release wrote it
    assert create_data(small, VERSION, options=QUIET).infos_written
    monkeypatch.setattr(convert, "infos_schema", lambda: schema)
    assert create_data(small, VERSION, options=QUIET).infos_written  # not read, rewritten


def test_changed_settings_remake_labels(small):
    create_data(small, VERSION, options=QUIET)
    redo = create_data(small, VERSION, options=ConvertOptions(progress=False, label_size=(30, 40)))
    assert redo.labels_written == 3 and redo.infos_written
    out = redo.out_dir
    _, labels = load_labels2d(out / load_infos(out, "train")["labels2d_path"].iloc[0])
    assert {(lab.height, lab.width) for lab in labels} == {(30, 40)}


def test_splits_json_and_unlisted_scenes(tmp_path, caplog):
    root = build(
        tmp_path / "ds",
        num_samples=2,
        num_points=50,
        scene_names=("scene-0061", "scene-9001", "scene-9002"),
    )
    summary = create_data(root, VERSION, options=QUIET)
    assert summary.samples_per_split == {"train": 6}  # unlisted scenes default to train
    assert "in no split" in caplog.text and "scene-9001" in caplog.text
    with pytest.raises(DatasetError, match=r"2 scene\(s\) are in no split .*scene-9001"):
        create_data(root, VERSION, options=ConvertOptions(progress=False, strict_splits=True))
    (root / VERSION / "splits.json").write_text(
        json.dumps({"train": ["scene-0061", "scene-9002"], "val": ["scene-9001"]})
    )
    summary = create_data(root, VERSION, options=QUIET)
    assert summary.samples_per_split == {"train": 4, "val": 2} and summary.infos_written
    assert set(load_infos(summary.out_dir, "val")["scene_name"]) == {"scene-9001"}
    (root / VERSION / "splits.json").write_text(
        json.dumps({"train": ["scene-0061"], "val": ["scene-0061"]})
    )
    with pytest.raises(DatasetError, match=r"splits.json: scene 'scene-0061' is listed in both"):
        create_data(root, VERSION, options=QUIET)


def test_missing_image_names_the_file(small):
    reader = NuScenesReader(small, VERSION)
    token = reader.scene_samples("scene-0061")[1]
    image = reader.image_path(reader.sample_data_token(token, "CAM_BACK_LEFT"))
    image.unlink()
    with pytest.raises(DatasetError, match=rf"{image.name}: image file is missing"):
        create_data(small, VERSION, options=QUIET)


def test_wrong_image_size_names_the_file(small):
    reader = NuScenesReader(small, VERSION)
    image = reader.image_path(
        reader.sample_data_token(reader.scene_samples("scene-0061")[0], "CAM_FRONT")
    )
    from PIL import Image

    Image.new("RGB", (100, 50)).save(image, format="JPEG")
    with pytest.raises(DatasetError, match=rf"{image.name}: image is 100x50 but sample_data"):
        create_data(small, VERSION, options=QUIET)


def test_lidar_of_wrong_size_names_the_file(small):
    reader = NuScenesReader(small, VERSION)
    lidar = reader.path(
        reader.table("sample_data").at[
            reader.sample_data_token(reader.scene_samples("scene-0061")[2], "LIDAR_TOP"), "filename"
        ]
    )
    with open(lidar, "ab") as f:
        f.write(b"\0" * 7)
    with pytest.raises(DatasetError, match=rf"{lidar.name}: \d+ bytes is not a multiple of 5"):
        create_data(small, VERSION, options=QUIET)


def test_missing_sample_camera_is_an_error(small):
    tables = read_tables(small)
    cam_sensor = next(s["token"] for s in tables["sensor"] if s["channel"] == "CAM_BACK")
    cs = {c["token"] for c in tables["calibrated_sensor"] if c["sensor_token"] == cam_sensor}
    # Drop CAM_BACK of the middle keyframe (and relink its neighbours).
    recs = [r for r in tables["sample_data"] if r["calibrated_sensor_token"] in cs]
    mid = recs[1]
    recs[0]["next"], recs[2]["prev"] = recs[2]["token"], recs[0]["token"]
    tables["sample_data"] = [r for r in tables["sample_data"] if r["token"] != mid["token"]]
    write_tables(small, {"sample_data": tables["sample_data"]})
    with pytest.raises(DatasetError, match=rf"sample '{mid['sample_token']}' has no CAM_BACK"):
        create_data(small, VERSION, options=QUIET)


def test_options_validate():
    with pytest.raises(ValueError, match=r"sweeps: expected an integer >= 0, got -1"):
        ConvertOptions(sweeps=-1)
    with pytest.raises(ValueError, match=r"label_scale: expected > 0"):
        ConvertOptions(label_scale=0.0)
    with pytest.raises(ValueError, match=r"label_size: expected \(H, W\)"):
        ConvertOptions(label_size=(1, 2, 3))


def test_cli_runs_end_to_end(small, tmp_path):
    out = tmp_path / "out"
    cmd = [
        sys.executable,
        str(REPO / "tools" / "create_data.py"),
        f"data_root={small}",
        f"version={VERSION}",
        f"out={out}",
        "label_size=[40,60]",
        "sweeps=1",
        "progress=false",
    ]
    # The tool must find the package without the repo on PYTHONPATH; other entries (where an
    # installation keeps its packages, as on the GPU machines) stay.
    keep = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep)
            if p and Path(p).resolve() != REPO.resolve()]  # fmt: skip
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    if keep:
        env["PYTHONPATH"] = os.pathsep.join(keep)
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "samples per split: train: 3" in proc.stdout
    assert "commands: left: 1, right: 0, straight: 2" in proc.stdout
    infos = load_infos(out, "train")
    assert len(infos) == 3
    _, labels = load_labels2d(out / infos["labels2d_path"].iloc[0])
    assert (labels[0].height, labels[0].width) == (40, 60)
    assert not (tmp_path / "outputs").exists()  # Hydra leaves no run folder behind
    bad = subprocess.run(
        [*cmd[:2], f"data_root={tmp_path / 'nope'}", "progress=false"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
        timeout=300,
    )
    assert bad.returncode != 0 and "nope does not exist" in bad.stderr


def test_workers_give_identical_labels_and_labels_false(small, tmp_path):
    a = create_data(small, VERSION, out=tmp_path / "a", options=QUIET).out_dir
    b = create_data(
        small, VERSION, out=tmp_path / "b", options=ConvertOptions(progress=False, workers=2)
    ).out_dir
    for rel in load_infos(a, "train")["labels2d_path"]:
        (_, la), (_, lb) = load_labels2d(a / rel), load_labels2d(b / rel)
        for x, y in zip(la, lb):
            for key in ("u", "v", "depth", "label"):
                np.testing.assert_array_equal(getattr(x, key), getattr(y, key))
    c = create_data(
        small, VERSION, out=tmp_path / "c", options=ConvertOptions(progress=False, labels=False)
    ).out_dir
    assert set(load_infos(c, "train")["labels2d_path"]) == {""}
    assert not (c / "labels2d").exists()
    with pytest.raises(DatasetError, match=r"has no 2-D labels \(converted with labels=false\?\)"):
        Img2OccDataset(load_infos(c, "train"), small)


def test_multiframe_labels_add_static_points_only(tmp_path):
    root = build(tmp_path / "ds", num_samples=3, num_points=3000, ego_path="left")
    one = create_data(root, VERSION, out=tmp_path / "one", options=QUIET).out_dir
    multi = create_data(
        root, VERSION, out=tmp_path / "multi", options=ConvertOptions(progress=False, multiframe=1)
    ).out_dir
    rel = load_infos(one, "train")["labels2d_path"].iloc[1]
    (_, base), (_, more) = load_labels2d(one / rel), load_labels2d(multi / rel)
    added = 0
    for x, y in zip(base, more):
        bx = {(u, v): (d, lab) for u, v, d, lab in zip(x.u, x.v, x.depth, x.label)}
        by = {(u, v): (d, lab) for u, v, d, lab in zip(y.u, y.v, y.depth, y.label)}
        assert bx.keys() <= by.keys()
        for key, (d, lab) in by.items():
            if key not in bx:
                assert lab in (11, 12, 13, 14, 15, 16)  # neighbours bring static classes only
                added += 1
            else:
                assert d <= bx[key][0]  # the z-buffer keeps the nearest of both frames
    assert added > 20
