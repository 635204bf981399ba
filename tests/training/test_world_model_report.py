"""The world-model evaluation table (one table, both settings) and the eval-settings keys."""

from __future__ import annotations

import csv
import io

import numpy as np
import pytest
from omegaconf import OmegaConf

from renderworld.training.stages.world_model.report import NOT_APPLICABLE, report_tables
from renderworld.training.stages.world_model.settings import eval_settings, setting_header

HS = (1.0, 2.0)


def _metrics(prefix: str, offset: float) -> dict[str, float]:
    out = {}
    for m in ("model", "copy_paste", "warp_cv"):
        for h in ("1s", "2s", "avg"):
            out[f"val/{prefix}{m}/miou_{h}"] = 0.1 + offset
            out[f"val/{prefix}{m}/iou_{h}"] = 0.5 + offset
            out[f"val/{prefix}{m}/cam/miou_{h}"] = 0.2 + offset
    for m in ("model", "cv_traj"):
        for h in ("1s", "2s", "avg"):
            out[f"val/{prefix}{m}/l2_at_horizon_{h}"] = 1.0 + offset
            out[f"val/{prefix}{m}/l2_mean_to_horizon_{h}"] = 0.5 + offset
            out[f"val/{prefix}{m}/collision_boxes_at_horizon_{h}"] = 0.0
            out[f"val/{prefix}{m}/collision_occupancy_at_horizon_{h}"] = 0.01
    return out


BOTH = (("3D-Occ", ""), ("Camera", "camera/"))


def test_one_table_has_a_row_per_setting_and_method():
    metrics = {**_metrics("", 0.0), **_metrics("camera/", 0.05)}
    text, md, csv_text = report_tables(metrics, HS, ["header line"], BOTH)
    rows = list(csv.DictReader(io.StringIO(csv_text)))
    assert [(r["setting"], r["method"]) for r in rows] == [
        (s, m) for s in ("3D-Occ", "Camera")
        for m in ("model", "Copy&Paste", "CV-warp", "CV-trajectory")
    ]  # fmt: skip
    cam_model = rows[4]
    assert float(cam_model["miou_1s_pct"]) == pytest.approx(15.0)
    assert float(cam_model["cam_miou_2s_pct"]) == pytest.approx(25.0)  # kept in the CSV
    assert float(cam_model["l2_mean_to_horizon_2s_m"]) == pytest.approx(0.55)
    assert float(cam_model["collision_occupancy_at_horizon_1s_pct"]) == pytest.approx(1.0)
    assert rows[0]["miou_1s_pct"] != cam_model["miou_1s_pct"]
    assert rows[3]["miou_1s_pct"] == "" and rows[1]["l2_at_horizon_1s_m"] == ""  # n/a: empty
    table = [line for line in md.splitlines() if line.startswith("| ")]
    assert table[0].startswith("| setting | method | mIoU 1s")
    assert "| Camera | model | 15.00 |" in md
    for line in table:  # no empty cell in the markdown table
        cells = line.strip("|").split("|")
        assert all(c.strip() for c in cells), line
    assert f"{NOT_APPLICABLE}: not applicable" in md.split(table[-1])[1]  # legend under it
    assert "Camera   CV-trajectory" in text and "not applicable" in text


