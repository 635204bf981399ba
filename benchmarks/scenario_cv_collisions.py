"""How often a constant-velocity (CV) plan collides with GT agent boxes, per simulator preset.

    PYTHONPATH=. python benchmarks/scenario_cv_collisions.py [preset ...]

Builds the worlds of each preset (nothing is written) and, for every keyframe with 5 history
and 6 future keyframes, runs the planning collision metric (``collisions_with_boxes``: ego box
centred at each waypoint, 0.5 m BEV raster) on the CV plan (the last 0.5 s displacement
repeated 6 times) and on the true future against the boxes of every vehicle, pedestrian and
movable object within the grid. Prints the fraction of windows with a collision at any of the
6 steps, for all scenes, the interaction scenes and each behaviour.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from renderworld.constants import FUTURE_FRAMES, HISTORY_FRAMES, KEYFRAME_DT  # noqa: E402
from renderworld.metrics.collision import collisions_with_boxes  # noqa: E402
from renderworld.sim import build_worlds  # noqa: E402
from renderworld.sim.scene import INTERACTIONS  # noqa: E402
from tools.make_fixtures import config_from_preset  # noqa: E402

_AGENTS = ("vehicle.", "human.", "movable_object.")


def _boxes(world, k, p, yaw):
    """[6, M, 5] agent boxes (x, y, length, width, yaw) of steps k+1..k+6, frame of keyframe k."""
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, s], [-s, c]])
    objs = [o for o in world.objects if o.annotate and o.category.startswith(_AGENTS)]
    out = np.zeros((FUTURE_FRAMES, max(len(objs), 1), 5))
    out[..., :2] = 1e3  # padding far outside the grid when there is no agent
    for m, o in enumerate(objs):
        for j in range(FUTURE_FRAMES):
            xy, a = o.trajectory.pose((k + j + 1) * KEYFRAME_DT)
            q = rot @ (xy - p)
            out[j, m] = (q[0], q[1], o.size[1], o.size[0], a - yaw)
    return out, rot


def rates(preset: str) -> dict[str, tuple[int, int, int]]:
    """{group: (windows, CV collisions, true-future collisions)}: ``all``, ``interaction`` and
    one group per behaviour."""
    cfg = config_from_preset(preset)
    res = {"all": [0, 0, 0], "interaction": [0, 0, 0]}
    for world in build_worlds(cfg):
        tr = world.ego.trajectory
        for k in range(HISTORY_FRAMES - 1, cfg.keyframes - FUTURE_FRAMES):
            (p0, _), (p, yaw) = tr.pose((k - 1) * KEYFRAME_DT), tr.pose(k * KEYFRAME_DT)
            boxes, rot = _boxes(world, k, p, yaw)
            j = np.arange(1, FUTURE_FRAMES + 1)[:, None]
            cv = j * (rot @ (p - p0))
            gt = (tr.pose((k + j[:, 0]) * KEYFRAME_DT)[0] - p) @ rot.T
            hit, _ = collisions_with_boxes(np.stack([cv, gt]), boxes)
            b = world.spec.behaviour
            groups = ["all", *(["interaction"] if b in INTERACTIONS else []), b]
            for g in groups:
                res.setdefault(g, [0, 0, 0])
                res[g][0] += 1
                res[g][1] += int(hit[0].any())
                res[g][2] += int(hit[1].any())
    return {g: tuple(v) for g, v in res.items()}


def main(presets: list[str]) -> None:
    print(f"{'preset':<14}{'scenes':<18}{'windows':>8}{'CV coll.':>10}{'GT coll.':>10}")
    for preset in presets:
        for group, (n, cv, gt) in rates(preset).items():
            if n:
                print(f"{preset:<14}{group:<18}{n:>8}{cv / n:>10.1%}{gt / n:>10.1%}")


if __name__ == "__main__":
    main(sys.argv[1:] or ["mini", "interactions", "scenarios"])
