"""Optional effects and the run report.

Each effect (ego motion, agent motion, LiDAR noise, camera noise, rain, fog, night) is a
separate function called only when a scene's description enables it; :class:`EffectReport`
records which effects ran, how often, and the time they took, next to the fixed stages
(static scene build, ray casting, shading, voxelising, writing).
"""

from __future__ import annotations

import time
from contextlib import contextmanager

import numpy as np

__all__ = [
    "EFFECTS",
    "EffectReport",
    "lidar_noise",
    "lidar_weather",
    "camera_noise",
    "camera_fog",
    "camera_rain",
]

EFFECTS: tuple[str, ...] = (
    "ego_motion",
    "agent_motion",
    "lidar_noise",
    "camera_noise",
    "rain",
    "fog",
    "night",
)


class EffectReport:
    """Which effects ran and what every effect and stage cost (seconds, wall clock)."""

    def __init__(self):
        self.effects = {
            e: {"ran": False, "calls": 0, "seconds": 0.0, "scenes": []} for e in EFFECTS
        }
        self.stages: dict[str, dict] = {}

    @contextmanager
    def effect(self, name: str, scene: str):
        """Time one call of effect ``name`` for ``scene``."""
        if name not in self.effects:
            raise ValueError(f"effect: unknown effect {name!r}; expected one of {EFFECTS}")
        t0 = time.perf_counter()
        try:
            yield
        finally:
            e = self.effects[name]
            e["ran"] = True
            e["calls"] += 1
            e["seconds"] += time.perf_counter() - t0
            if scene not in e["scenes"]:
                e["scenes"].append(scene)

    @contextmanager
    def stage(self, name: str):
        """Time one call of the fixed stage ``name``."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            s = self.stages.setdefault(name, {"calls": 0, "seconds": 0.0})
            s["calls"] += 1
            s["seconds"] += time.perf_counter() - t0

    def ran(self) -> list[str]:
        """Names of the effects that ran at least once."""
        return [k for k, v in self.effects.items() if v["ran"]]

    def to_dict(self) -> dict:
        """JSON-serialisable form (seconds rounded to 0.1 ms)."""
        eff = {k: {**v, "seconds": round(v["seconds"], 4)} for k, v in self.effects.items()}
        st = {k: {**v, "seconds": round(v["seconds"], 4)} for k, v in self.stages.items()}
        return {"effects": eff, "stages": st}

    def summary(self) -> str:
        """Human-readable table of effects and stages."""
        lines = ["effect         ran   calls  seconds"]
        for k, v in self.effects.items():
            lines.append(
                f"{k:<14} {'yes' if v['ran'] else 'no ':<5} {v['calls']:>5}  {v['seconds']:7.2f}"
            )
        lines.append("stage          calls  seconds")
        for k, v in self.stages.items():
            lines.append(f"{k:<14} {v['calls']:>5}  {v['seconds']:7.2f}")
        return "\n".join(lines)


def lidar_noise(
    rng, ranges: np.ndarray, sigma: float, dropout: float
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian range noise (``sigma`` m) and random dropout; returns (ranges [N], keep [N])."""
    noisy = ranges + rng.normal(0.0, sigma, ranges.shape).astype(ranges.dtype)
    return noisy, rng.random(ranges.shape) >= dropout


def lidar_weather(rng, ranges: np.ndarray, intensity: np.ndarray, weather: str):
    """Rain/fog: range-dependent extinction of returns and weaker intensities.

    Returns:
        (intensity [N], keep [N] bool).
    """
    visibility = 60.0 if weather == "fog" else 250.0  # metres (meteorological visibility)
    trans = np.exp(-2.0 * 3.0 * ranges / visibility)  # two-way Beer-Lambert, 3/visibility per m
    keep = rng.random(ranges.shape) < np.clip(trans * 1.6, 0.0, 1.0)
    if weather == "rain":
        keep &= rng.random(ranges.shape) >= 0.05
    return intensity * trans, keep


def camera_noise(rng, img: np.ndarray, night: bool) -> np.ndarray:
    """Exposure variation and sensor noise on a linear RGB image [H, W, 3] in 0..1."""
    gain = rng.normal(1.0, 0.06)
    sigma = 0.035 if night else 0.015
    noise = rng.standard_normal(img.shape, dtype=np.float32) * np.float32(sigma)
    return img * np.float32(gain) + noise


def camera_fog(img: np.ndarray, depth: np.ndarray, colour=(0.75, 0.77, 0.8), beta=35.0):
    """Blend towards the fog colour by ``1 - exp(-depth / beta)``; depth [H, W] metres (inf sky)."""
    a = np.exp(-np.minimum(depth, 1e4) / beta)[..., None]
    return img * a + np.asarray(colour) * (1 - a)


def camera_rain(rng, img: np.ndarray) -> np.ndarray:
    """Darker, desaturated image with short bright rain streaks."""
    grey = img.mean(-1, keepdims=True)
    out = 0.8 * (0.7 * img + 0.3 * grey)
    h, w = img.shape[:2]
    n = max(h * w // 600, 1)
    xs, ys = rng.integers(0, w, n), rng.integers(0, h, n)
    lengths = rng.integers(max(h // 40, 2), max(h // 15, 3), n)
    for x, y, ln in zip(xs, ys, lengths):
        out[y : y + ln, x] = out[y : y + ln, x] * 0.6 + 0.35
    return out
