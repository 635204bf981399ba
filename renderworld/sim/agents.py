"""Motion: paths, speed profiles, trajectories and box-overlap checks.

A :class:`Trajectory` samples an agent's ground pose (x, y, yaw; scene frame, metres and
radians) densely in time (seconds from the scene start) and interpolates between samples.
Agents follow lane paths (:class:`Path`) with a speed profile; overlaps between boxes are found
with a vectorised separating-axis test so that generated scenes never interpenetrate.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Path", "Trajectory", "rects_overlap", "arc_path", "transition_arc", "DT_MOTION"]

DT_MOTION = 0.02  # seconds between trajectory samples


class Path:
    """A polyline resampled every 0.2 m, with arc length, position and heading lookups.

    Args:
        points: [P, 2] waypoints, metres, scene frame.
    """

    def __init__(self, points: np.ndarray):
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[0] < 2 or pts.shape[1] != 2:
            raise ValueError(f"points: expected shape [P>=2, 2], got {pts.shape}")
        seg = np.hypot(*np.diff(pts, axis=0).T)
        keep = np.concatenate([[True], seg > 1e-9])
        pts = pts[keep]
        s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
        n = max(int(np.ceil(s[-1] / 0.2)) + 1, 2)
        self.s = np.linspace(0.0, s[-1], n)
        self.xy = np.stack([np.interp(self.s, s, pts[:, 0]), np.interp(self.s, s, pts[:, 1])], -1)
        d = np.gradient(self.xy, self.s, axis=0)
        self.heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))

    @property
    def length(self) -> float:
        """Path length, metres."""
        return float(self.s[-1])

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points [N, 2] and headings [N] (rad) at arc lengths ``s`` [N] (clamped to the path)."""
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.length)
        xy = np.stack(
            [np.interp(s, self.s, self.xy[:, 0]), np.interp(s, self.s, self.xy[:, 1])], -1
        )
        return xy, np.interp(s, self.s, self.heading)

    def offset(self, lateral) -> Path:
        """A path displaced by ``lateral`` metres (left +): a scalar or a callable of arc length."""
        d = lateral(self.s) if callable(lateral) else np.full_like(self.s, float(lateral))
        normal = np.stack([-np.sin(self.heading), np.cos(self.heading)], -1)
        return Path(self.xy + d[:, None] * normal)

    def project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Arc length [N] of the nearest path sample and distance [N] to it, for points [N, 2]."""
        xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))
        d2 = ((xy[:, None, :] - self.xy[None, :, :]) ** 2).sum(-1)
        i = d2.argmin(1)
        return self.s[i], np.sqrt(d2[np.arange(len(xy)), i])


def transition_arc(radius: float, angle: float, transition: float, ds: float = 0.05):
    """A turn whose curvature ramps linearly (clothoids) into and out of a circular arc.

    Args:
        radius: the arc's radius, metres (the tightest of the turn).
        angle: signed total turn, radians (left > 0), 0 < |angle| < 170 degrees.
        transition: length of each clothoid, metres (> 0).
        ds: integration step, metres.

    Returns:
        (points [N, 2] from the origin heading +x, shift): ``shift`` is how much farther from
        the start the crossing of the entry and exit tangents lies than a plain arc's (metres).
    """
    a = abs(angle)
    if not 0.0 < a < np.deg2rad(170.0) or transition <= 0.0 or transition > radius * a:
        raise ValueError(
            f"transition_arc: need 0 < |angle| < 170 deg and 0 < transition <= radius * |angle|, "
            f"got angle {np.rad2deg(angle):.1f} deg, transition {transition} m, radius {radius} m"
        )
    length = radius * a + transition
    s = np.linspace(0.0, length, max(int(np.ceil(length / ds)), 2) + 1)
    kappa = np.minimum(1.0, np.minimum(s, length - s) / transition) / radius
    h = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * np.diff(s))])
    h *= angle / h[-1]  # signed, and exact at the end despite the quadrature
    mid = 0.5 * (h[1:] + h[:-1])
    xy = np.concatenate(
        [
            np.zeros((1, 2)),
            np.cumsum(np.diff(s)[:, None] * np.stack([np.cos(mid), np.sin(mid)], -1), 0),
        ]
    )
    x_cross = xy[-1, 0] - xy[-1, 1] * np.cos(angle) / np.sin(angle)
    return xy, float(x_cross - radius * np.tan(a / 2))


def arc_path(
    start, heading: float, pieces: list[tuple[str, float, float]], transition: float = 0.0
) -> np.ndarray:
    """Waypoints [P, 2] of straight and circular pieces.

    Args:
        start: (x, y) metres.
        heading: initial heading, radians.
        pieces: ``("line", length, 0)`` or ``("arc", radius, signed_angle)`` (left turn > 0).
        transition: metres of clothoid into and out of every arc (0: the curvature jumps). The
            arc keeps its radius and its entry and exit lines; the turn starts ``shift`` earlier
            and ends ``shift`` later on them (:func:`transition_arc`), so each arc must sit
            between two lines; where one is shorter than the shift, the transition shortens.
    """
    pieces = [list(p) for p in pieces]
    turns = {}
    if transition > 0.0:
        for i, (kind, radius, angle) in enumerate(pieces):
            if kind != "arc":
                continue
            near = [pieces[j] for j in (i - 1, i + 1) if 0 <= j < len(pieces)]
            if len(near) < 2 or any(p[0] != "line" for p in near):
                raise ValueError(f"arc_path: arc {i} needs a line on both sides for a transition")
            room = min(p[1] for p in near)
            length = min(transition, radius * abs(angle))
            for _ in range(8):  # a short line gets a shorter transition (shift ~ length / 2)
                xy, shift = transition_arc(radius, angle, length)
                if shift < room:
                    break
                length *= 0.9 * room / shift
            else:
                raise ValueError(f"arc_path: arc {i} has no room for a transition ({room} m)")
            for p in near:
                p[1] -= shift
            turns[i] = xy
    pts = [np.asarray(start, dtype=np.float64)]
    h = float(heading)
    for i, (kind, a, b) in enumerate(pieces):
        p = pts[-1]
        if kind == "line":
            n = max(int(a / 2.0), 1)
            for k in range(1, n + 1):
                pts.append(p + (a * k / n) * np.array([np.cos(h), np.sin(h)]))
        elif i in turns:
            rot = np.array([[np.cos(h), -np.sin(h)], [np.sin(h), np.cos(h)]])
            pts.extend(p + turns[i][10::10] @ rot.T)
            if len(turns[i]) % 10 != 1:
                pts.append(p + rot @ turns[i][-1])
            h += b
        else:
            radius, angle = a, b
            side = np.sign(angle)
            centre = p + side * radius * np.array([-np.sin(h), np.cos(h)])
            n = max(int(abs(angle) / np.deg2rad(2.0)), 2)
            for k in range(1, n + 1):
                hk = h + angle * k / n
                pts.append(centre - side * radius * np.array([-np.sin(hk), np.cos(hk)]))
            h += angle
    return np.stack(pts)


class Trajectory:
    """Ground poses sampled at ``times`` (seconds): x, y [T] metres and yaw [T] radians.

    Args:
        times: [T] strictly increasing seconds.
        xy: [T, 2] metres, scene frame.
        yaw: [T] radians (unwrapped or not).
    """

    def __init__(self, times: np.ndarray, xy: np.ndarray, yaw: np.ndarray):
        self.times = np.asarray(times, dtype=np.float64)
        self.xy = np.asarray(xy, dtype=np.float64)
        self.yaw = np.unwrap(np.asarray(yaw, dtype=np.float64))
        if self.xy.shape != (len(self.times), 2) or self.yaw.shape != self.times.shape:
            raise ValueError(
                f"xy/yaw: expected [T, 2] and [T] for T={len(self.times)}, got "
                f"{self.xy.shape} and {self.yaw.shape}"
            )

    @classmethod
    def along(cls, path: Path, s_of_t: np.ndarray, times: np.ndarray, reverse=False) -> Trajectory:
        """Follow ``path`` with arc length ``s_of_t`` [T] at ``times`` [T]."""
        xy, heading = path.at(s_of_t)
        return cls(times, xy, heading + (np.pi if reverse else 0.0))

    @classmethod
    def fixed(cls, times: np.ndarray, x: float, y: float, yaw: float) -> Trajectory:
        """A static pose at every time."""
        n = len(times)
        return cls(times, np.tile([x, y], (n, 1)), np.full(n, yaw))

    def pose(self, t) -> tuple[np.ndarray, np.ndarray]:
        """(xy [..., 2], yaw [...]) at time(s) ``t`` seconds (clamped to the sampled span)."""
        t = np.asarray(t, dtype=np.float64)
        x = np.interp(t, self.times, self.xy[:, 0])
        y = np.interp(t, self.times, self.xy[:, 1])
        return np.stack([x, y], -1), np.interp(t, self.times, self.yaw)

    def speed(self, t: float) -> float:
        """Speed, m/s, at time ``t`` (finite difference over 0.1 s)."""
        a, _ = self.pose(t - 0.05)
        b, _ = self.pose(t + 0.05)
        return float(np.hypot(*(b - a)) / 0.1)


def rects_overlap(ca, yaw_a, half_a, cb, yaw_b, half_b) -> np.ndarray:
    """Whether oriented rectangles overlap (separating-axis test), broadcasting over batch dims.

    Args:
        ca, cb: [..., 2] centres, metres.
        yaw_a, yaw_b: [...] headings of the rectangles' length axes, radians.
        half_a, half_b: [..., 2] half (length, width), metres.

    Returns:
        [...] bool, True where the closed rectangles intersect.
    """
    ca, cb = np.asarray(ca, dtype=np.float64), np.asarray(cb, dtype=np.float64)
    half_a, half_b = np.asarray(half_a, dtype=np.float64), np.asarray(half_b, dtype=np.float64)
    ua = np.stack([np.cos(yaw_a), np.sin(yaw_a)], -1)
    va = np.stack([-np.sin(yaw_a), np.cos(yaw_a)], -1)
    ub = np.stack([np.cos(yaw_b), np.sin(yaw_b)], -1)
    vb = np.stack([-np.sin(yaw_b), np.cos(yaw_b)], -1)
    d = cb - ca
    separated = np.zeros(np.broadcast_shapes(d.shape[:-1], ua.shape[:-1], ub.shape[:-1]), bool)
    for axis in (ua, va, ub, vb):
        ra = half_a[..., 0] * np.abs((ua * axis).sum(-1)) + half_a[..., 1] * np.abs(
            (va * axis).sum(-1)
        )
        rb = half_b[..., 0] * np.abs((ub * axis).sum(-1)) + half_b[..., 1] * np.abs(
            (vb * axis).sum(-1)
        )
        separated |= np.abs((d * axis).sum(-1)) > ra + rb
    return ~separated
