"""The main job's recording: the job's checkpoints, a mini_val scene, the report paragraph."""

from __future__ import annotations

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
    tokenizer_checkpoint(tok, tmp_path / "tokenizer" / "checkpoints" / "best.pt")
    lines: list[str] = []
    text = job.main_job_recording(tmp_path, root, infos_dir=infos, log=lines.append)
    assert (tmp_path / "scene.rrd").is_file()
    assert text.startswith("3-D recording of one mini_val scene: [scene.rrd](scene.rrd)")
    assert "8 keyframes of scene-0103" in text  # the val split's scene of the tiny fixture
    assert "`rerun scene.rrd`" in text and "`rerun --web-viewer scene.rrd`" in text
    skips = [x for x in lines if "skipping" in x]
    assert len(skips) == 2 and all("does not exist" in x for x in skips)
    assert "Layer left out: img2occ: img2occ_ckpt" in text
