"""Run a simulation: scene descriptions → worlds → sensors + Occ3D → a nuScenes-format dataset.

The dataset is written into a temporary directory beside ``out`` and renamed into place at the
end, so an interrupted run never leaves a complete-looking dataset; leftovers of killed runs
are removed by the next run. All scenes are generated and validated before anything is written.
``config.mode`` picks what is written: everything, or only the Occ3D labels, tables and maps
(:mod:`renderworld.sim.modes`).
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from renderworld.constants import CAMERA_NAMES, KEYFRAME_DT, LIDAR_NAME
from renderworld.geometry import pose_to_translation_quaternion
from renderworld.sim.effects import EffectReport
from renderworld.sim.layout import World
from renderworld.sim.meshes import Raycaster
from renderworld.sim.modes import mode_report, scene_description_suffix
from renderworld.sim.occupancy import Voxeliser
from renderworld.sim.render import camera_depth, render_camera, scan_lidar
from renderworld.sim.roads import ROAD
from renderworld.sim.scene import SimConfig
from renderworld.sim.sensors import SensorRig, camera_time_offsets, xform
from renderworld.sim.traffic import build_world
from renderworld.sim.writer import DatasetWriter, link_chain

__all__ = ["simulate", "build_worlds", "ego_pose_matrix", "REPORT_NAME"]

REPORT_NAME = "sim_report.json"
LOCATIONS = ("singapore-onenorth", "boston-seaport", "singapore-queenstown",
             "singapore-hollandvillage")  # fmt: skip
_BASE_TIME = 1531883530_000000  # µs, 2018-07-18


def ego_pose_matrix(world: World, t: float) -> np.ndarray:
    """[4, 4] ego (rear axle) → scene frame at time ``t`` seconds; z = 0."""
    (x, y), yaw = world.ego.trajectory.pose(t)
    m = np.eye(4)
    m[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    m[:2, 3] = x, y
    return m


def build_worlds(config: SimConfig) -> list[World]:
    """Generate and validate every scene of ``config`` (nothing is written)."""
    config.validate()
    return [
        build_world(name, spec, config.keyframes, config.seed, i)
        for i, (name, spec) in enumerate(config.named_scenes)
    ]


def simulate(config: SimConfig, out, overwrite: bool = False, progress: bool = True) -> dict:
    """Simulate ``config`` into the dataset root ``out``.

    Args:
        config: what to simulate (validated first).
        out: dataset root to create.
        overwrite: replace an existing ``out``; otherwise an existing one is an error.
        progress: show a tqdm bar over keyframes.

    Returns:
        The run report (also written to ``<out>/sim_report.json``): counts, bytes, seconds,
        the mode and what it wrote (:func:`renderworld.sim.modes.mode_report`), seconds per
        stage (lidar, camera, semantics, mask_lidar, camera_depth, mask_camera, write_files,
        ...), and per effect whether it ran, in which scenes, and the seconds it took. Files are
        encoded and written on a writer thread beside the simulation: ``write_files`` is the
        time spent handing them over and waiting for it, ``write_tables`` includes the last wait.

    Raises:
        ValueError: on an invalid description (before anything is written).
        FileExistsError: when ``out`` exists and ``overwrite`` is False.
    """
    if not isinstance(config, SimConfig):
        raise TypeError(f"config: expected a SimConfig, got {type(config).__name__}")
    out = Path(out)
    t_start = time.perf_counter()
    report = EffectReport()
    with report.stage("generate"):
        worlds = build_worlds(config)
    if out.exists() and not overwrite:
        raise FileExistsError(f"out: {out} already exists; pass overwrite=True to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)
    for stale in out.parent.glob(f".{out.name}.partial-*"):
        shutil.rmtree(stale, ignore_errors=True)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    tmp.mkdir()
    writer = DatasetWriter(tmp, config.version, config.seed, config.sensors.jpeg_quality,
                           lidarseg=config.mode == "full", background=True)  # fmt: skip
    try:
        s = config.sensors
        rig = SensorRig.build(s.image_width, s.image_height)
        mask_size = (max(int(s.image_width * s.mask_camera_scale), 8),
                     max(int(s.image_height * s.mask_camera_scale), 8))  # fmt: skip
        voxeliser = Voxeliser(rig, s.lidar_azimuth_steps, mask_size)
        _sensor_records(writer)
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(worlds) * config.keyframes, desc="simulating", unit="kf")
        maps: dict[str, dict] = {}
        for i, world in enumerate(worlds):
            _simulate_scene(writer, world, i, config, rig, voxeliser, mask_size, report, maps, bar)
        if bar is not None:
            bar.close()
        with report.stage("write_tables"):
            writer.finish()
            if config.splits is not None:  # the split the infos builder assigns per scene
                writer._write(f"{config.version}/splits.json", config.splits_json())
        result = {
            "dataroot": str(out),
            "version": config.version,
            "scenes": [w.name for w in worlds],
            "keyframes_per_scene": config.keyframes,
            "files": writer.files,
            "bytes": writer.bytes,
            "seconds": round(time.perf_counter() - t_start, 3),
            **mode_report(config.mode),
            **report.to_dict(),
            "config": config.to_dict(),
        }
        import json

        (tmp / REPORT_NAME).write_text(json.dumps(result, indent=1, sort_keys=True))
        if out.exists():
            trash = out.parent / f".{out.name}.old-{os.getpid()}"
            out.rename(trash)
            tmp.rename(out)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            tmp.rename(out)
    except BaseException:
        writer.close()  # no file is written into tmp after this
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    result["summary"] = report.summary()
    return result


def _sensor_records(writer: DatasetWriter) -> None:
    for ch in (LIDAR_NAME, *CAMERA_NAMES):
        modality = "lidar" if ch == LIDAR_NAME else "camera"
        writer.add("sensor", writer.tok("sensor", ch), channel=ch, modality=modality)


def _pose_record(writer, token, pose_global, ts):
    t, q = pose_to_translation_quaternion(pose_global)
    t[2] = 0.0
    writer.add("ego_pose", token, translation=[float(v) for v in t],
               rotation=[float(v) for v in q], timestamp=int(ts))  # fmt: skip


def _simulate_scene(writer, world, i, config, rig, voxeliser, mask_size, report, maps, bar):
    """Write one scene: its log, map and calibration, every keyframe, then the linked chains."""
    name = world.name
    offset = np.eye(4)
    offset[:2, 3] = (300.0 + 137.0 * i, 900.0 + 53.0 * i)
    log_tok, logfile = _write_log_and_map(writer, world, i, maps)
    calib = {}
    for ch in (LIDAR_NAME, *CAMERA_NAMES):
        t, q = pose_to_translation_quaternion(rig.sensor_to_ego[ch])
        k = rig.intrinsics[ch].tolist() if ch in rig.intrinsics else []
        calib[ch] = writer.tok("calibrated_sensor", name, ch)
        writer.add("calibrated_sensor", calib[ch], sensor_token=writer.tok("sensor", ch),
                   translation=[float(v) for v in t], rotation=[float(v) for v in q],
                   camera_intrinsic=k)  # fmt: skip
    with report.stage("static_build"):
        r = world.raster
        ext = (r.x0 - 400, r.y0 - 400, r.x0 + r.shape[0] * r.cell + 400,
               r.y0 + r.shape[1] * r.cell + 400)  # fmt: skip
        caster = Raycaster(world.objects, ext)
    scene = _SceneState(
        writer=writer, world=world, index=i, config=config, rig=rig, voxeliser=voxeliser,
        mask_size=mask_size, report=report, caster=caster, calib=calib, offset=offset,
        logfile=logfile, base_ts=_BASE_TIME + i * 3_600_000_000,
    )  # fmt: skip
    for k in range(config.keyframes):
        _simulate_keyframe(scene, k)
        if bar is not None:
            bar.update(1)
    _finish_scene(scene, log_tok)


@dataclass
class _SceneState:
    """What every keyframe of a scene writes with, and the records it collects for chaining."""

    writer: Any
    world: Any
    index: int
    config: Any
    rig: Any
    voxeliser: Any
    mask_size: tuple
    report: Any
    caster: Any
    calib: dict
    offset: np.ndarray
    logfile: str
    base_ts: int
    samples: list = field(default_factory=list)
    sds: dict = field(default_factory=lambda: {ch: [] for ch in (LIDAR_NAME, *CAMERA_NAMES)})
    anns: dict = field(default_factory=dict)


def _write_log_and_map(writer, world, i, maps) -> tuple[str, str]:
    """The scene's ``log`` record and, once per location, its ``map``; (log token, log name)."""
    loc = LOCATIONS[i % len(LOCATIONS)]
    logfile = f"n015-2018-07-{18 + i % 10:02d}-{10 + i % 12:02d}-{(7 * i) % 60:02d}-00+0800"
    log_tok = writer.tok("log", world.name)
    writer.add("log", log_tok, logfile=logfile, vehicle="n015", date_captured=logfile[5:15],
               location=loc)  # fmt: skip
    if loc not in maps:
        mtok = writer.tok("map", loc)
        r = world.raster
        png = np.where(r.classes[::10, ::10].T[::-1] == ROAD, 255, 0).astype(np.uint8)
        writer.write_map(mtok, png)
        maps[loc] = writer.add("map", mtok, log_tokens=[], category="semantic_prior",
                               filename=f"maps/{mtok}.png")  # fmt: skip
    maps[loc]["log_tokens"].append(log_tok)
    return log_tok, logfile