def test_movers_and_heading_columns_and_the_movers_rows():
    metrics = _metrics("", 0.0)
    for m in ("model", "warp_object_cv", "warp_gt_movers"):
        for h in ("1s", "2s", "avg"):
            metrics[f"val/{m}/miou_{h}"] = 0.3
            metrics[f"val/{m}/movers_miou_{h}"] = 0.25 if m != "warp_gt_movers" else 1.0
    for h in ("1s", "2s"):
        metrics[f"val/model/heading_median_{h}"] = 1.5
        metrics[f"val/model/heading_mean_{h}"] = 2.75
    text, md, csv_text = report_tables(metrics, HS, [])
    rows = {r["method"]: r for r in csv.DictReader(io.StringIO(csv_text))}
    assert float(rows["object-CV warp"]["movers_miou_1s_pct"]) == pytest.approx(25.0)
    assert float(rows["GT-pose warp + GT movers (ref.)"]["movers_miou_avg_pct"]) == 100.0
    assert float(rows["model"]["heading_median_2s_deg"]) == 1.5
    assert float(rows["model"]["heading_mean_1s_deg"]) == 2.75
    assert rows["CV-trajectory"]["heading_median_1s_deg"] == ""  # not given: empty
    head = next(line for line in md.splitlines() if line.startswith("| setting"))
    cols = [c.strip() for c in head.strip("|").split("|")]
    assert cols.index("Movers 1s") == cols.index("mIoU avg") + 1
    assert cols.index("Head med 1s") == cols.index("L2 avg") + 1
    assert "Head med avg" not in cols  # a heading is reported per horizon only
    model = next(line for line in md.splitlines() if line.startswith("| 3D-Occ | model |"))
    assert dict(zip(cols, (c.strip() for c in model.strip("|").split("|"))))["Head mean 2s"] == (
        "2.75"
    )
    assert "reads the future, an upper bound" in md


def test_legend_lines_only_for_what_is_shown():
    metrics = {k: v for k, v in _metrics("", 0.0).items()}
    metrics["val/model/miou_2s"] = float("nan")
    _, md, _ = report_tables(metrics, HS, [], (("3D-Occ", ""),))
    assert "nan: undefined" in md and "| nan |" in md
    _, md, _ = report_tables(_metrics("", 0.0), HS, [])
    assert "nan: undefined" not in md


def test_report_tables_checks_settings():
    with pytest.raises(ValueError, match="settings: expected at least one"):
        report_tables({}, HS, [], ())
    with pytest.raises(ValueError, match=r"settings: expected \(label, metric prefix\)"):
        report_tables({}, HS, [], (("3D-Occ",),))


def _cfg(**top):
    stage = {"occ_root": top.pop("occ_root", None)}
    return OmegaConf.create({"task": top.pop("task", "eval"), "stage": stage, **top})


def test_eval_settings_default_and_both(tmp_path):
    settings, root = eval_settings(_cfg())
    assert [(s.label, s.prefix, s.inputs) for s in settings] == [("3D-Occ", "", "occ")]
    assert root is None
    ck = tmp_path / "cam.pt"
    ck.write_bytes(b"x")
    settings, root = eval_settings(_cfg(pseudo_labels=str(tmp_path), camera_ckpt=str(ck)))
    assert root == str(tmp_path)
    assert [(s.label, s.prefix, s.inputs, s.ckpt) for s in settings] == [
        ("3D-Occ", "", "occ_target", None), ("Camera", "camera/", "occ", str(ck))
    ]  # fmt: skip
    assert "trained on pseudo labels" in setting_header(settings, "a.pt", "t.pt")
    settings, _ = eval_settings(_cfg(pseudo_labels=str(tmp_path)))
    assert settings[1].ckpt is None
    header = setting_header(settings, "a.pt", "t.pt")
    assert "the 3D-Occ checkpoint; no camera_ckpt given" in header
    assert "GT targets, tokenizer = t.pt; Camera" in header
    assert header.endswith("tokenizer = t.pt (the 3D-Occ tokenizer; no camera_tokenizer_ckpt)")
    settings, _ = eval_settings(_cfg(pseudo_labels=str(tmp_path), camera_tokenizer_ckpt=str(ck)))
    assert settings[0].tokenizer is None and settings[1].tokenizer == str(ck)
    header = setting_header(settings, "a.pt", "t.pt")
    assert header.endswith(f"tokenizer = {ck} (camera_tokenizer_ckpt)")
    settings, root = eval_settings(_cfg(occ_root=str(tmp_path)))  # training's Camera setting
    assert [s.label for s in settings] == ["Camera"] and root == str(tmp_path)
    # Training ignores the eval-only keys.
    settings, _ = eval_settings(_cfg(task="train", pseudo_labels="/nope"))
    assert [s.label for s in settings] == ["3D-Occ"]


