import subprocess
import sys

import pytest

from renderworld import constants as C


def test_class_lists_and_maps():
    assert C.NUM_OCC3D_CLASSES == 18 and C.FREE_ID == 17
    assert len(C.OCC3D_COLORS) == 18
    assert len(C.LIDARSEG_CLASSES) == 32
    assert sorted(C.LIDARSEG_TO_OCC3D) == list(range(32))
    lut = C.lidarseg_to_occ3d_lut()
    assert lut[17] == C.OCC3D_CLASSES.index("car")
    assert lut[24] == C.OCC3D_CLASSES.index("driveable_surface")
    assert lut[30] == C.OCC3D_CLASSES.index("vegetation")
    assert {lut[i] for i in (2, 3, 4, 6)} == {C.OCC3D_CLASSES.index("pedestrian")}
    # No lidarseg class maps to free.
    assert C.FREE_ID not in C.LIDARSEG_TO_OCC3D.values()


def test_grids_share_the_occ3d_range():
    for g in C.GRIDS.values():
        assert g.range_min == C.OCC3D_GRID.range_min and g.range_max == C.OCC3D_GRID.range_max
        for full, n in zip(C.OCC3D_GRID.shape, g.shape):
            assert full % n == 0  # integer down-sampling of the Occ3D grid
    with pytest.raises(ValueError, match="grid: unknown grid 'nope'"):
        C.get_grid("nope")


def test_import_is_light():
    code = (
        "import sys, renderworld, renderworld.geometry, renderworld.constants;"
        "bad=[m for m in ('open3d','hydra','torch','pandas') if m in sys.modules];"
        "print(','.join(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
