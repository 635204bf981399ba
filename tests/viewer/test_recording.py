"""A recording of the tiny fixture with every layer, read back with Rerun's own reader."""

from __future__ import annotations

import collections
import dataclasses

import numpy as np
import pytest
import torch

from renderworld.constants import CAMERA_NAMES, FREE_ID, LIDAR_NAME
from renderworld.data import NuScenesReader

rr = pytest.importorskip("rerun", reason="rerun-sdk is not installed (pip install '.[viz]')")
from rerun.chunk import RrdReader  # noqa: E402

from renderworld.viewer import LAYERS, hidden_voxels, write_scene_recording  # noqa: E402

SCENE = "scene-0103"  # the tiny fixture's mini_val scene, 8 keyframes
FORECASTS = [f"/world/forecast/{s:.1f}s" for s in (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)]


def read_back(path):
    """{(entity, component): {frame: instances}} and {timeline: sorted values} of a .rrd."""
    counts: dict = collections.defaultdict(dict)
    timelines: dict = collections.defaultdict(set)
    for chunk in RrdReader(path).stream():
        if chunk.is_static:
            continue
        rb = chunk.to_record_batch()
        frames = rb.column("frame").to_pylist()
        timelines["frame"].update(frames)
        timelines["time"].update(rb.column("time").cast("int64").to_pylist())  # ns
        for name in rb.schema.names:
            if ":" not in name:
                continue
            for f, v in zip(frames, rb.column(name).to_pylist(), strict=True):
                if v is not None:
                    counts[(chunk.entity_path, name)][f] = len(v)
    return counts, {k: sorted(v) for k, v in timelines.items()}


@pytest.fixture(scope="module")
def full_recording(converted, tiny_models, tmp_path_factory):
    root, infos = converted
    img2occ, tok, planner = tiny_models
    img2occ.set_threshold(0.0)  # untrained opacities are low: read out every voxel's class
    out = tmp_path_factory.mktemp("rec") / "scene.rrd"
    lines: list[str] = []
    summary = write_scene_recording(
        root, out, scene=SCENE, infos_dir=infos, img2occ=img2occ, tokenizer=tok,
        planner=planner, gaussians="splats", min_opacity=0.0, voxels="all", log=lines.append,
    )  # fmt: skip
    return summary, lines, read_back(out)


def test_every_layer_is_written_with_the_right_counts(full_recording, converted):
    summary, lines, (counts, timelines) = full_recording
    root, _ = converted
    reader = NuScenesReader(root, "v1.0-mini")
    tokens = reader.scene_samples(SCENE)
    assert summary.skipped == [] and not any("skipping" in x for x in lines)
    assert summary.frames == len(tokens) == 8
    # Timelines: one frame per keyframe, times are the LiDAR keyframe timestamps.
    assert timelines["frame"] == list(range(8))
    stamps = [reader.timestamp(reader.sample_data_token(t, LIDAR_NAME)) for t in tokens]
    assert np.allclose(np.asarray(timelines["time"], dtype=np.float64) / 1e9,
                       np.asarray(stamps) / 1e6)  # fmt: skip
    for i, tok in enumerate(tokens):
        lidar = reader.sample_data_token(tok, LIDAR_NAME)
        assert counts[("/world/ego/lidar", "Points3D:positions")][i] == len(
            reader.lidar_points(lidar)
        )
        occupied = int((reader.occ3d(tok).semantics != FREE_ID).sum())
        assert counts[("/world/ego/occupancy/gt", "Boxes3D:centers")][i] == occupied > 0
        assert counts[("/world/agents", "Boxes3D:centers")][i] == len(reader.sample_boxes(tok))
        # Every coarse-grid voxel carries one Gaussian (50 x 50 x 4); none is dropped at 0.
        assert counts[("/world/ego/img2occ/gaussians", "GaussianSplats3D:centers")][i] == 10_000
        assert counts[("/world/ego/img2occ/occupancy", "Boxes3D:centers")][i] == 10_000
        assert 0 < counts[("/world/ego/tokenizer/reconstruction", "Boxes3D:centers")][i] <= 10_000
        for cam in CAMERA_NAMES:
            assert counts[(f"/world/ego/cameras/{cam}", "EncodedImage:blob")][i] == 1
            assert counts[(f"/world/ego/cameras/{cam}", "Pinhole:image_from_camera")][i] == 1
    # Forecasts and plans exist from the first keyframe with 5 frames of history (index 4).
    planned = counts[("/world/ego/plan/planned", "LineStrips3D:strips")]
    assert sorted(planned) == [4, 5, 6, 7]
    for entity in FORECASTS:
        assert sorted(counts[(entity, "Boxes3D:centers")]) == [4, 5, 6, 7]
        assert sorted(counts[(entity, "Transform3D:translation")]) == [4, 5, 6, 7]
    assert summary.instances["world/ego/plan/planned"] == 4 * 6
    # GT future positions: 3, 2, 1, 0 keyframes remain after keyframes 4..7.
    assert summary.instances["world/ego/plan/gt"] == 3 + 2 + 1
    assert summary.bytes == summary.path.stat().st_size > 0