@pytest.mark.parametrize(
    ("top", "match"),
    [
        ({"camera_ckpt": "x.pt"}, r"camera_ckpt: 'x.pt' needs pseudo_labels="),
        ({"camera_tokenizer_ckpt": "t.pt"}, r"camera_tokenizer_ckpt: 't.pt' needs pseudo_labels="),
        ({"pseudo_labels": "/p", "occ_root": "/q"}, r"pseudo_labels: set together with stage"),
        ({"pseudo_labels": "/does/not/exist"}, r"pseudo_labels: '/does/not/exist' does not exist"),
        ({"pseudo_labels": 3}, r"pseudo_labels: expected a path or null, got 3"),
    ],
)
def test_eval_settings_errors_name_the_key(top, match):
    with pytest.raises(ValueError, match=match):
        eval_settings(_cfg(**top))


def test_baselines_reference_splits_and_classes_in_the_table():
    metrics = _metrics("", 0.0)
    for h in ("1s", "2s", "avg"):
        metrics[f"val/warp_ctr/miou_{h}"] = 0.3
        metrics[f"val/warp_gt_pose/miou_{h}"] = 0.45
        metrics[f"val/ctr_traj/l2_at_horizon_{h}"] = 0.7
        metrics[f"val/model/turning/miou_{h}"] = 0.12
        metrics[f"val/warp_cv/straight/l2_at_horizon_{h}"] = 9.0  # not a planner: ignored
        metrics[f"val/model/straight/l2_at_horizon_{h}"] = 0.25
    metrics["val/model/turning/num_windows"] = 18.0
    metrics["val/model/class_iou/car_1s"] = 0.061
    text, md, csv_text = report_tables(metrics, HS, [], (("3D-Occ", ""),))
    rows = {r["method"]: r for r in csv.DictReader(io.StringIO(csv_text))}
    assert list(rows) == [
        "model", "Copy&Paste", "CV-warp", "CTR-warp", "CV-trajectory", "CTR-trajectory",
        "GT-pose warp (ref.)",
    ]  # fmt: skip
    assert float(rows["CTR-warp"]["miou_2s_pct"]) == pytest.approx(30.0)
    assert float(rows["CTR-trajectory"]["l2_at_horizon_1s_m"]) == pytest.approx(0.7)
    assert float(rows["model"]["turning_miou_1s_pct"]) == pytest.approx(12.0)
    assert float(rows["model"]["turning_windows"]) == 18.0
    assert float(rows["model"]["straight_l2_at_horizon_2s_m"]) == pytest.approx(0.25)
    assert float(rows["model"]["iou_car_1s_pct"]) == pytest.approx(6.1)
    assert rows["Copy&Paste"]["iou_car_1s_pct"] == ""
    assert "| 3D-Occ | GT-pose warp (ref.) | 45.00 |" in md
    assert "reads the future, an upper bound for a static world, not a method" in md
    assert "GT-pose warp (ref.)" in text


def test_the_forecast_picture_shows_a_turning_window():
    import math

    import torch

    from renderworld.training.stages.world_model.pictures import turning_window

    def item(yaw_deg: float) -> dict:
        poses = torch.zeros(6, 3)
        poses[:, 2] = torch.linspace(0, math.radians(yaw_deg), 6)
        return {"future_poses": poses, "future_mask": torch.ones(6, dtype=torch.bool)}

    windows = [item(30), item(0), item(0), item(2), item(0), item(-40), item(0)]
    assert turning_window(windows) == 5  # nearest the middle (3) of those turning > 5 deg
    assert turning_window([item(0)] * 4) == 2  # none turns: the middle


