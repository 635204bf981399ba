"""Simulated LiDAR scans and camera images by ray casting a world.

LiDAR points are written in the LIDAR_TOP frame with (x, y, z, intensity 0..255, ring 0..31)
and one lidarseg label each. Camera images are shaded per class (distinct base colours,
procedural texture in world coordinates so it sticks to surfaces, Lambert sun lighting) with
rays through pixel centres (i + 0.5, j + 0.5).
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import LIDAR_NAME
from renderworld.sim import effects as fx
from renderworld.sim.effects import EffectReport
from renderworld.sim.layout import World
from renderworld.sim.meshes import GROUND_OBJECT, Hits, Raycaster
from renderworld.sim.objects import CLASS_COLOURS
from renderworld.sim.roads import ROAD, SIDEWALK, TERRAIN
from renderworld.sim.scene import SensorSpec
from renderworld.sim.sensors import SensorRig, lidar_beams, rotate

__all__ = ["scan_lidar", "render_camera", "camera_depth", "hit_labels"]

#: LiDAR reflectivity per lidarseg class (0..1); retro-reflective props are bright.
_REFLECT = {2: 0.25, 9: 0.8, 12: 0.85, 14: 0.3, 16: 0.4, 17: 0.4, 18: 0.45, 21: 0.35, 22: 0.35,
            23: 0.45, 24: 0.12, 26: 0.25, 27: 0.2, 28: 0.35, 30: 0.3}  # fmt: skip


def hit_labels(world: World, hits: Hits, points: np.ndarray) -> np.ndarray:
    """lidarseg label [N] uint8 of ray hits (ground from the raster; 0 on a miss)."""
    labels = np.zeros(len(hits.t), dtype=np.uint8)
    obj_labels = np.array([o.label for o in world.objects] + [0], dtype=np.uint8)
    is_obj = hits.obj >= 0
    labels[is_obj] = obj_labels[hits.obj[is_obj]]
    ground = hits.obj == GROUND_OBJECT
    labels[ground] = world.raster.classify(points[ground, :2])
    return labels


def scan_lidar(world, caster: Raycaster, rig: SensorRig, sensors: SensorSpec, t: float,
               ego_pose: np.ndarray, rng, report: EffectReport):  # fmt: skip
    """One LIDAR_TOP sweep at time ``t`` (all rays at ``t``).

    Args:
        ego_pose: [4, 4] ego→scene at ``t``.

    Returns:
        ``(points [N, 5] float32 LiDAR frame, labels [N] uint8 lidarseg, range_image [32, A]
        float32 metres of the true range of every kept return, -1 where none)``.
    """
    el = lidar_beams()
    a = sensors.lidar_azimuth_steps
    az = np.arange(a) * (2 * np.pi / a)
    ce, se = np.cos(el)[:, None], np.sin(el)[:, None]
    dirs_l = np.stack([ce * np.cos(az), ce * np.sin(az), np.broadcast_to(se, (32, a))], -1)
    dirs_l = dirs_l.reshape(-1, 3)
    ring = np.repeat(np.arange(32), a)
    l2s = ego_pose @ rig.sensor_to_ego[LIDAR_NAME]
    dirs = rotate(l2s, dirs_l)
    hits = caster.cast(l2s[:3, 3][None], dirs, t)
    keep = np.isfinite(hits.t) & (hits.t < sensors.lidar_range) & (hits.t > 1.0)
    true_r = hits.t.copy()
    pts_scene = l2s[:3, 3] + dirs * np.where(keep, hits.t, 0.0)[:, None]
    labels = hit_labels(world, hits, pts_scene)
    cos_inc = np.abs((hits.normal * dirs).sum(1))
    refl = np.array([_REFLECT.get(i, 0.3) for i in range(256)], dtype=np.float32)[labels]
    ground = hits.obj == GROUND_OBJECT
    paint = world.raster.paint_at(pts_scene[ground, :2]) > 0
    refl[np.nonzero(ground)[0][paint]] = 0.7
    intensity = 255.0 * refl * (0.3 + 0.7 * cos_inc) * np.clip(8.0 / np.maximum(true_r, 1), 0.15, 1)
    ranges = true_r
    scene = world.name
    if world.spec.effects.lidar_noise:
        with report.effect("lidar_noise", scene):
            ranges, ok = fx.lidar_noise(
                rng, ranges, sensors.lidar_range_sigma, sensors.lidar_dropout
            )
            keep &= ok
    if world.spec.effects.weather != "clear":
        with report.effect(world.spec.effects.weather, scene):
            intensity, ok = fx.lidar_weather(rng, true_r, intensity, world.spec.effects.weather)
            keep &= ok
    range_image = np.where(keep, true_r, -1.0).astype(np.float32).reshape(32, a)
    pts = dirs_l[keep] * ranges[keep, None]
    out = np.concatenate(
        [pts, np.clip(intensity[keep], 0, 255)[:, None], ring[keep, None]], axis=1
    ).astype(np.float32)
    return out, labels[keep], range_image


def _noise(p: np.ndarray, freq: float, salt: int) -> np.ndarray:
    """Value noise in [0, 1] of world points [N, 3], constant per cell of size 1/freq."""
    c = np.floor(p * freq).astype(np.int64)
    h = (c[:, 0] * 73856093) ^ (c[:, 1] * 19349663) ^ (c[:, 2] * 83492791) ^ (salt * 2654435761)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFF).astype(np.float32) / 65535.0


def _albedo(world: World, hits: Hits, labels: np.ndarray, p: np.ndarray) -> np.ndarray:
    n = len(labels)
    col = np.full((n, 3), 0.5, dtype=np.float32)
    obj_col = np.array([o.colour for o in world.objects] + [(0.5, 0.5, 0.5)], np.float32)
    is_obj = hits.obj >= 0
    col[is_obj] = obj_col[hits.obj[is_obj]]
    for lab in (ROAD, SIDEWALK, TERRAIN):
        m = (labels == lab) & (hits.obj == GROUND_OBJECT)
        col[m] = CLASS_COLOURS[lab]
    fine, coarse = _noise(p, 6.0, 1), _noise(p, 0.7, 2)
    tex = 0.85 + 0.2 * fine + 0.15 * coarse
    grass = labels == TERRAIN
    tex[grass] = 0.6 + 0.45 * fine[grass] + 0.3 * coarse[grass]
    tiles = (labels == SIDEWALK) & ((np.mod(p[:, 0], 0.6) < 0.05) | (np.mod(p[:, 1], 0.6) < 0.05))
    tex[tiles] *= 0.7
    veg = labels == 30
    tex[veg] = 0.55 + 0.6 * _noise(p, 3.0, 3)[veg]
    col = col * tex[:, None]
    part = hits.part
    vehicle = (labels >= 14) & (labels <= 23)
    col[vehicle & (part == 1)] = (0.12, 0.15, 0.2)  # glass / cabin
    col[veg & (part == 2)] = (0.35, 0.25, 0.15)  # trunks
    ped = labels == 2
    col[ped & (part == 0)] *= 0.45  # trousers
    col[ped & (part == 2)] = (0.85, 0.65, 0.5)  # heads
    stripes = (part == 3) & (
        ((labels == 9) & (np.mod(np.floor((p[:, 0] + p[:, 1]) / 0.4), 2) == 0))
        | ((labels == 12) & (p[:, 2] > 0.3) & (p[:, 2] < 0.42))
    )
    col[stripes & (labels == 9)] = (0.85, 0.1, 0.1)
    col[stripes & (labels == 12)] = (0.95, 0.95, 0.95)
    # Building facades: windows on vertical faces, darker roofs.
    bld = labels == 28
    vert = np.abs(hits.normal[:, 2]) < 0.5
    u = p[:, 0] * -hits.normal[:, 1] + p[:, 1] * hits.normal[:, 0]
    win = bld & vert & (np.mod(u, 3.0) > 0.8) & (np.mod(u, 3.0) < 2.2)
    win &= (np.mod(p[:, 2], 3.2) > 1.0) & (np.mod(p[:, 2], 3.2) < 2.4) & (p[:, 2] > 1.0)
    col[win] = (0.2, 0.26, 0.33)
    col[bld & ~vert] *= 0.6
    # Road paint.
    g = np.nonzero((hits.obj == GROUND_OBJECT) & (labels == ROAD))[0]
    paint = world.raster.paint_at(p[g, :2])
    col[g[paint == 1]] = (0.9, 0.9, 0.88)
    col[g[paint == 2]] = (0.9, 0.75, 0.2)
    return col


def render_camera(world, caster: Raycaster, rig: SensorRig, channel: str, t: float,
                  ego_pose: np.ndarray, rng, report: EffectReport) -> np.ndarray:  # fmt: skip
    """Render camera ``channel`` at time ``t`` with ego pose [4, 4] → uint8 image [H, W, 3]."""
    w, h = rig.width, rig.height
    c2s = ego_pose @ rig.sensor_to_ego[channel]
    dirs = rotate(c2s.astype(np.float32), rig.pixel_rays(channel, w, h).astype(np.float32))
    origin = c2s[:3, 3].astype(np.float32)
    hits = caster.cast(origin[None], dirs, t)
    hit = np.isfinite(hits.t)
    p = origin + dirs * np.where(hit, hits.t, np.float32(0.0))[:, None]
    labels = hit_labels(world, hits, p)
    col = _albedo(world, hits, labels, p)
    eff = world.spec.effects
    sun = world.sun
    if eff.night:
        with report.effect("night", world.name):
            light = np.full(len(p), 0.06, dtype=np.float32)
            ego_fwd = ego_pose[:3, 0]
            rel = p - ego_pose[:3, 3]
            dist = np.linalg.norm(rel, axis=1) + 1e-6
            ahead = np.clip((rel * ego_fwd).sum(1) / dist, 0, 1) ** 4
            light += (
                1.2
                * ahead
                * np.clip((hits.normal * -rel / dist[:, None]).sum(1), 0, 1)
                / (1 + (dist / 12.0) ** 2)
            )
            near = np.linalg.norm(world.lamps[:, :2] - origin[:2], axis=1)
            lit = hit & (hits.t < 60.0)  # lamps light only nearby surfaces
            p32, n32 = p[lit].astype(np.float32), hits.normal[lit]
            for lamp in world.lamps[np.argsort(near)[:6]].astype(np.float32):
                d = lamp - p32
                r2 = (d * d).sum(1) + 1e-6
                cos = np.clip((n32 * d).sum(1), 0, None) / np.sqrt(r2)
                light[lit] += 0.9 * cos / (1 + r2 / 36.0)
            sky = np.array([0.02, 0.03, 0.07])
    else:
        light = 0.45 + 0.6 * np.clip((hits.normal * sun.astype(np.float32)).sum(1), 0, 1)
        sky = None
    img = col * light.astype(np.float32)[:, None]
    up = np.clip(dirs[:, 2], 0, 1)[:, None]
    sky_col = (
        np.broadcast_to(sky, img.shape)
        if sky is not None
        else (1 - up) * np.float32([0.82, 0.86, 0.92]) + up * np.float32([0.4, 0.55, 0.85])
    )
    img = np.where(hit[:, None], img, sky_col).reshape(h, w, 3)
    if eff.weather == "fog":
        with report.effect("fog", world.name):
            img = fx.camera_fog(img, np.where(hit, hits.t, np.inf).reshape(h, w))
    if eff.weather == "rain":
        with report.effect("rain", world.name):
            img = fx.camera_rain(rng, img)
    if eff.camera_noise:
        with report.effect("camera_noise", world.name):
            img = fx.camera_noise(rng, img, eff.night)
    return (np.clip(img, 0, 1) ** np.float32(1 / 1.1) * 255 + 0.5).astype(np.uint8)


def camera_depth(caster: Raycaster, rig: SensorRig, channel: str, t: float, ego_pose, w, h):
    """Camera z-depth [h, w] (metres, inf on a miss) of a ``w`` x ``h`` ray grid at time ``t``."""
    c2s = ego_pose @ rig.sensor_to_ego[channel]
    d_cam = rig.pixel_rays(channel, w, h)
    hits = caster.cast(c2s[:3, 3][None], rotate(c2s, d_cam), t)
    return (hits.t * d_cam[:, 2]).reshape(h, w)