def _simulate_keyframe(sc: _SceneState, k: int) -> None:
    """Keyframe k: poses, agents, LiDAR, cameras, Occ3D labels and annotations."""
    writer, world, rig, report, name = sc.writer, sc.world, sc.rig, sc.report, sc.world.name
    eff = world.spec.effects
    t = k * KEYFRAME_DT
    ts = sc.base_ts + k * 500_000
    rng = np.random.default_rng([sc.config.seed, sc.index, k, 11])
    s_tok = writer.tok("sample", name, k)
    sc.samples.append(
        writer.add("sample", s_tok, timestamp=ts, scene_token=writer.tok("scene", name))
    )
    cam_off = camera_time_offsets(rig)
    times = {LIDAR_NAME: (t, ts)} | {c: (t + o / 1e6, ts + o) for c, o in cam_off.items()}
    if eff.ego_motion:
        with report.effect("ego_motion", name):
            poses = {c: ego_pose_matrix(world, tc) for c, (tc, _) in times.items()}
    else:
        p0 = ego_pose_matrix(world, 0.0)
        poses = {c: p0 for c in times}
    full = sc.config.mode == "full"
    if sc.caster.moving:
        with report.effect("agent_motion", name):
            for tc, _ in times.values() if full else [times[LIDAR_NAME]]:
                sc.caster.dynamic(tc)
    with report.stage("lidar"):
        pts, labels, range_image = scan_lidar(world, sc.caster, rig, sc.config.sensors, t,
                                              poses[LIDAR_NAME], rng, report)  # fmt: skip
    for ch, (tc, tsc) in times.items():
        sd_tok = writer.tok("sample_data", name, k, ch)
        ext_ = "pcd.bin" if ch == LIDAR_NAME else "jpg"
        rel = f"samples/{ch}/{sc.logfile}__{ch}__{tsc}.{ext_}"
        if full and ch == LIDAR_NAME:
            with report.stage("write_files"):
                writer.write_points(rel, pts)
                writer.write_lidarseg(sd_tok, labels)
        elif full:
            with report.stage("camera"):
                img = render_camera(world, sc.caster, rig, ch, tc, poses[ch], rng, report)
            with report.stage("write_files"):
                writer.write_jpeg(rel, img)
        _pose_record(writer, sd_tok, sc.offset @ poses[ch], tsc)
        sc.sds[ch].append(writer.add(
            "sample_data", sd_tok, sample_token=s_tok, ego_pose_token=sd_tok,
            calibrated_sensor_token=sc.calib[ch], filename=rel,
            fileformat="pcd" if ch == LIDAR_NAME else "jpg",
            width=0 if ch == LIDAR_NAME else rig.width,
            height=0 if ch == LIDAR_NAME else rig.height,
            timestamp=int(tsc), is_key_frame=True))  # fmt: skip
    with report.stage("semantics"):
        sem = sc.voxeliser.semantics(world, t, poses[LIDAR_NAME])
    with report.stage("mask_lidar"):
        p_ego = xform(rig.sensor_to_ego[LIDAR_NAME], pts[:, :3].astype(np.float64))
        m_lidar = sc.voxeliser.mask_lidar(range_image, p_ego)
    with report.stage("camera_depth"):
        depths = [camera_depth(sc.caster, rig, ch, t, poses[LIDAR_NAME], *sc.mask_size)
                  for ch in CAMERA_NAMES]  # fmt: skip
    with report.stage("mask_camera"):
        m_cam = sc.voxeliser.mask_camera(depths, m_lidar)
    with report.stage("write_files"):
        writer.write_occ3d(name, s_tok, sem, m_lidar, m_cam)
    with report.stage("annotations"):
        l2g = sc.offset @ poses[LIDAR_NAME] @ rig.sensor_to_ego[LIDAR_NAME]
        _annotate(writer, world, name, k, t, s_tok, sc.offset, l2g, pts, sc.anns)


