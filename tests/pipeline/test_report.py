"""The main job's report.md from a pipeline output folder (no training: made-up step outputs)."""

from __future__ import annotations

import json
import re

import numpy as np
from omegaconf import OmegaConf

from renderworld.constants import FREE_ID, GRIDS
from renderworld.pipeline.job_report import main_job_report as _report
from renderworld.pipeline.runner import StepResult
from renderworld.training.figures import bev_forecast_figure
from renderworld.training.schedule import write_schedule
from renderworld.training.stages.world_model.report import write_report


def _outputs(out):
    tok = {"val/miou": 0.6, "val/iou": 0.9, "val/cam/miou": 0.55, "val/cam/iou": float("nan")}
    tok.update({f"val/iou_{c}": 0.5 for c in ("car", "bus", "terrain")})
    (out / "tokenizer_eval").mkdir(parents=True)
    (out / "tokenizer_eval" / "eval_metrics.json").write_text(json.dumps(tok))
    (out / "img2occ_eval").mkdir()
    (out / "img2occ_eval" / "occ3d_metrics.md").write_text(
        "| id | class | IoU |\n|---:|---|---:|\n| 0 | others | – |\n| 4 | car | 4.59 |\n"
    )
    metrics = {}
    for pre in ("", "camera/"):
        for m in ("model", "copy_paste", "warp_cv"):
            metrics.update({f"val/{pre}{m}/{k}_{h}": 0.1 for k in ("miou", "iou")
                            for h in ("1s", "avg")})  # fmt: skip
        for m in ("model", "cv_traj"):
            metrics.update({f"val/{pre}{m}/{k}_{h}": 0.5 for h in ("1s", "avg")
                            for k in ("l2_at_horizon", "collision_boxes_at_horizon")})  # fmt: skip
    wm = out / "world_model_eval"
    write_report(metrics, wm, (1.0,), ["one table"], (("3D-Occ", ""), ("Camera", "camera/")))
    occ = np.full(GRIDS["coarse"].shape, FREE_ID, dtype=np.uint8)
    for name in ("bev_forecast.png", "bev_movers.png", "trajectories.png"):
        bev_forecast_figure([("GT", [occ])], ["t=0"], GRIDS["coarse"], wm / name)


def test_report_has_one_world_model_table_pictures_and_no_empty_cell(tmp_path):
    out = tmp_path / "out"
    _outputs(out)
    cfg = OmegaConf.create({"data_root": str(tmp_path / "data"), "out": str(out)})
    results = [StepResult("tokenizer", "skipped", 12.0, "f"), StepResult("img2occ", "ran", 3, "g")]
    results.append(StepResult("img2occ_eval", "ran", 1, "h"))
    write_schedule(out / "tokenizer", 700, 700, False, 20.0, 190.0)
    write_schedule(out / "img2occ", 1795, 2700, True, 11.25, 675.0)
    text = _report(cfg, out, results, 5.0).read_text()
    # The run table says how far each training got, and where a time guard stopped one.
    assert "| tokenizer | skipped | 12 | 700 of 700 steps |" in text
    assert "| img2occ | ran | 3 | **stopped at step 1795 of 2700** (time guard 11.25 min) |" in text
    assert "| img2occ_eval | ran | 1 | – |" in text
    assert "Not in this run yet" not in text
    assert text.count("| setting | method |") == 1  # one table, both settings
    assert "| Camera | CV-trajectory |" in text and "| 3D-Occ | model |" in text
    for name in ("bev_forecast.png", "bev_movers.png", "trajectories.png"):
        assert f"(figures/{name})" in text and (out / "figures" / name).is_file()
    assert "![A window where a car moves: model, object-CV warp, GT-pose warp, GT](" in text
    assert "## Planner" not in text  # no bundle yet
    (out / "planner").mkdir()
    (out / "planner" / "planner.pt").write_bytes(b"made up")
    text = _report(cfg, out, results, 5.0).read_text()
    assert f'load_planner("{out / "planner" / "planner.pt"}")' in text
    # No empty cell; every dash / n/a is explained by a legend line.
    for line in text.splitlines():
        if line.startswith("|"):
            assert all(c.strip() for c in line.strip().strip("|").split("|")), line
    assert "–: not applicable" in text
    assert "–: class absent from both GT and prediction" in text  # per-class tables
    assert "n/a" in text and "n/a: " in text  # the tokenizer's NaN camera-mask IoU
    assert not re.search(r"\|[ \t]*\|", text)


