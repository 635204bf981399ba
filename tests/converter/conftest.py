import pytest

from tests.converter.datasets_for_tests import build, build_and_convert


@pytest.fixture(scope="session")
def left_turn(tmp_path_factory):
    """Two scenes (mini train + val) of 8 keyframes driving a left turn; converted."""
    root = tmp_path_factory.mktemp("left") / "ds"
    out = build_and_convert(root, scene_names=("scene-0061", "scene-0103"), ego_path="left")
    return root, out


@pytest.fixture(scope="session")
def moving_raw(tmp_path_factory):
    """A left-turn dataset with LiDAR sweeps, not converted."""
    return build(tmp_path_factory.mktemp("raw") / "ds", ego_path="left", sweeps=2, num_samples=4)