def _finish_scene(sc: _SceneState, log_tok: str) -> None:
    """Link the prev/next chains, write the instances and the scene record."""
    writer, name, spec = sc.writer, sc.world.name, sc.world.spec
    eff = spec.effects
    link_chain(sc.samples)
    for chain in sc.sds.values():
        link_chain(chain)
    for key, chain in sorted(sc.anns.items()):
        link_chain(chain)
        obj_cat = chain[0].pop("_category")
        for rec in chain[1:]:
            rec.pop("_category")
        writer.add("instance", writer.tok("instance", name, key),
                   category_token=writer.tok("category", obj_cat), nbr_annotations=len(chain),
                   first_annotation_token=chain[0]["token"],
                   last_annotation_token=chain[-1]["token"])  # fmt: skip
    # renderworld.sim.scene.behaviour_of reads the behaviour back from this description.
    desc = f"{spec.kind.replace('_', '-')}, {spec.behaviour.replace('_', ' ')}"
    desc += ", rain" if eff.weather == "rain" else ", fog" if eff.weather == "fog" else ""
    desc += ", night" if eff.night else ", day"
    desc += scene_description_suffix(sc.config.mode)
    writer.add("scene", writer.tok("scene", name), name=name, description=f"Simulated {desc}",
               log_token=log_tok, nbr_samples=len(sc.samples),
               first_sample_token=sc.samples[0]["token"],
               last_sample_token=sc.samples[-1]["token"])  # fmt: skip


