"""The main job's closed-loop step and its report section (made-up outputs, no driving)."""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from renderworld.pipeline.job_report import main_job_report
from renderworld.pipeline.main_job import main_job_steps
from renderworld.pipeline.runner import StepResult

REPO = Path(__file__).resolve().parents[2]


def test_closed_loop_step_drives_the_interaction_split_with_the_job_bundle(tmp_path):
    cfg = OmegaConf.load(REPO / "configs" / "pipeline.yaml")
    cfg.out, cfg.data_root = str(tmp_path / "out"), str(tmp_path / "sim_mini")
    steps = main_job_steps(cfg, REPO)
    names = [s.name for s in steps]
    step = steps[names.index("closed_loop")]
    assert names.index("planner") < names.index("closed_loop")
    assert names.index("planner_camera") < names.index("closed_loop")
    assert step.command[1] == "tools/drive.py"
    assert set(step.depends_on) == {"planner", "planner_camera", "img2occ"}
    args = dict(a.split("=", 1) for a in step.command[2:])
    assert args["preset"] == "interactions"
    assert args["planner"] == str(tmp_path / "out" / "planner" / "planner.pt")
    # The Camera setting drives on its cameras: its bundle and the Img2Occ that reads them.
    assert args["camera_planner"] == str(tmp_path / "out" / "planner_camera" / "planner.pt")
    assert args["img2occ"] == str(tmp_path / "out" / "img2occ" / "checkpoints" / "last.pt")
    camera = steps[names.index("planner_camera")]
    assert set(camera.depends_on) == {"tokenizer_camera", "world_model_camera"}
    assert args["planners"] == "[log_replay,cv,ctr,rule_based,stop]"
    assert step.out_dir == tmp_path / "out" / "closed_loop"
    assert REPO / "configs" / "drive.yaml" in step.inputs
    from renderworld.viewer import rerun_available

    assert args.get("record") == ("scene-6000" if rerun_available() else None)
    cfg.scenarios = False
    assert "closed_loop" not in {s.name for s in main_job_steps(cfg, REPO)}


def test_report_shows_the_closed_loop_table_and_one_picture_per_behaviour(tmp_path):
    out = tmp_path / "out"
    cfg = OmegaConf.create({"data_root": str(tmp_path / "data"), "out": str(out)})
    results = [StepResult("closed_loop", "ran", 90.0, "f")]
    assert "Closed-loop driving" not in main_job_report(cfg, out, results, 1.0).read_text()
    run = out / "closed_loop"
    (run / "figures").mkdir(parents=True)
    (run / "closed_loop.md").write_text("| planner | PDMS |\n|---|---|\n| cv | 0.125 |\n")
    for b in ("lead_brake", "cut_in"):
        (run / "figures" / f"closed_loop_{b}.png").write_bytes(b"png")
    text = main_job_report(cfg, out, results, 1.0).read_text()
    assert "Closed-loop driving (interaction split)" in text and "| cv | 0.125 |" in text
    assert "PDMS = NC x DAC x (5 TTC + 5 EP + 2 C) / 12" in text
    assert "Rerun recording" not in text
    (run / "closed_loop_scene-6000.rrd").write_bytes(b"rrd")
    text = main_job_report(cfg, out, results, 1.0).read_text()
    assert f"`rerun {run / 'closed_loop_scene-6000.rrd'}`" in text
    for b in ("lead_brake", "cut_in"):
        assert f"(figures/closed_loop_{b}.png)" in text
        assert (out / "figures" / f"closed_loop_{b}.png").is_file()