def _mover_item(cars_now, cars_past, turn_deg: float = 0.0, cls: str = "car") -> dict:
    """A window of 3 history + 6 future coarse frames; the ego drives 6.4 m/s forward (4 cells
    per second: frame t-2 lies 4 cells behind). Cars are 2x2-cell boxes at their lowest cell
    (ix, iy) in frame t (``cars_now``) and in frame t-2's own ego frame (``cars_past``); ``cls``
    another movable class instead."""
    import math

    import torch

    from renderworld.constants import FREE_ID, GRIDS, OCC3D_CLASSES

    car = OCC3D_CLASSES.index(cls)
    occ = np.full((9, *GRIDS["coarse"].shape), FREE_ID, dtype=np.uint8)
    occ[..., 0] = OCC3D_CLASSES.index("driveable_surface")
    for frame, cars in ((2, cars_now), (0, cars_past)):
        for ix, iy in cars:
            occ[frame, ix : ix + 2, iy : iy + 2, 1:3] = car
    future = torch.zeros(6, 3)
    future[:, 0] = 3.2 * torch.arange(1, 7)
    future[:, 2] = torch.linspace(0, math.radians(turn_deg), 6)
    return {
        "occ": torch.from_numpy(occ),
        "history_poses": torch.tensor([[-6.4, 0.0, 0.0], [-3.2, 0.0, 0.0], [0.0, 0.0, 0.0]]),
        "future_poses": future,
        "future_mask": torch.ones(6, dtype=torch.bool),
    }


def test_the_movers_picture_shows_the_window_of_the_fastest_car_in_view():
    from renderworld.constants import GRIDS, OCC3D_CLASSES
    from renderworld.training.stages.world_model.pictures import mover_window

    grid = GRIDS["coarse"]  # 1.6 m cells; the ego's motion moves frame t-2 by 4 cells
    parked = _mover_item([(30, 30)], [(34, 30)])  # the same place in the world
    moving = _mover_item([(30, 30), (15, 20)], [(34, 30), (13, 20)])  # 6 cells/s: 9.6 m/s
    # Faster, but clipped by the grid's edge (11.2 m/s), gone from the grid by +3 s (12.8 m/s
    # towards the back, the ego 19.2 m forward) or a truck (11.2 m/s): none is shown.
    edge = _mover_item([(10, 0)], [(7, 0)])
    leaving = _mover_item([(20, 10)], [(32, 10)])
    truck = _mover_item([(10, 20)], [(7, 20)], cls="truck")
    pick = mover_window([parked, edge, moving, leaving, truck], grid, history=3, future=6)
    assert pick.index == 2
    assert pick.speed_mps == pytest.approx(9.6)
    assert pick.class_id == OCC3D_CLASSES.index("car")
    assert pick.centroid_m == pytest.approx((-40 + 1.6 * 16, -40 + 1.6 * 21))
    # Two as fast: the lower index.
    assert mover_window([parked, moving, moving], grid, 3, 6).index == 1
    # Nothing moves (parked cars are still once the ego's motion is compensated): the turning
    # window, at speed 0.
    still = [parked, _mover_item([(30, 30)], [(34, 30)], turn_deg=30), parked, parked, edge]
    pick = mover_window(still, grid, history=3, future=6)
    assert (pick.index, pick.speed_mps, pick.class_id, pick.centroid_m) == (1, 0.0, None, None)
    with pytest.raises(ValueError, match="classes: expected names among"):
        mover_window(still, grid, 3, 6, classes=("driveable_surface",))
    with pytest.raises(ValueError, match=r"lag: expected an int in \[1, 2\]"):
        mover_window(still, grid, 3, 6, lag=3)


def test_collision_counts_table_and_csv_hold_the_counts_behind_the_rates(tmp_path):
    from renderworld.training.stages.world_model.report import (
        collision_counts_table,
        write_report,
    )

    metrics = _metrics("", 0.0)
    assert collision_counts_table(metrics, HS) == ""  # no counts: no table (older metrics)
    for m, hits in (("model", 0), ("cv_traj", 3)):
        for src in ("boxes", "occupancy"):
            for conv in ("at_horizon", "mean_to_horizon"):
                for h in ("1s", "2s"):
                    metrics[f"val/{m}/collision_{src}_hits_{conv}_{h}"] = hits
                    metrics[f"val/{m}/collision_{src}_evaluated_{conv}_{h}"] = 12
    table = collision_counts_table(metrics, HS)
    assert (
        "| 3D-Occ | CV-trajectory | boxes | at horizon | 3 / 12 (25.0 %) | 3 / 12 (25.0 %) |"
        in table
    )
    assert "| 3D-Occ | model | occupancy | mean to horizon | 0 / 12 (0.0 %) |" in table
    write_report(metrics, tmp_path, HS, ["h"])
    md = (tmp_path / "world_model_eval.md").read_text()
    assert "colliding / evaluated waypoints" in md and table in md
    rows = list(csv.DictReader(open(tmp_path / "world_model_eval.csv")))
    cv = next(r for r in rows if r["method"] == "CV-trajectory")
    assert float(cv["collision_boxes_hits_at_horizon_2s"]) == 3
    assert float(cv["collision_occupancy_evaluated_mean_to_horizon_1s"]) == 12


