"""Rerun stays out of the package's light imports; the occupancy-to-boxes geometry."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from renderworld.constants import FREE_ID, GRIDS
from renderworld.viewer import gaussian_arrays, grid_for_shape, hidden_voxels, occupancy_boxes

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    "modules",
    ["renderworld", "renderworld.planning", "renderworld.viewer, renderworld.viewer.checkpoints"],
)
def test_rerun_is_not_imported(modules):
    code = f"import sys, {modules}\nprint([m for m in sys.modules if m.split('.')[0] == 'rerun'])"
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_the_viewer_package_itself_imports_neither_rerun_nor_torch():
    code = (
        "import sys, renderworld.viewer\nprint([m for m in ('rerun', 'torch') if m in sys.modules])"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_occupied_voxels_become_boxes_at_their_centres():
    occ = np.full((50, 50, 4), FREE_ID, dtype=np.uint8)
    occ[0, 0, 0] = 4  # car at the grid's corner
    occ[25, 30, 3] = 16
    boxes = occupancy_boxes(occ)
    assert grid_for_shape(occ.shape) == GRIDS["coarse"]
    np.testing.assert_allclose(boxes.half_size, [0.8, 0.8, 0.8], rtol=1e-6)
    np.testing.assert_allclose(boxes.centres, [[-39.2, -39.2, -0.2], [0.8, 8.8, 4.6]], atol=1e-5)
    assert boxes.classes.tolist() == [4, 16]
    mask = np.zeros(occ.shape, bool)
    mask[25, 30, 3] = True
    assert occupancy_boxes(occ, mask=mask).classes.tolist() == [16]
    with pytest.raises(ValueError, match=r"occupancy: expected class ids 0\.\.17, got max 18"):
        occupancy_boxes(occ + 1)
    with pytest.raises(ValueError, match=r"mask: expected shape \(50, 50, 4\)"):
        occupancy_boxes(occ, mask=mask[:, :, :2])
    with pytest.raises(ValueError, match=r"occupancy: expected \[X, Y, Z\]"):
        occupancy_boxes(occ[0])


def test_gaussians_keep_opacity_as_alpha_and_reorder_quaternions():
    v = 3
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (v, 1))  # identity, [w, x, y, z]
    logits = np.zeros((v, 17))
    logits[np.arange(v), [4, 11, 16]] = 1.0
    arr = gaussian_arrays(np.zeros((v, 3)), quats, np.ones((v, 3)), np.array([0.02, 0.5, 1.0]),
                          logits, min_opacity=0.05)  # fmt: skip
    assert arr["classes"].tolist() == [11, 16]
    assert arr["rgba"][:, 3].tolist() == [128, 255]
    np.testing.assert_array_equal(arr["quats_xyzw"], [[0, 0, 0, 1], [0, 0, 0, 1]])
    with pytest.raises(ValueError, match=r"scales: expected shape \[3, 3\]"):
        gaussian_arrays(np.zeros((v, 3)), quats, np.ones((v, 2)), np.ones(v), logits)


def test_only_voxels_enclosed_on_all_six_faces_are_hidden():
    occ = np.zeros((5, 5, 5), dtype=bool)
    occ[1:4, 1:4, 1:4] = True  # a 3x3x3 block: only its centre is enclosed
    hidden = hidden_voxels(occ)
    assert hidden.sum() == 1 and hidden[2, 2, 2]
    assert not hidden_voxels(np.ones((3, 3, 3), bool))[0, 1, 1], "the grid border counts as free"
    sem = np.where(occ, 4, FREE_ID).astype(np.uint8)
    assert len(occupancy_boxes(sem, surface_only=True).classes) == 26
