"""Planning metrics: L2 (two named conventions) and collision rate.

Protocol (docs/protocol.md#planning-l2, #collision-rate). Trajectories are [S, 2] waypoints of
frames t+1..t+S (0.5 s apart) in the current ego frame, metres. Error at step k = Euclidean distance
of waypoint k.

* ``l2_at_horizon@Hs`` (UniAD; the paper's Table 6.3): mean over samples of the error at the
  horizon's step (1 s = step 2, 2 s = 4, 3 s = 6).
* ``l2_mean_to_horizon@Hs`` (ST-P3 / VAD): mean of the errors of all steps 1..k over samples.
* ``collision_<source>_at_horizon@Hs`` / ``collision_<source>_mean_to_horizon@Hs``: fraction of
  evaluated waypoints whose ego box collides (at the step / over steps 1..k), for
  source ``boxes`` (future GT agent boxes on a 0.5 m BEV) and ``occupancy`` (future GT object
  voxels, classes 1..10). See :mod:`renderworld.metrics.collision` for the box rules.
* Steps with ``valid`` False (the scene ended) are excluded everywhere and counted
  (``masked_steps``); steps where the GT trajectory itself collides are excluded from that
  source's rate and counted (``collision_<source>_gt_skipped``); steps whose ego box falls
  outside the raster are excluded and counted (``collision_<source>_outside_grid``).
* ``collision_<source>_hits_<convention>@Hs`` / ``collision_<source>_evaluated_<convention>@Hs``:
  the integer counts behind each rate (colliding waypoints / evaluated waypoints).
* ``avg`` = mean of the horizon values. Rates are fractions (tables print percent).
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import FUTURE_FRAMES, OCC3D_GRID, GridSpec
from renderworld.metrics.collision import (
    COLLISION_BEV_GRID,
    BevGrid,
    collisions_with_boxes,
    collisions_with_occupancy,
)
from renderworld.metrics.forecast import FORECAST_HORIZONS_S, checked_horizons
from renderworld.metrics.occupancy import _to_numpy

__all__ = ["PLANNING_PROTOCOL", "PlanningMetric", "l2_errors"]

PLANNING_PROTOCOL = (
    "L2 at-horizon = UniAD (error at the step), mean-to-horizon = ST-P3/VAD (mean over steps "
    "up to it); collision: ego box 4.084x1.85 m centred at the waypoint, heading = travel "
    "direction, vs GT agent boxes (0.5 m BEV) and GT object occupancy (classes 1-10); steps "
    "where the GT trajectory collides are skipped and counted; masked steps excluded"
)


def l2_errors(pred, gt) -> np.ndarray:
    """Per-step Euclidean error.

    Args:
        pred: [..., S, 2] metres.
        gt: same shape.

    Returns:
        [..., S] float64 metres.
    """
    p, g = (
        np.asarray(_to_numpy(pred, "pred"), np.float64),
        np.asarray(_to_numpy(gt, "gt"), np.float64),
    )
    if p.shape != g.shape or p.ndim < 2 or p.shape[-1] != 2:
        raise ValueError(f"pred: expected [..., S, 2] matching gt {g.shape}, got {p.shape}")
    if not (np.isfinite(p).all() and np.isfinite(g).all()):
        raise ValueError("pred/gt: expected finite trajectories, got NaN or inf")
    return np.sqrt(((p - g) ** 2).sum(-1))


class PlanningMetric:
    """Accumulates planning L2 and collision statistics over a split.

    Args:
        steps: S waypoints per trajectory (6 = 3 s).
        horizons_s: reported horizons (seconds).
        box_grid: BEV raster for agent boxes.
        occupancy_grid: voxel grid of the GT occupancy passed to ``update``.
    """

    SOURCES = ("boxes", "occupancy")

    def __init__(
        self,
        steps: int = FUTURE_FRAMES,
        horizons_s=FORECAST_HORIZONS_S,
        box_grid: BevGrid = COLLISION_BEV_GRID,
        occupancy_grid: GridSpec = OCC3D_GRID,
    ):
        self.steps = steps
        self.horizons_s, self.horizon_steps = checked_horizons(steps, horizons_s)
        self.box_grid = box_grid
        self.occupancy_grid = occupancy_grid
        self.reset()

    def reset(self) -> None:
        """Zero every count."""
        s = self.steps
        self.err_sum = np.zeros(s)
        self.err_count = np.zeros(s, dtype=np.int64)
        self.masked_steps = 0
        self.num_samples = 0
        self.coll = {
            src: {
                k: np.zeros(s, dtype=np.int64)
                for k in ("hit", "evaluated", "gt_skipped", "outside")
            }
            for src in self.SOURCES
        }
        self.sources_seen: set[str] = set()

    def update(
        self,
        pred,
        gt,
        valid=None,
        agent_boxes=None,
        agent_valid=None,
        occupancy=None,
        occupancy_poses=None,
    ) -> None:
        """Add a batch of B planned trajectories.

        Args:
            pred: [B, S, 2] (or [S, 2]) planned waypoints, metres, current ego frame.
            gt: same shape, GT future ego positions.
            valid: [B, S] bool (False past the scene end) or None.
            agent_boxes: per sample [S, M, 5|7] GT agent boxes (sequence of B arrays, M may
                differ) or None to skip the box collision source.
            agent_valid: per sample [S, M] bool or None.
            occupancy: [B, S, X, Y, Z] GT future occupancy on ``occupancy_grid`` or None.
            occupancy_poses: [B, S, 3] (x, y, yaw) of each occupancy frame in the current ego
                frame, or None when the occupancy is in the current ego frame.
        """
        p = np.asarray(_to_numpy(pred, "pred"), np.float64)
        batched = p.ndim == 3
        if not batched:
            p = p[None]
            gt = np.asarray(_to_numpy(gt, "gt"))[None]
            valid = None if valid is None else np.asarray(_to_numpy(valid, "valid"))[None]
            agent_boxes = None if agent_boxes is None else [agent_boxes]
            agent_valid = None if agent_valid is None else [agent_valid]
            occupancy = (
                None if occupancy is None else np.asarray(_to_numpy(occupancy, "occupancy"))[None]
            )
            occupancy_poses = None if occupancy_poses is None else np.asarray(occupancy_poses)[None]
        if p.ndim != 3 or p.shape[1] != self.steps:
            raise ValueError(f"pred: expected [B, {self.steps}, 2], got {p.shape}")
        err = l2_errors(p, gt)  # validates gt shape and finiteness
        b = p.shape[0]
        if valid is None:
            v = np.ones((b, self.steps), dtype=bool)
        else:
            v = np.asarray(_to_numpy(valid, "valid"))
            if v.shape != (b, self.steps) or v.dtype != np.bool_:
                raise ValueError(
                    f"valid: expected bool [{b}, {self.steps}], got {v.dtype} {v.shape}"
                )
        g = np.asarray(_to_numpy(gt, "gt"), np.float64)
        self.num_samples += b
        self.masked_steps += int((~v).sum())
        self.err_sum += np.where(v, err, 0.0).sum(0)
        self.err_count += v.sum(0)

        if agent_boxes is not None:
            if len(agent_boxes) != b or (agent_valid is not None and len(agent_valid) != b):
                raise ValueError(
                    f"agent_boxes: expected {b} per-sample arrays, got {len(agent_boxes)}"
                )
            self.sources_seen.add("boxes")
            for i in range(b):
                bv = None if agent_valid is None else agent_valid[i]
                hit, ok = collisions_with_boxes(
                    np.stack([p[i], g[i]]), agent_boxes[i], bv, self.box_grid
                )
                self._count("boxes", (hit[0], ok[0]), (hit[1], ok[1]), v[i])
        if occupancy is not None:
            occ = np.asarray(_to_numpy(occupancy, "occupancy"))
            if occ.ndim != 5 or occ.shape[:2] != (b, self.steps):
                raise ValueError(
                    f"occupancy: expected [{b}, {self.steps}, X, Y, Z], got {occ.shape}"
                )
            self.sources_seen.add("occupancy")
            for i in range(b):
                poses = None if occupancy_poses is None else occupancy_poses[i]
                hit, ok = collisions_with_occupancy(
                    np.stack([p[i], g[i]]), occ[i], self.occupancy_grid, poses
                )
                self._count("occupancy", (hit[0], ok[0]), (hit[1], ok[1]), v[i])

    def _count(self, src: str, pred_c, gt_c, valid: np.ndarray) -> None:
        (p_hit, p_eval), (g_hit, _) = pred_c, gt_c
        c = self.coll[src]
        gt_skip = valid & g_hit
        outside = valid & ~g_hit & ~p_eval
        use = valid & ~g_hit & p_eval
        c["gt_skipped"] += gt_skip
        c["outside"] += outside
        c["evaluated"] += use
        c["hit"] += use & p_hit

    def merge(self, other: PlanningMetric) -> PlanningMetric:
        """Add another accumulator's counts; returns self."""
        if not isinstance(other, PlanningMetric) or other.steps != self.steps:
            raise ValueError("other: expected a PlanningMetric with the same steps")
        self.err_sum += other.err_sum
        self.err_count += other.err_count
        self.masked_steps += other.masked_steps
        self.num_samples += other.num_samples
        for src in self.SOURCES:
            for k in self.coll[src]:
                self.coll[src][k] += other.coll[src][k]
        self.sources_seen |= other.sources_seen
        return self

    @staticmethod
    def _ratio(num, den) -> float:
        return float(num / den) if den > 0 else float("nan")

    def compute(self) -> dict:
        """All accumulated metrics (keys in the module docstring), plus counts and protocol.

        A collision source never passed to ``update`` is absent from the output (not zero).
        """
        out: dict = {"num_samples": self.num_samples, "masked_steps": self.masked_steps}
        for name, num, den in (("l2", self.err_sum, self.err_count),) + tuple(
            (f"collision_{s}", self.coll[s]["hit"], self.coll[s]["evaluated"])
            for s in self.SOURCES
            if s in self.sources_seen
        ):
            at, mean = [], []
            for h, k in zip(self.horizons_s, self.horizon_steps):
                at.append(self._ratio(num[k - 1], den[k - 1]))
                mean.append(self._ratio(num[:k].sum(), den[:k].sum()))
                out[f"{name}_at_horizon@{h:g}s"] = at[-1]
                out[f"{name}_mean_to_horizon@{h:g}s"] = mean[-1]
            out[f"{name}_at_horizon_avg"] = float(np.mean(at))
            out[f"{name}_mean_to_horizon_avg"] = float(np.mean(mean))
            if name == "l2":
                continue
            for h, k in zip(self.horizons_s, self.horizon_steps):  # the rates' counts
                out[f"{name}_hits_at_horizon@{h:g}s"] = int(num[k - 1])
                out[f"{name}_evaluated_at_horizon@{h:g}s"] = int(den[k - 1])
                out[f"{name}_hits_mean_to_horizon@{h:g}s"] = int(num[:k].sum())
                out[f"{name}_evaluated_mean_to_horizon@{h:g}s"] = int(den[:k].sum())
        for s in self.SOURCES:
            if s in self.sources_seen:
                out[f"collision_{s}_gt_skipped"] = int(self.coll[s]["gt_skipped"].sum())
                out[f"collision_{s}_outside_grid"] = int(self.coll[s]["outside"].sum())
        out["protocol"] = PLANNING_PROTOCOL
        return out

    def format_table(self, label: str = "model") -> str:
        """Printable table: L2 in metres, collision in percent, both conventions named."""
        r = self.compute()
        hs = [f"{h:g}s" for h in self.horizons_s]
        lines = [
            f"# Planning: {r['protocol']}",
            f"{'metric':<44}" + "".join(f"{h:>8}" for h in hs) + f"{'avg':>8}",
        ]
        names = ["l2"] + [f"collision_{s}" for s in self.SOURCES if s in self.sources_seen]
        for n in names:
            scale, unit = (1.0, "m") if n == "l2" else (100.0, "%")
            for conv in ("at_horizon", "mean_to_horizon"):
                vals = [r[f"{n}_{conv}@{h}"] * scale for h in hs] + [r[f"{n}_{conv}_avg"] * scale]
                lines.append(
                    f"{label + ' ' + n + ' ' + conv + ' (' + unit + ')':<44}"
                    + "".join(f"{x:>8.2f}" for x in vals)
                )
        return "\n".join(lines)
