"""The package's own reader (renderworld.data) reads the tiny fixture consistently."""

from __future__ import annotations

import numpy as np

from renderworld.constants import CAMERA_NAMES, LIDAR_NAME, OCC3D_GRID
from renderworld.data import NuScenesReader
from renderworld.geometry import VoxelGrid, transform_points
from renderworld.sim.sensors import SensorRig


def test_reader_loads_checks_and_reads_every_keyframe(tiny_dataset):
    r = NuScenesReader(tiny_dataset, "v1.0-mini").load_all()  # foreign keys and chains checked
    assert r.scene_names() == ["scene-0061", "scene-0103"]
    rig = SensorRig.build(192, 108)
    grid = VoxelGrid(OCC3D_GRID)
    agree = []
    for scene in r.scene_names():
        samples = r.scene_samples(scene)
        assert len(samples) == 8
        for tok in samples:
            lidar = r.sample_data_token(tok, LIDAR_NAME)
            pts = r.lidar_points(lidar)
            labels = r.lidarseg_labels(lidar, occ3d=True)
            occ = r.occ3d(tok)
            assert occ is not None and occ.semantics.shape == OCC3D_GRID.shape
            assert not (occ.mask_camera.astype(bool) & ~occ.mask_lidar.astype(bool)).any()
            ego = transform_points(r.sensor_to_ego(lidar), pts[:, :3].astype(np.float64))
            idx, inside = grid.points_to_index(ego)
            idx = idx[inside]
            got = occ.semantics[idx[:, 0], idx[:, 1], idx[:, 2]]
            agree.append((got == labels[inside]).mean())
            for ch in CAMERA_NAMES:
                cam = r.sample_data_token(tok, ch)
                np.testing.assert_allclose(r.intrinsics(cam), rig.intrinsics[ch])
                assert r.image_path(cam).exists()
                assert 0 < r.timestamp(cam) - r.timestamp(lidar) <= 50_000
            boxes = r.sample_boxes(tok)
            assert len(boxes) > 0 and (boxes["num_lidar_pts"] >= 0).all()
            assert set(boxes["occ3d_class"]) <= set(range(1, 11))
    assert min(agree) >= 0.95, agree