def test_images_and_calibration_are_the_dataset_s(full_recording, converted):
    summary, _, _ = full_recording
    root, _ = converted
    reader = NuScenesReader(root, "v1.0-mini")
    first = reader.scene_samples(SCENE)[0]
    sd = reader.sample_data_token(first, "CAM_FRONT")
    rows = {}
    for chunk in RrdReader(summary.path).stream():
        if chunk.entity_path == "/world/ego/cameras/CAM_FRONT" and not chunk.is_static:
            rb = chunk.to_record_batch()
            frames = rb.column("frame").to_pylist()
            if 0 in frames:  # the first keyframe's row
                r = frames.index(0)
                rows.update({n: rb.column(n)[r].as_py() for n in rb.schema.names if ":" in n})
    assert bytes(rows["EncodedImage:blob"][0]) == reader.image_path(sd).read_bytes()
    k = np.asarray(rows["Pinhole:image_from_camera"][0], dtype=np.float64).reshape(3, 3).T
    np.testing.assert_allclose(k, reader.intrinsics(sd), rtol=1e-6)  # stored column-major
    assert rows["Pinhole:resolution"][0] == [192.0, 108.0]


def test_missing_models_are_skipped_with_one_line_each(converted, tmp_path):
    root, infos = converted
    lines: list[str] = []
    summary = write_scene_recording(
        root, tmp_path / "data.rrd", scene=SCENE, infos_dir=infos, max_frames=2, log=lines.append
    )
    skips = [x for x in lines if "skipping" in x]
    assert len(skips) == 3 and len(summary.skipped) == 3
    assert any("'img2occ'" in x and "img2occ_ckpt" in x for x in skips)
    counts, timelines = read_back(summary.path)
    assert timelines["frame"] == [0, 1]
    # Default voxels="surface": the GT boxes are the occupied voxels not hidden on six faces.
    reader = NuScenesReader(root, "v1.0-mini")
    for i, tok in enumerate(reader.scene_samples(SCENE)[:2]):
        occupied = reader.occ3d(tok).semantics != FREE_ID
        visible = int((occupied & ~hidden_voxels(occupied)).sum())
        assert counts[("/world/ego/occupancy/gt", "Boxes3D:centers")][i] == visible
        assert 0 < visible < occupied.sum()
    entities = {e for e, _ in counts}
    assert "/world/ego/occupancy/gt" in entities
    assert not any(e.startswith(("/world/forecast", "/world/ego/img2occ")) for e in entities)


def test_model_layers_without_infos_are_skipped(converted, tiny_models, tmp_path):
    root, _ = converted
    img2occ, tok, planner = tiny_models
    lines: list[str] = []
    summary = write_scene_recording(
        root, tmp_path / "x.rrd", scene=SCENE, infos_dir=tmp_path / "none", img2occ=img2occ,
        tokenizer=tok, planner=planner, layers=["ego", "img2occ", "tokenizer", "forecast"],
        log=lines.append,
    )  # fmt: skip
    assert len(summary.skipped) == 3
    assert all("no converter infos" in x for x in summary.skipped)


def test_bad_arguments_name_the_argument(converted, tmp_path):
    root, _ = converted
    with pytest.raises(ValueError, match=r"layers: unknown \['voxels'\]"):
        write_scene_recording(root, tmp_path / "a.rrd", layers=["voxels"])
    with pytest.raises(TypeError, match="layers: expected a list"):
        write_scene_recording(root, tmp_path / "a.rrd", layers="lidar")
    with pytest.raises(ValueError, match="gaussians: expected one of"):
        write_scene_recording(root, tmp_path / "a.rrd", gaussians="blobs")
    with pytest.raises(ValueError, match=r"first_view: expected 'data' or one of \[\]"):
        write_scene_recording(root, tmp_path / "a.rrd", first_view="forecast", layers=["ego"])
    with pytest.raises(ValueError, match="voxels: expected 'surface' or 'all'"):
        write_scene_recording(root, tmp_path / "a.rrd", voxels="some")
    with pytest.raises(ValueError, match=r"out: expected a \.rrd"):
        write_scene_recording(root, tmp_path / "a.txt")
    with pytest.raises(ValueError, match="scene: 'scene-9999' is not in"):
        write_scene_recording(root, tmp_path / "a.rrd", scene="scene-9999")
    with pytest.raises(ValueError, match="max_frames: expected an integer >= 1"):
        write_scene_recording(root, tmp_path / "a.rrd", max_frames=0)
    assert not list(tmp_path.iterdir()), "nothing is written on a bad argument"
    assert set(LAYERS) >= {"cameras", "lidar", "gt_occupancy", "img2occ", "forecast"}


