"""The official devkit's map_pointcloud_to_image as the oracle for the 2-D labels.

Runs the devkit in its own venv (tests/devkit_oracle.py) on a builder dataset whose ego moves
between the LiDAR and camera timestamps, and compares its projected points, z-buffered per pixel,
with the converter's full-resolution labels.
"""

import numpy as np
import pytest

from data_converters import label_maps
from data_converters.fast_index import TableIndex
from data_converters.labels import point_sources
from data_converters.sample_infos import camera_views, scene_frames
from renderworld.constants import CAMERA_NAMES
from renderworld.data import NuScenesReader
from tests.converter.datasets_for_tests import VERSION, build

pytestmark = pytest.mark.devkit

SNIPPET = """
import json, sys
import numpy as np
from nuscenes.nuscenes import NuScenes, NuScenesExplorer
nusc = NuScenes(version=sys.argv[2], dataroot=sys.argv[1], verbose=False)
explorer = NuScenesExplorer(nusc)
sample = nusc.get("sample", sys.argv[3])
out = {}
for cam in json.loads(sys.argv[4]):
    pts, depth, _ = explorer.map_pointcloud_to_image(sample["data"]["LIDAR_TOP"],
                                                      sample["data"][cam], min_dist=1.0)
    out[cam] = [pts[0].tolist(), pts[1].tolist(), depth.tolist()]
print(json.dumps(out))
"""


def test_labels_match_devkit_map_pointcloud_to_image(tmp_path):
    from tests.devkit_oracle import run_devkit

    root = build(tmp_path / "ds", num_samples=3, ego_path="left", num_points=3000)
    tables = TableIndex(NuScenesReader(root, VERSION))
    frames = scene_frames(tables, "scene-0061", 0)
    token = frames.tokens[1]
    result = run_devkit(SNIPPET, str(root), VERSION, token, '["' + '","'.join(CAMERA_NAMES) + '"]')
    _, views = camera_views(tables, token, lambda hw: hw)  # full resolution
    labels = label_maps(point_sources(tables, frames, 1), views)
    total = 0
    for c, cam in enumerate(CAMERA_NAMES):
        u, v, depth = (np.asarray(x) for x in result[cam])
        h, w = views[c].image_size
        expect = {}
        for key, d in zip(zip(np.floor(u).astype(int), np.floor(v).astype(int)), depth):
            expect[key] = min(d, expect.get(key, np.inf))
        got = {
            (int(a), int(b)): float(d) for a, b, d in zip(labels[c].u, labels[c].v, labels[c].depth)
        }
        # The devkit drops a 1-pixel border (1 < u < W - 1); compare the pixels inside it.
        inner = {k for k in got if 2 <= k[0] <= w - 3 and 2 <= k[1] <= h - 3}
        assert inner == {k for k in expect if 2 <= k[0] <= w - 3 and 2 <= k[1] <= h - 3}, cam
        for k in inner:
            assert got[k] == pytest.approx(expect[k], rel=1e-5, abs=1e-4)
        total += len(inner)
    assert total > 500