def test_the_gt_pose_object_cv_reference_row(tmp_path):
    """``warp_gt_object_cv``: the current frame's movers moved by the object-CV rule, carried
    along the GT future poses; a model-free reference row of the table and the CSV."""
    import torch
    from torch.utils.data import default_collate

    from renderworld.constants import GRIDS, OCC3D_CLASSES
    from renderworld.training.stages.world_model.evaluation import MODEL_FREE_METHODS
    from renderworld.training.stages.world_model.references import reference_forecasts
    from renderworld.training.stages.world_model.report import (
        METHODS,
        MODEL_MOVERS,
        REFERENCES,
        write_report,
    )

    grid, car = GRIDS["coarse"], OCC3D_CLASSES.index("car")
    # The ego drives 2 cells per frame; a parked car at (30, 30) and a car at (15, 20) that
    # drove 6 cells forward in the last second: 3 cells per frame, 1 more than the ego.
    batch = default_collate([_mover_item([(30, 30), (15, 20)], [(34, 30), (13, 20)])])
    refs = reference_forecasts(batch, "occ", 3, grid)
    free = [r for r in REFERENCES if r != MODEL_MOVERS]  # the learned movers' row reads a model
    assert list(refs) == free and set(free) <= set(MODEL_FREE_METHODS)
    assert MODEL_MOVERS not in MODEL_FREE_METHODS
    box = {(0, 0), (0, 1), (1, 0), (1, 1)}
    for k in range(1, 7):
        cells = set(zip(*(t.tolist() for t in torch.nonzero(
            (refs["warp_gt_object_cv"][0, k - 1] == car).any(-1), as_tuple=True))))  # fmt: skip
        want = {(30 - 2 * k + a, 30 + b) for a, b in box} | {(15 + k + a, 20 + b) for a, b in box}
        assert cells == want, k
        static = (refs["warp_gt_pose"][0, k - 1] == car).any(-1)
        assert static[15 - 2 * k, 20] and not static[15 + k + 1, 20]  # the static warp: not moved
    # Beside the other references, with the movers' column; in the markdown, CSV and legend.
    names = [m[0] for m in METHODS]
    assert names.index("warp_gt_pose") + 1 == names.index("warp_gt_object_cv")
    assert names.index("warp_gt_object_cv") + 1 == names.index(MODEL_MOVERS)
    assert names.index(MODEL_MOVERS) + 1 == names.index("warp_gt_movers")
    metrics = _metrics("", 0.0)
    for h in ("1s", "2s", "avg"):
        metrics[f"val/warp_gt_object_cv/miou_{h}"] = 0.4
        metrics[f"val/warp_gt_object_cv/movers_miou_{h}"] = 0.35
    write_report(metrics, tmp_path, HS, ["h"])
    md = (tmp_path / "world_model_eval.md").read_text()
    assert "| 3D-Occ | GT-pose + object-CV movers (ref.) | 40.00 | 40.00 | 40.00 | 35.00 |" in md
    assert "GT-pose + object-CV movers (ref.) = the current frame with its movers moved" in md
    rows = {r["method"]: r for r in csv.DictReader(open(tmp_path / "world_model_eval.csv"))}
    row = rows["GT-pose + object-CV movers (ref.)"]
    assert float(row["movers_miou_2s_pct"]) == pytest.approx(35.0)
    assert row["l2_at_horizon_1s_m"] == ""  # a forecast without a plan