def _annotate(writer, world, name, k, t, s_tok, offset, l2g, pts, anns) -> None:
    ego_xy = world.ego.trajectory.pose(t)[0]
    pts_g = xform(l2g, pts[:, :3].astype(np.float64))
    for obj in world.objects:
        if not obj.annotate:
            continue
        (xy, yaw) = obj.trajectory.pose(t)
        yaw = float(np.mod(yaw + np.pi, 2 * np.pi) - np.pi)
        if np.hypot(*(xy - ego_xy)) > 50.0:
            continue
        w, ln, h = obj.size
        centre = np.array([xy[0], xy[1], h / 2, 1.0]) @ offset.T
        c, s = np.cos(yaw), np.sin(yaw)
        rel = pts_g - centre[:3]
        lx, ly = rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c
        n_pts = int(
            ((np.abs(lx) <= ln / 2) & (np.abs(ly) <= w / 2) & (np.abs(rel[:, 2]) <= h / 2)).sum()
        )
        speed = obj.trajectory.speed(t) if obj.moving else 0.0
        if obj.label in (14, 21):
            attr = "cycle.with_rider"
        elif obj.label == 2:
            attr = "pedestrian.moving" if speed > 0.2 else "pedestrian.standing"
        elif obj.category.startswith("vehicle."):
            attr = (
                "vehicle.moving"
                if speed > 0.3
                else "vehicle.stopped"
                if obj.moving
                else "vehicle.parked"
            )
        else:
            attr = None
        vis = "4" if n_pts >= 10 else "3" if n_pts >= 5 else "2" if n_pts >= 1 else "1"
        rec = writer.add(
            "sample_annotation", writer.tok("sample_annotation", name, obj.key, k),
            sample_token=s_tok, instance_token=writer.tok("instance", name, obj.key),
            attribute_tokens=[writer.tok("attribute", attr)] if attr else [],
            visibility_token=vis, translation=[float(v) for v in centre[:3]],
            size=[float(w), float(ln), float(h)],
            rotation=[float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))],
            num_lidar_pts=n_pts, num_radar_pts=0, _category=obj.category)  # fmt: skip
        anns.setdefault(obj.key, []).append(rec)
