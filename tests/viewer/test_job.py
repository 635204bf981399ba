"""The main job's recording: the job's checkpoints, a mini_val scene, the report paragraph."""

from __future__ import annotations

from pathlib import Path

import pytest

from renderworld.viewer import job
from tests.viewer.helpers import tokenizer_checkpoint


def test_without_rerun_the_report_says_how_to_install_it(monkeypatch, tmp_path):
    monkeypatch.setattr(job, "rerun_available", lambda: False)
    text = job.main_job_recording(tmp_path, tmp_path)
    assert text.startswith("No 3-D recording: rerun-sdk is not installed")
    assert "renderworld[viz]" in text and not list(tmp_path.iterdir())


def test_records_a_val_scene_with_the_checkpoints_the_job_has(converted, tiny_models, tmp_path):
    pytest.importorskip("rerun", reason="rerun-sdk is not installed (pip install '.[viz]')")
    root, infos = converted
    _, tok, _ = tiny_models
    (tmp_path / "tokenizer" / "checkpoints").mkdir(parents=True)
    tokenizer_checkpoint(tok, tmp_path / "tokenizer" / "checkpoints" / "last.pt")
    lines: list[str] = []
    text = job.main_job_recording(tmp_path, root, infos_dir=infos, log=lines.append)
    assert (tmp_path / "viewer" / "scene.rrd").is_file()
    link = "[viewer/scene.rrd](viewer/scene.rrd)"
    assert text.startswith(f"3-D recording of one mini_val scene: {link}")
    assert "8 keyframes of scene-0103" in text  # the val split's scene of the tiny fixture
    assert "`rerun viewer/scene.rrd`" in text and "`rerun --web-viewer viewer/scene.rrd`" in text
    skips = [x for x in lines if "skipping" in x]
    assert len(skips) == 2 and all("does not exist" in x for x in skips)
    assert "Layer left out: img2occ: img2occ_ckpt" in text


def test_the_job_step_writes_what_the_report_section_links(converted, tiny_models, tmp_path):
    pytest.importorskip("rerun", reason="rerun-sdk is not installed (pip install '.[viz]')")
    import subprocess
    import sys

    root, infos = converted
    assert job.report_section(tmp_path).startswith("No 3-D recording: viewer/scene.rrd was not")
    _, tok, _ = tiny_models
    (tmp_path / "tokenizer" / "checkpoints").mkdir(parents=True)
    tokenizer_checkpoint(tok, tmp_path / "tokenizer" / "checkpoints" / "last.pt")
    cmd = job.view_command(sys.executable, tmp_path, root)
    run = subprocess.run(
        [*cmd, f"infos_dir={infos}", "max_frames=2"], capture_output=True, text=True,
        cwd=Path(__file__).resolve().parents[2], timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]
    assert "2 keyframes of scene-0103" in run.stdout
    assert run.stdout.count("skipping layer") == 2  # no img2occ / world-model checkpoint
    section = job.report_section(tmp_path)
    assert section.startswith("3-D recording of one mini_val scene: [viewer/scene.rrd]")
    assert "`rerun viewer/scene.rrd`" in section


def _job_cfg(tmp_path):
    from omegaconf import OmegaConf

    repo = Path(__file__).resolve().parents[2]
    cfg = OmegaConf.load(repo / "configs" / "pipeline.yaml")
    cfg.out, cfg.data_root = str(tmp_path / "out"), str(tmp_path / "data")
    return cfg, repo


def test_the_main_job_records_after_its_trainings_only_with_rerun(monkeypatch, tmp_path):
    import renderworld.viewer
    from renderworld.pipeline.main_job import main_job_steps

    cfg, repo = _job_cfg(tmp_path)
    monkeypatch.setattr(renderworld.viewer, "rerun_available", lambda: True)
    steps = main_job_steps(cfg, repo)
    names = [s.name for s in steps]
    step = steps[names.index("viewer")]
    assert set(step.depends_on) == {"infos", "img2occ", "tokenizer", "world_model"}
    assert names.index("viewer") > max(names.index(n) for n in step.depends_on)
    assert step.out_dir == tmp_path / "out" / "viewer"
    args = dict(a.split("=", 1) for a in step.command[2:])
    assert step.command[1] == "tools/view.py" and args["split"] == "val"
    assert args["out"] == str(tmp_path / "out" / "viewer" / "scene.rrd")
    for run in ("img2occ", "tokenizer", "world_model"):
        assert args[f"{run}_ckpt"] == str(tmp_path / "out" / run / "checkpoints" / "last.pt")
    monkeypatch.setattr(renderworld.viewer, "rerun_available", lambda: False)
    assert "viewer" not in [s.name for s in main_job_steps(cfg, repo)]


def test_the_report_links_the_recording_or_says_why_not(monkeypatch, tmp_path):
    from renderworld.pipeline.job_report import main_job_report

    cfg, _ = _job_cfg(tmp_path)
    out = tmp_path / "out"
    monkeypatch.setattr(job, "rerun_available", lambda: False)
    text = main_job_report(cfg, out, [], 1.0).read_text()
    assert "3-D recording (Rerun)" in text
    assert "No 3-D recording: rerun-sdk is not installed (pip install 'renderworld[viz]'" in text
    (out / "viewer").mkdir(parents=True)
    (out / "viewer" / "scene.rrd").write_bytes(b"\0" * 2**20)
    text = main_job_report(cfg, out, [], 1.0).read_text()
    assert "[viewer/scene.rrd](viewer/scene.rrd) (1.0 MiB)" in text
    assert "`rerun viewer/scene.rrd`" in text