def test_report_plots_the_curves_of_every_training_run(tmp_path):
    out = tmp_path / "out"
    _outputs(out)
    runs = ("img2occ", "tokenizer", "tokenizer_camera", "world_model", "world_model_camera")
    for run in runs:
        (out / run).mkdir()
        rows = [f"{s},0,train/loss,{1.0 / (s + 1)}" for s in range(3)]
        (out / run / "metrics.csv").write_text("\n".join(["step,epoch,key,value", *rows]) + "\n")
    cfg = OmegaConf.create({"data_root": str(tmp_path / "data"), "out": str(out)})
    text = _report(cfg, out, [StepResult("tokenizer_camera", "ran", 1.0, "f")], 1.0).read_text()
    for run in runs:
        assert f"![{run} training curves](figures/curves_{run}.png)" in text
        assert (out / "figures" / f"curves_{run}.png").is_file()
    assert "| tokenizer_camera | ran |" in text


def test_an_unreadable_input_is_named_in_the_report(tmp_path):
    """A torn or corrupt JSON does not drop its section silently: the report names the file."""
    out, data = tmp_path / "out", tmp_path / "data"
    _outputs(out)
    cfg = OmegaConf.create({"data_root": str(data), "out": str(out)})
    metrics = out / "tokenizer_eval" / "eval_metrics.json"
    data.mkdir()
    (data / "sim_report.json").write_text(json.dumps({"scenes": ["a", "b"], "files": 7}))
    fine = _report(cfg, out, [], 1.0).read_text()
    assert "| mIoU (classes 0..16, full volume, OccWorld protocol) | 60.00 % |" in fine
    assert "2 scenes, 7 files" in fine and "is unreadable" not in fine
    metrics.write_text('{"val/miou": 0.6, "val/io')  # a torn write
    (data / "sim_report.json").write_text("[1, 2]")  # JSON, but not a report
    text = _report(cfg, out, [], 1.0).read_text()
    tok = text.split("## Tokenizer reconstruction", 1)[1].split("\n## ", 1)[0]
    assert f"**Not shown: `{metrics}` is unreadable** (JSONDecodeError: " in tok
    assert "OccWorld protocol" not in tok
    assert f"Simulated fixture: **Not shown: `{data / 'sim_report.json'}` is unreadable** " in text
    assert "expected a JSON object, got a list" in text and "2 scenes" not in text
    assert "## Forecasting and planning" in text  # the other sections are still there
    metrics.unlink()  # missing (the step has not run): no section, no note
    (data / "sim_report.json").unlink()
    text = _report(cfg, out, [], 1.0).read_text()
    assert "## Tokenizer reconstruction" not in text and "## Data" not in text
    assert "is unreadable" not in text


def test_readme_pictures_are_checked_in_and_small():
    from pathlib import Path

    repo = Path(__file__).resolve().parents[2]
    refs = re.findall(r"\]\((docs/figures/[^)]+\.png)\)", (repo / "README.md").read_text())
    assert len(refs) >= 4
    for ref in refs:
        path = repo / ref
        assert path.is_file(), ref
        assert path.stat().st_size <= 160_000, (ref, path.stat().st_size)


def test_training_curves_have_a_val_panel_and_no_empty_one(tmp_path):
    from PIL import Image

    from renderworld.pipeline.report import plot_training_curves

    rows = ["step,epoch,key,value"]
    rows += [f"{s},0,train/loss,{1.0 / (s + 1)}" for s in range(0, 100, 10)]
    rows += [f"{s},0,val/model/miou_avg,{0.1 + s / 1000}" for s in (50, 100)]
    rows += ["100,0,val/model/miou_1s,0.2"]  # a val key not asked for: no panel
    csv_path = tmp_path / "metrics.csv"
    csv_path.write_text("\n".join(rows) + "\n")
    keys = ("train/loss", "val/loss", "val/model/miou_avg")  # val/loss absent: no panel
    png = plot_training_curves(csv_path, tmp_path / "c.png", keys=keys)
    one = plot_training_curves(csv_path, tmp_path / "one.png", keys=("train/loss",))
    w2, w1 = Image.open(png).size[0], Image.open(one).size[0]
    assert abs(w2 - 2 * w1) <= 2  # two panels: train loss and the val metric
    assert plot_training_curves(csv_path, tmp_path / "none.png", keys=("val/",)) is None
