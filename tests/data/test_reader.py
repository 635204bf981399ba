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


def test_table_cache_round_trip_and_invalidation(tmp_path):
    import json

    build_tiny_dataset(tmp_path / "c")
    cold = NuScenesReader(tmp_path / "c", VERSION).load_all()
    warm = NuScenesReader(tmp_path / "c", VERSION)
    assert warm._cache.get("sample_data") is not None  # written by the cold load
    for name in ("sample", "sample_data", "calibrated_sensor", "sample_annotation"):
        a, b = cold.table(name), warm.table(name)
        assert list(a.index) == list(b.index)
        for col in a.columns:
            assert a[col].tolist() == b[col].tolist(), (name, col)
    s = warm.scene_samples("scene-0061")[1]
    cam = warm.sample_data_token(s, "CAM_FRONT")
    np.testing.assert_allclose(warm.sensor_to_ego(cam), cold.sensor_to_ego(cam))
    assert warm.sample_boxes(s).equals(cold.sample_boxes(s))
    # Editing any table invalidates the cache: the edit is checked, not served stale.
    path = tmp_path / "c" / VERSION / "ego_pose.json"
    poses = json.loads(path.read_text())
    path.write_text(json.dumps(poses[1:]))
    from renderworld.data import DatasetError

    with pytest.raises(DatasetError, match="ego_pose_token="):
        NuScenesReader(tmp_path / "c", VERSION).table("sample_data")
    # cache=False never touches the cache folder.
    NuScenesReader(tmp_path / "c", VERSION, cache=False, cache_dir=tmp_path / "nocache")
    assert not (tmp_path / "nocache").exists()