def test_tool_writes_the_recording_and_says_how_to_open_it(converted, tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    root, infos = converted
    out = tmp_path / "tool.rrd"
    run = subprocess.run(
        [sys.executable, "tools/view.py", f"data_root={root}", f"infos_dir={infos}",
         "split=val", f"out={out}", "max_frames=1", "layers=[ego,lidar,img2occ]",
         f"img2occ_ckpt={tmp_path / 'absent.pt'}"],
        cwd=Path(__file__).resolve().parents[2], capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]
    skips = [x for x in run.stdout.splitlines() if "skipping" in x]
    assert skips == [f"viewer: skipping layer 'img2occ': img2occ_ckpt "
                     f"{str(tmp_path / 'absent.pt')!r} does not exist"]  # fmt: skip
    assert f"rerun {out}" in run.stdout
    assert f"1 keyframes of {SCENE}" in run.stdout  # split=val: the val split's first scene
    counts, timelines = read_back(out)
    assert timelines["frame"] == [0]
    assert {e for e, _ in counts} == {"/world/ego", "/world/ego/box", "/world/ego/lidar"}


def test_a_scene_shorter_than_the_planner_history_skips_the_forecast(converted, tiny_models,
                                                                     tmp_path):  # fmt: skip
    from renderworld.planning import Planner
    from renderworld.world import WorldModel

    root, infos = converted
    _, tok, planner = tiny_models
    long_history = dataclasses.replace(planner.config, history_frames=9)
    lines: list[str] = []
    summary = write_scene_recording(
        root, tmp_path / "s.rrd", scene=SCENE, infos_dir=infos, layers=["ego", "forecast"],
        planner=Planner(tok, WorldModel(long_history)), log=lines.append,
    )  # fmt: skip
    assert summary.skipped == [
        "forecast: history/future: windows of 9 keyframes need a scene that long; the longest has 8"
    ]
    assert [x for x in lines if "skipping" in x] == [
        f"viewer: skipping layer 'forecast': {summary.skipped[0][len('forecast: ') :]}"
    ]


@pytest.mark.parametrize(
    ("mode", "column"),
    [("ellipsoids", "Ellipsoids3D:centers"), ("points", "Points3D:positions")],
)
def test_gaussians_as_ellipsoids_or_points(converted, tiny_models, tmp_path, mode, column):
    root, infos = converted
    img2occ = tiny_models[0]
    summary = write_scene_recording(
        root, tmp_path / "g.rrd", scene=SCENE, infos_dir=infos, img2occ=img2occ,
        layers=["img2occ"], gaussians=mode, min_opacity=0.0, max_frames=1, log=None,
    )  # fmt: skip
    counts, _ = read_back(summary.path)
    assert counts[("/world/ego/img2occ/gaussians", column)] == {0: 10_000}


def test_a_dataset_without_occ3d_skips_gt_occupancy_with_one_line(converted, tmp_path):
    import shutil

    root, _ = converted
    copy = tmp_path / "no_gts"
    shutil.copytree(root, copy, ignore=shutil.ignore_patterns("gts", "renderworld_*"))
    lines: list[str] = []
    summary = write_scene_recording(
        copy, tmp_path / "n.rrd", scene=SCENE, layers=["ego", "gt_occupancy"], max_frames=2,
        log=lines.append,
    )  # fmt: skip
    assert summary.skipped == ["gt_occupancy: no Occ3D GT file for any keyframe of the scene"]
    assert sum("skipping layer 'gt_occupancy'" in x for x in lines) == 1
    counts, _ = read_back(summary.path)
    assert not any(e == "/world/ego/occupancy/gt" for e, _ in counts)


def test_a_pose_aware_planner_draws_forecasts_in_its_predicted_frames(
    converted, tiny_models, tmp_path
):
    """The main job's pose-aware world model: forecasts and plans at every keyframe with a
    history, each forecast frame placed with the model's own predicted heading."""
    from renderworld.planning import Planner
    from renderworld.world.pose import PoseWarpWorldModel

    root, infos = converted
    _, tok, planner = tiny_models
    torch.manual_seed(1)
    pw = PoseWarpWorldModel(planner.world_model.config, anchors="ctr_cv", movers="learned")
    with torch.no_grad():  # a pose head that turns: headings differ from the travel direction
        for p in pw.pose.parameters():
            p.add_(0.05 * torch.randn_like(p))
    out = tmp_path / "scene.rrd"
    lines: list[str] = []
    summary = write_scene_recording(
        root, out, scene=SCENE, infos_dir=infos, tokenizer=tok, planner=Planner(tok, pw),
        layers=["ego", "forecast"], log=lines.append,
    )  # fmt: skip
    assert summary.skipped == [], lines
    counts, _ = read_back(out)
    assert sorted(counts[("/world/ego/plan/planned", "LineStrips3D:strips")]) == [4, 5, 6, 7]
    # The forecast movers: one path per moving road user, at every keyframe with a history.
    assert len(counts[("/world/ego/movers", "LineStrips3D:strips")]) == 4
    assert max(counts[("/world/ego/movers", "LineStrips3D:strips")]) > 0
    for entity in FORECASTS:
        assert sorted(counts[(entity, "Boxes3D:centers")]) == [4, 5, 6, 7]
