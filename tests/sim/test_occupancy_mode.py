"""mode=occupancy: only what the world model reads, and the same world as the full mode.

Both modes simulate the tiny preset cut to 5 keyframes of 64x36 images (2 scenes, one with
rain, LiDAR noise and moving agents) into one temporary folder each.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from data_converters import ConvertOptions, create_data
from renderworld.constants import CAMERA_NAMES, FREE_ID, LIDAR_NAME
from renderworld.data import DatasetError, NuScenesReader, OccSequenceDataset, load_infos
from renderworld.data.occupancy_only import SIM_REPORT_NAME, is_occupancy_only
from renderworld.sim import REPORT_NAME, SimConfig, simulate
from renderworld.sim.modes import OCCUPANCY_ONLY, writes_sensor_files
from renderworld.sim.writer import DatasetWriter
from tests.conftest import REPO_ROOT
from tests.sim.helpers import VERSION, tables
from tools.make_fixtures import config_from_preset, sim_config

SMALL = dict(keyframes=5, image_size="64x36")
QUIET = ConvertOptions(progress=False, labels=False)


@pytest.fixture(scope="module")
def roots(tmp_path_factory):
    base = tmp_path_factory.mktemp("modes")
    out = {}
    for mode in ("full", "occupancy"):
        out[mode] = base / mode
        simulate(config_from_preset("tiny", mode=mode, **SMALL), out[mode], progress=False)
    return out


def _files(root, pattern):
    return sorted(str(p.relative_to(root)) for p in root.rglob(pattern) if p.is_file())


def _plain(value):
    """Nested lists of a parquet cell (numpy arrays of arrays) as plain Python lists."""
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    return value.item() if isinstance(value, np.generic) else value


def test_occupancy_mode_writes_no_sensor_files(roots):
    full, occ = roots["full"], roots["occupancy"]
    assert _files(full, "*.jpg") and _files(full, "*.pcd.bin")  # the full mode does write them
    assert _files(occ, "*.jpg") == [] and _files(occ, "*.pcd.bin") == []
    assert _files(occ, "*.bin") == [] and not (occ / "samples").exists()
    assert not (occ / "lidarseg").exists() and not (occ / VERSION / "lidarseg.json").exists()
    assert _files(occ, "labels.npz") == _files(full, "labels.npz")
    assert len(_files(occ, "labels.npz")) == 2 * 5
    report = json.loads((occ / REPORT_NAME).read_text())
    assert report["mode"] == "occupancy" and report["sensor_files"] is False
    assert "camera" not in report["stages"] and report["stages"]["semantics"]["calls"] == 10
    assert json.loads((full / REPORT_NAME).read_text())["sensor_files"] is True
    t = tables(occ)
    assert all(s["description"].endswith(OCCUPANCY_ONLY) for s in t["scene"])
    # sample_data records stay (ego pose chain, sample['data']) with the full mode's filenames.
    assert t["sample_data"] == tables(full)["sample_data"]
    assert len(t["sample_data"]) == 10 * (1 + len(CAMERA_NAMES))


def test_occ3d_labels_are_identical_to_the_full_mode(roots):
    rels = _files(roots["full"], "labels.npz")
    for rel in rels:
        a, b = np.load(roots["full"] / rel), np.load(roots["occupancy"] / rel)
        for key in ("semantics", "mask_lidar", "mask_camera"):
            np.testing.assert_array_equal(a[key], b[key], err_msg=f"{rel}:{key}")
        assert (a["semantics"] != FREE_ID).sum() > 1000, rel  # a real, non-empty world
        assert 0 < a["mask_camera"].sum() < a["mask_lidar"].sum(), rel
        assert (roots["full"] / rel).read_bytes() == (roots["occupancy"] / rel).read_bytes()


def test_poses_and_annotations_are_identical(roots):
    full, occ = tables(roots["full"]), tables(roots["occupancy"])
    assert set(full) - set(occ) == {"lidarseg"}
    for name in occ:
        if name != "scene":
            assert occ[name] == full[name], name
    for a, b in zip(full["scene"], occ["scene"]):
        assert b == {**a, "description": a["description"] + ", " + OCCUPANCY_ONLY}
    anns = occ["sample_annotation"]
    assert len(anns) > 20 and sum(a["num_lidar_pts"] > 0 for a in anns) > 10
    assert {a["visibility_token"] for a in anns} <= {"1", "2", "3", "4"}


def test_create_data_without_labels_and_sequence_windows(roots, tmp_path):
    infos = {}
    for mode, root in roots.items():
        out = create_data(root, VERSION, out=tmp_path / mode, options=QUIET).out_dir
        infos[mode] = load_infos(out, "train")
    a, b = infos["full"], infos["occupancy"]
    assert len(b) == 5 and (b["occ_path"] != "").all() and (b["labels2d_path"] == "").all()
    for col in ("sample_token", "ego2global", "command", "future_boxes", "occ_path", "cam0_path"):
        assert _plain(a[col].tolist()) == _plain(b[col].tolist()), col
    assert b["cam0_width"].tolist() == [64] * 5 and b["cam0_height"].tolist() == [36] * 5
    ds = {m: OccSequenceDataset(infos[m], roots[m], history=2, future=2) for m in roots}
    assert len(ds["occupancy"]) == len(ds["full"]) == 2
    for i in range(2):
        x, y = ds["full"][i], ds["occupancy"][i]
        for key in ("occ", "mask_camera", "history_poses", "future_traj", "command"):
            assert (x[key] == y[key]).all(), key
        assert y["future_boxes_mask"].any() and y["occ"].shape[0] == 4
        assert (y["future_boxes"] == x["future_boxes"]).all()


def test_create_data_with_labels_is_one_clear_error(roots, tmp_path):
    occ = roots["occupancy"]
    assert is_occupancy_only(occ) and not is_occupancy_only(roots["full"])
    with pytest.raises(DatasetError, match=r"occupancy-only dataset \(.*LIDAR_TOP.*pcd\.bin does"):
        create_data(occ, VERSION, out=tmp_path / "out", options=ConvertOptions(progress=False))
    assert not (tmp_path / "out").exists()  # refused before anything is written
    reader = NuScenesReader(occ, VERSION)
    sd = reader.sample_data_token(tables(occ)["sample"][0]["token"], "CAM_FRONT")
    with pytest.raises(DatasetError, match=r"image file is missing \(this is an occupancy-only"):
        reader.image_path(sd)
    with pytest.raises(DatasetError, match=r"point cloud file is missing \(this is an occ"):
        reader.lidar_points(reader.sample_data_token(tables(occ)["sample"][0]["token"], LIDAR_NAME))


def test_create_data_cli_labels_true_prints_the_error_without_a_traceback(roots, tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    cmd = [sys.executable, str(REPO_ROOT / "tools" / "create_data.py"),
           f"data_root={roots['occupancy']}", f"version={VERSION}", f"out={tmp_path / 'o'}",
           "progress=false"]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert proc.returncode == 1
    assert "occupancy-only dataset" in proc.stderr and "labels=false" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_unreadable_run_report_names_the_file(tmp_path):
    (tmp_path / SIM_REPORT_NAME).write_text("{not json")
    with pytest.raises(DatasetError, match=r"sim_report\.json: not a readable JSON"):
        is_occupancy_only(tmp_path)


def test_bad_mode_raises_naming_mode(tmp_path):
    with pytest.raises(ValueError, match=r"^mode: expected one of \('full', 'occupancy'\), got 'f"):
        SimConfig(mode="fast").validate()
    with pytest.raises(ValueError, match=r"^mode: expected one of"):
        config_from_preset("tiny", mode="images")
    with pytest.raises(ValueError, match=r"^mode: expected one of"):
        simulate(SimConfig(mode="Occupancy"), tmp_path / "out", progress=False)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match=r"^mode: expected one of"):
        writes_sensor_files("lidar")
    writer = DatasetWriter(tmp_path / "w", VERSION, 0, lidarseg=False)
    with pytest.raises(ValueError, match=r"^lidarseg: this writer was made with lidarseg=False"):
        writer.write_lidarseg("t" * 32, np.zeros(3, np.uint8))
    assert "lidarseg" not in writer.tables


DEVKIT_SNIPPET = """
import json, sys
from nuscenes.nuscenes import NuScenes
nusc = NuScenes(version=sys.argv[2], dataroot=sys.argv[1], verbose=False)
sample = nusc.sample[3]
lidar = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
boxes = nusc.get_boxes(lidar["token"])
print(json.dumps({"scenes": len(nusc.scene), "samples": len(nusc.sample),
                  "anns": len(nusc.sample_annotation), "lidarseg": hasattr(nusc, "lidarseg"),
                  "channels": sorted(sample["data"]), "boxes": len(boxes),
                  "pose": nusc.get("ego_pose", lidar["ego_pose_token"])["translation"]}))
