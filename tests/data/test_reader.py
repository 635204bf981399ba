import numpy as np
import pytest

from renderworld.constants import OCC3D_CLASSES
from renderworld.data import NuScenesReader
from renderworld.geometry import pose_matrix
from tests.data.builder import CAM_Q, CAM_T, VERSION, build_tiny_dataset


@pytest.fixture()
def tiny(tmp_path):
    build_tiny_dataset(tmp_path / "ds")
    return NuScenesReader(tmp_path / "ds", VERSION)


def test_scene_and_samples_in_order(tiny):
    assert tiny.scene_names() == ["scene-0061"]
    samples = tiny.scene_samples("scene-0061")
    assert len(samples) == 3
    ts = [tiny.table("sample").at[s, "timestamp"] for s in samples]
    assert ts == sorted(ts)
    assert tiny.scene_samples(tiny.scene_token("scene-0061")) == samples
    assert tiny.scene_of_sample(samples[1]) == "scene-0061"


def test_tables_load_lazily_and_once(tiny):
    assert tiny._tables == {}
    first = tiny.table("ego_pose")
    assert tiny.table("ego_pose") is first
    assert "sample" not in tiny._tables  # ego_pose references nothing


def test_sample_data_calibration_and_poses(tiny):
    s = tiny.scene_samples("scene-0061")[1]
    cam = tiny.sample_data_token(s, "CAM_FRONT")
    lidar = tiny.sample_data_token(s, "LIDAR_TOP")
    np.testing.assert_allclose(tiny.sensor_to_ego(cam), pose_matrix(CAM_T, CAM_Q))
    np.testing.assert_allclose(tiny.ego_to_global(cam)[:3, 3], [105.0, 50.0, 0.0])
    assert tiny.intrinsics(cam)[0, 0] == pytest.approx(316.6)
    assert tiny.timestamp(cam) - tiny.timestamp(lidar) == 10000
    assert tiny.image_path(cam).is_file()
    assert tiny.sd_channel[cam] == "CAM_FRONT"


def test_points_labels_and_occ3d(tiny):
    s = tiny.scene_samples("scene-0061")[0]
    lidar = tiny.sample_data_token(s, "LIDAR_TOP")
    pts = tiny.lidar_points(lidar)
    assert pts.shape == (50, 5) and pts.dtype == np.float32
    raw = tiny.lidarseg_labels(lidar, occ3d=False)
    occ = tiny.lidarseg_labels(lidar)
    assert raw[:3].tolist() == [17, 24, 30]
    names = [OCC3D_CLASSES[i] for i in occ[:3]]
    assert names == ["car", "driveable_surface", "vegetation"]
    labels = tiny.occ3d(s)
    assert labels.semantics.shape == (200, 200, 16)
    assert (labels.semantics[:, :, 0] == 11).all()


def test_boxes(tiny):
    s = tiny.scene_samples("scene-0061")[2]
    boxes = tiny.sample_boxes(s)
    assert len(boxes) == 1
    b = boxes.iloc[0]
    assert b["category"] == "vehicle.car" and OCC3D_CLASSES[b["occ3d_class"]] == "car"
    assert (b["center_x"], b["width"], b["length"]) == (120.0, 1.9, 4.5)
    assert b["yaw"] == pytest.approx(0.5)


def test_load_all(tiny):
    assert tiny.load_all() is tiny
    assert set(tiny._tables) >= {"sample", "lidarseg", "map"}
