"""The official nuScenes devkit (own venv) loads the tiny fixture with lidarseg, and its
LiDAR→image projection agrees with the package's to well under a pixel."""

from __future__ import annotations

import numpy as np
import pytest

from renderworld.constants import CAMERA_NAMES
from renderworld.geometry import lidar_to_camera_transform, map_lidar_to_image, pose_matrix
from tests.devkit_oracle import run_devkit
from tests.sim.helpers import VERSION, by_token, tables

pytestmark = pytest.mark.devkit

SNIPPET = """
import json, sys
import numpy as np
from nuscenes.nuscenes import NuScenes
nusc = NuScenes(version=sys.argv[2], dataroot=sys.argv[1], verbose=False)
sample = nusc.get("sample", sys.argv[3])
lidar = sample["data"]["LIDAR_TOP"]
out = {"scenes": len(nusc.scene), "samples": len(nusc.sample), "lidarseg": len(nusc.lidarseg),
       "categories": len(nusc.category), "cams": {}}
for ch in json.loads(sys.argv[4]):
    cam = sample["data"][ch]
    path, boxes, K = nusc.get_sample_data(cam)
    pts, coloring, im = nusc.explorer.map_pointcloud_to_image(lidar, cam, show_lidarseg=True)
    out["cams"][ch] = {"uv": pts[:2].T.tolist(), "n_colour": int(len(coloring)),
                       "K": np.asarray(K).tolist(), "boxes": len(boxes), "size": list(im.size)}
pc_path, boxes, _ = nusc.get_sample_data(lidar)
out["lidar_boxes"] = len(boxes)
print(json.dumps(out))
"""


def test_devkit_loads_and_projects_like_the_package(tiny_dataset):
    t = tables(tiny_dataset)
    sample = t["sample"][3]
    res = run_devkit(SNIPPET, str(tiny_dataset), VERSION, sample["token"], _json(CAMERA_NAMES))
    assert res["scenes"] == 2 and res["samples"] == 16 and res["lidarseg"] == 16
    assert res["categories"] == 32 and res["lidar_boxes"] > 5
    sds = [sd for sd in t["sample_data"] if sd["sample_token"] == sample["token"]]
    by_ch = {sd["filename"].split("/")[1]: sd for sd in sds}
    cs, poses = by_token(t["calibrated_sensor"]), by_token(t["ego_pose"])

    def mat(rec):
        return pose_matrix(rec["translation"], rec["rotation"])

    lidar = by_ch["LIDAR_TOP"]
    pts = np.fromfile(tiny_dataset / lidar["filename"], dtype="<f4").reshape(-1, 5)
    total = 0
    for ch in CAMERA_NAMES:
        cam, dk = by_ch[ch], res["cams"][ch]
        K = np.asarray(cs[cam["calibrated_sensor_token"]]["camera_intrinsic"])
        np.testing.assert_allclose(dk["K"], K)
        assert dk["size"] == [cam["width"], cam["height"]]
        T = lidar_to_camera_transform(
            mat(cs[lidar["calibrated_sensor_token"]]),
            mat(poses[lidar["ego_pose_token"]]),
            mat(poses[cam["ego_pose_token"]]),
            mat(cs[cam["calibrated_sensor_token"]]),
        )
        uv, _, _ = map_lidar_to_image(pts, T, K, cam["width"], cam["height"])
        dk_uv = np.asarray(dk["uv"]).reshape(-1, 2)
        assert len(dk_uv) == len(uv) == dk["n_colour"] and len(uv) > 100, ch
        assert np.abs(dk_uv - uv).max() < 0.5, ch
        total += len(uv)
    assert res["cams"]["CAM_FRONT"]["boxes"] > 0 and total > 2000


def _json(x):
    import json

    return json.dumps(list(x))
