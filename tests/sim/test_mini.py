"""The full ``mini`` preset (slow: generates ~240 keyframes once, then cached)."""

from __future__ import annotations

import numpy as np
import pytest

from renderworld.constants import MINI_TRAIN_SCENES, MINI_VAL_SCENES
from renderworld.data import NuScenesReader
from renderworld.geometry import yaw_of
from tests.sim.test_motion import COMMAND_LATERAL_THRESHOLD

pytestmark = pytest.mark.slow


def test_mini_dataset_names_size_and_commands(mini_dataset):
    r = NuScenesReader(mini_dataset, "v1.0-mini").load_all()
    assert sorted(r.scene_names()) == sorted(MINI_TRAIN_SCENES + MINI_VAL_SCENES)
    size = sum(p.stat().st_size for p in mini_dataset.rglob("*") if p.is_file())
    assert size <= 400 * 2**20, f"mini is {size / 2**20:.0f} MiB"
    seen = set()
    for scene in r.scene_names():
        samples = r.scene_samples(scene)
        assert len(samples) >= 20
        poses = [r.ego_to_global(r.sample_data_token(s, "LIDAR_TOP")) for s in samples]
        for k in range(len(poses) - 6):
            d = np.linalg.inv(poses[k]) @ poses[k + 6][:, 3]
            lat = d[1]
            seen.add("left" if lat >= COMMAND_LATERAL_THRESHOLD else
                     "right" if lat <= -COMMAND_LATERAL_THRESHOLD else "straight")  # fmt: skip
            assert abs(yaw_of(poses[k])) <= np.pi
    assert seen == {"left", "right", "straight"}
