"""Pictures of world-model evaluations: PNG sizes from tiny synthetic inputs, argument checks."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from renderworld.constants import FREE_ID, GRIDS, GridSpec
from renderworld.training.figures import bev_forecast_figure, trajectory_figure
from renderworld.training.stages.world_model.pictures import picture_windows

GRID = GridSpec("toy", (-8.0, -8.0, -1.0), (8.0, 8.0, 3.0), (8, 8, 2))


def _frame(cls: int = 4) -> np.ndarray:
    occ = np.full(GRID.shape, FREE_ID, dtype=np.uint8)
    occ[:, :, 0] = 11  # driveable surface
    occ[5, 3, 1] = cls
    return occ


def test_bev_forecast_figure_writes_a_png_of_the_layout_size(tmp_path):
    rows = [(name, [_frame(c) for c in (1, 4, 7, 9)]) for name in ("GT", "pseudo", "forecast")]
    out = bev_forecast_figure(rows, ["t=0", "+1 s", "+2 s", "+3 s"], GRID, tmp_path / "b.png")
    with Image.open(out) as im:
        w, h = im.size
    # figsize = (1.75 * cols + 0.9, 1.75 * rows + 0.9) inches at 80 dpi
    assert (w, h) == (round(80 * (1.75 * 4 + 0.9)), round(80 * (1.75 * 3 + 0.9)))
    assert 5_000 < out.stat().st_size < 250_000
    one = bev_forecast_figure([("GT", [_frame()])], ["t=0"], GRID, tmp_path / "one.png")
    with Image.open(one) as im:
        assert im.size == (round(80 * 2.65), round(80 * 2.65))


def test_bev_forecast_figure_shows_the_class_colours(tmp_path):
    from renderworld.constants import OCC3D_COLORS

    out = bev_forecast_figure([("GT", [_frame(4)])], ["t=0"], GRID, tmp_path / "c.png")
    pixels = np.asarray(Image.open(out).convert("RGB")).reshape(-1, 3)
    for cls in (4, 11):  # car and driveable surface are drawn (image and legend)
        assert (np.abs(pixels.astype(int) - OCC3D_COLORS[cls]).sum(1) == 0).any(), cls


@pytest.mark.parametrize(
    ("rows", "cols", "match"),
    [
        ([], ["t=0"], r"rows/col_titles: expected at least one row and one column, got 0 rows"),
        ([("GT", [_frame()])], [], r"got 1 rows and 0 columns"),
        ([("GT", [_frame(), _frame()])], ["t=0"],
         r"rows\[0\] \('GT'\): expected 1 frames .* got 2"),
        ([("GT", [np.zeros((8, 8, 3), np.uint8)])], ["t=0"],
         r"rows\[0\]\[0\]: expected occ.*\(8, 8, 2\)"),
        ([("GT", [_frame().astype(np.int64)])], ["t=0"], r"rows\[0\]\[0\]: expected uint8"),
        ([("GT", [_frame() + 30])], ["t=0"], r"rows\[0\]\[0\]: class ids must be 0..17"),
    ],
)  # fmt: skip
def test_bev_forecast_figure_checks_its_layout(tmp_path, rows, cols, match):
    with pytest.raises(ValueError, match=match):
        bev_forecast_figure(rows, cols, GRID, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_bev_forecast_figure_circles_the_marks_in_the_first_column(tmp_path):
    rows = [(name, [_frame(), _frame()]) for name in ("GT", "model")]
    plain = bev_forecast_figure(rows, ["t=0", "+1 s"], GRID, tmp_path / "plain.png")
    marked = bev_forecast_figure(rows, ["t=0", "+1 s"], GRID, tmp_path / "m.png", marks=[(2, 3)])
    a = np.asarray(Image.open(plain).convert("RGB")).astype(int)
    b = np.asarray(Image.open(marked).convert("RGB")).astype(int)
    assert a.shape == b.shape
    cols = np.nonzero(np.abs(a - b).sum(axis=(0, 2)))[0]
    assert cols.size and cols.max() < a.shape[1] // 2  # drawn, in the left column only
    rows_changed = np.nonzero(np.abs(a - b).sum(axis=(1, 2)))[0]
    assert rows_changed.min() < a.shape[0] // 2 < rows_changed.max()  # in both rows
    for bad in ([(1.0, float("nan"))], [(1.0, 2.0, 3.0)]):
        with pytest.raises(ValueError, match="marks: expected finite"):
            bev_forecast_figure(rows, ["t=0", "+1 s"], GRID, tmp_path / "x.png", marks=bad)


def test_trajectory_figure_writes_a_png_of_the_layout_size(tmp_path):
    t = np.stack([np.linspace(0.5, 3.0, 6), np.zeros(6)], axis=1)
    panels = [
        {"occ": _frame(), "title": f"window {i}",
         "trajectories": {"GT future": t, "model": t + 0.2, "CV baseline": 1.1 * t}}
        for i in range(3)
    ]  # fmt: skip
    out = trajectory_figure(panels, GRID, tmp_path / "t.png", view=(-2, 6, -4, 4), title="plans")
    with Image.open(out) as im:
        assert im.size == (round(80 * 3.0 * 3), round(80 * 4.0))
    assert out.stat().st_size < 250_000


@pytest.mark.parametrize(
    ("panels", "match"),
    [
        ([], r"panels: expected at least one panel"),
        ([{"occ": None}], r"panels\[0\]: expected a mapping with 'occ' and 'trajectories'"),
        ([{"occ": np.zeros((2, 2, 2), np.uint8), "trajectories": {}}],
         r"panels\[0\]\.occ: expected"),
        ([{"occ": GRID, "trajectories": {}}], r"panels\[0\]\.occ: expected occupancy"),
        ([{"occ": None, "trajectories": {"m": np.zeros((6, 3))}}], r"panels\[0\]\.occ"),
    ],
)  # fmt: skip
def test_trajectory_figure_checks_its_arguments(tmp_path, panels, match):
    with pytest.raises(ValueError, match=match):
        trajectory_figure(panels, GRID, tmp_path / "x.png")
    panel = {"occ": _frame(), "trajectories": {}}
    with pytest.raises(ValueError, match=r"view: expected \(x min, x max, y min, y max\)"):
        trajectory_figure([panel], GRID, tmp_path / "x.png", view=(5, 1, -1, 1))


@pytest.mark.parametrize("bad", [np.zeros((6, 3)), np.zeros(6), np.array([[0.0, np.nan]])])
def test_trajectory_figure_rejects_a_bad_trajectory(tmp_path, bad):
    panel = {"occ": _frame(), "trajectories": {"model": bad}}
    with pytest.raises(
        ValueError, match=r"panels\[0\]\.trajectories\['model'\]: expected a finite"
    ):
        trajectory_figure([panel], GRID, tmp_path / "x.png")


def test_picture_windows_spread_over_the_split():
    assert picture_windows(28, 4) == [0, 9, 18, 27]
    assert picture_windows(2, 4) == [0, 1]
    assert picture_windows(0, 4) == []
    with pytest.raises(ValueError, match="n_windows/count"):
        picture_windows(5, 0)


def test_figures_work_on_the_real_grids(tmp_path):
    grid = GRIDS["coarse"]
    occ = np.full(grid.shape, FREE_ID, dtype=np.uint8)
    out = bev_forecast_figure([("GT", [occ])], ["t=0"], grid, tmp_path / "g.png")
    assert out.is_file()