"""


@pytest.mark.devkit
def test_official_devkit_loads_the_occupancy_tables(roots):
    from tests.devkit_oracle import run_devkit

    res = run_devkit(DEVKIT_SNIPPET, str(roots["occupancy"]), VERSION)
    t = tables(roots["occupancy"])
    assert (res["scenes"], res["samples"]) == (2, 10) and not res["lidarseg"]
    assert res["anns"] == len(t["sample_annotation"]) and res["boxes"] > 0
    assert res["channels"] == sorted([LIDAR_NAME, *CAMERA_NAMES])
    s3 = t["sample"][3]["token"]  # the devkit keeps the tables' record order
    sds = [sd for sd in t["sample_data"] if sd["sample_token"] == s3]
    lidar = next(sd for sd in sds if sd["filename"].startswith("samples/LIDAR_TOP/"))
    pose = next(p for p in t["ego_pose"] if p["token"] == lidar["ego_pose_token"])
    assert res["pose"] == pose["translation"]


def test_hydra_override_sets_the_mode():
    with initialize_config_dir(str(REPO_ROOT / "configs" / "sim"), version_base=None):
        default = compose("config", overrides=["out=x", "preset=mini"])
        occ = compose("config", overrides=["out=x", "preset=mini", "mode=occupancy"])
    assert sim_config(default).mode == "full"
    cfg = sim_config(occ)
    assert cfg.mode == "occupancy" and cfg.keyframes == 24 and len(cfg.scenes) == 10
    assert REPORT_NAME == SIM_REPORT_NAME
