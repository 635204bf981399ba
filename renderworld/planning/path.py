"""The path a plan's candidates follow: a polyline parametrised by arc length.

Frames: the current ego frame (x forward, y left; metres), the ego at the origin.
"""

from __future__ import annotations

import numpy as np

__all__ = ["PlanPath"]

_MAX_TURN = np.radians(60.0)  # a path point turning more than this folds the path


class PlanPath:
    """A polyline path parametrised by arc length (metres), current ego frame.

    Points that would fold the path back (a turn of more than :data:`_MAX_TURN` from the
    previous segment's direction, the first segment's measured from ``start``) are dropped:
    the path goes forward, as a car does; :attr:`folded` says whether any was. So are points
    within ``spacing_m`` of the last point kept (:attr:`thinned`).

    Args:
        points: [K, 2] metres, starting at the ego (duplicates dropped).
        extend_m: straight extension beyond the last point, along the last segment (or
            ``heading`` when the points do not move).
        heading: direction (radians) when the path has no length.
        start: direction (radians) of the car at the first point.
        spacing_m: the least distance between consecutive points kept, metres.
    """

    def __init__(self, points: np.ndarray, extend_m: float, heading: float = 0.0,
                 start: float = 0.0, spacing_m: float = 1e-3):  # fmt: skip
        pts = np.asarray(points, dtype=np.float64)
        keep = [0]
        direction = np.array([np.cos(start), np.sin(start)])
        self.folded = self.thinned = False
        for i in range(1, len(pts)):
            d = pts[i] - pts[keep[-1]]
            n = float(np.hypot(*d))
            if n <= max(spacing_m, 1e-3):
                self.thinned = self.thinned or n > 1e-3
                continue
            if d @ direction < np.cos(_MAX_TURN) * n:
                self.folded = True
                continue
            keep.append(i)
            direction = d / n
        pts = pts[keep]
        if len(pts) >= 2:
            d = pts[-1] - pts[-2]
            heading = float(np.arctan2(d[1], d[0]))
        end = pts[-1] + extend_m * np.array([np.cos(heading), np.sin(heading)])
        self.xy = np.concatenate([pts, end[None]])
        seg = np.hypot(*np.diff(self.xy, axis=0).T)
        self.s = np.r_[0.0, np.cumsum(seg)]
        self.heading = np.arctan2(*np.diff(self.xy, axis=0)[:, ::-1].T)
        self.length = float(self.s[-1])

    def project(self, xy: np.ndarray) -> np.ndarray:
        """[K] arc lengths (metres) of the path points nearest to positions [K, 2]."""
        a, d = self.xy[:-1], np.diff(self.xy, axis=0)  # segments [G, 2]
        rel = np.asarray(xy, dtype=np.float64)[:, None] - a[None]  # [K, G, 2]
        u = np.clip((rel * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-12), 0.0, 1.0)
        dist = np.hypot(*(rel - u[..., None] * d).transpose(2, 0, 1))
        g = dist.argmin(1)
        return self.s[g] + u[np.arange(len(g)), g] * np.diff(self.s)[g]

    def arcs_of(self, plan: np.ndarray) -> np.ndarray:
        """[S] arc lengths (metres) of the plan's waypoints [S, 2] (those the path was built
        through): their polyline's length up to each, or, where the path left points out
        (:attr:`folded`, :attr:`thinned`), their projections onto it, never backwards."""
        plan = np.asarray(plan, dtype=np.float64)
        if self.folded or self.thinned:
            return np.maximum.accumulate(self.project(plan))
        return np.cumsum(np.hypot(*np.diff(np.concatenate([np.zeros((1, 2)), plan]), axis=0).T))

    def frenet(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(arc lengths [K], lateral offsets [K], left +) of positions [K, 2], metres, from
        the path points nearest to them (:meth:`project`)."""
        arc = self.project(xy)
        on, h = self.at(arc)
        rel = np.asarray(xy, dtype=np.float64) - on
        return arc, -np.sin(h) * rel[:, 0] + np.cos(h) * rel[:, 1]

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(positions [..., 2], headings [...]) at arc lengths ``s`` (clipped to the path)."""
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.length)
        k = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.heading) - 1)
        u = (s - self.s[k])[..., None]
        h = self.heading[k]
        return self.xy[k] + u * np.stack([np.cos(h), np.sin(h)], -1), h

    def offset(self, s: np.ndarray, d: float, ramp_m: float, quintic: bool = False) -> np.ndarray:
        """Positions [..., 2] at ``s`` shifted ``d`` metres to the left, reached smoothly over
        the first ``ramp_m`` metres: a cubic smoothstep, or (``quintic``) a quintic one, whose
        curvature starts and ends at 0 (the wheel is turned, not jumped)."""
        xy, h = self.at(s)
        u = np.clip(np.asarray(s) / max(ramp_m, 1e-6), 0.0, 1.0)
        w = d * (u * u * u * (10.0 + u * (6.0 * u - 15.0)) if quintic else u * u * (3 - 2 * u))
        return xy + w[..., None] * np.stack([-np.sin(h), np.cos(h)], -1)
