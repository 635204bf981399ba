import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from renderworld.geometry import (
    compose,
    invert_pose,
    pose_matrix,
    pose_to_translation_quaternion,
    transform_points,
    yaw_of,
)

finite = st.floats(-100, 100, allow_nan=False, allow_infinity=False)
quat = st.tuples(*[st.floats(-1, 1, allow_nan=False) for _ in range(4)]).filter(
    lambda q: np.linalg.norm(q) > 1e-3
)


def test_identity_and_yaw_90():
    np.testing.assert_allclose(pose_matrix([0, 0, 0], [1, 0, 0, 0]), np.eye(4))
    s = np.sqrt(0.5)
    mat = pose_matrix([1, 2, 3], [s, 0, 0, s])  # +90 deg about z
    np.testing.assert_allclose(transform_points(mat, np.array([[1.0, 0, 0]])), [[1, 3, 3]])
    assert yaw_of(mat) == pytest.approx(np.pi / 2)


def test_pose_matrix_normalises_quaternion_and_rejects_bad_input():
    np.testing.assert_allclose(pose_matrix([0, 0, 0], [2, 0, 0, 0]), np.eye(4))
    with pytest.raises(ValueError, match="rotation: quaternion"):
        pose_matrix([0, 0, 0], [0, 0, 0, 0])
    with pytest.raises(ValueError, match="translation: expected 3"):
        pose_matrix([0, 0], [1, 0, 0, 0])
    with pytest.raises(ValueError, match="rotation: expected finite"):
        pose_matrix([0, 0, 0], [np.nan, 0, 0, 0])


@settings(max_examples=50, deadline=None)
@given(t=st.tuples(finite, finite, finite), q=quat, p=st.tuples(finite, finite, finite))
def test_inverse_round_trip(t, q, p):
    mat = pose_matrix(t, q)
    pts = np.array([p])
    back = transform_points(invert_pose(mat), transform_points(mat, pts))
    np.testing.assert_allclose(back, pts, atol=1e-9)
    np.testing.assert_allclose(compose(mat, invert_pose(mat)), np.eye(4), atol=1e-12)
    t2, q2 = pose_to_translation_quaternion(mat)
    np.testing.assert_allclose(pose_matrix(t2, q2), mat, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(t=st.tuples(finite, finite, finite), q=quat)
def test_torch_matches_numpy(t, q):
    mat = pose_matrix(t, q)
    pts = np.random.default_rng(0).normal(size=(7, 3)) * 10
    out_t = transform_points(torch.from_numpy(mat), torch.from_numpy(pts))
    np.testing.assert_allclose(out_t.numpy(), transform_points(mat, pts), atol=1e-9)
    np.testing.assert_allclose(invert_pose(torch.from_numpy(mat)).numpy(), invert_pose(mat))


def test_transform_points_rejects_bad_shape():
    with pytest.raises(ValueError, match=r"points: expected shape \[\.\.\., N, 3\]"):
        transform_points(np.eye(4), np.zeros((4, 2)))
