"""Road networks and the ground raster (driveable surface, sidewalk, terrain, paint).

Roads are centreline polylines with lanes, kerb-side parking strips and sidewalks. The ground
is flat (z = 0, scene frame); its class at any (x, y) comes from a 2D raster computed once per
scene, which LiDAR, cameras and the Occ3D voxeliser all read, so the three agree.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Road", "Junction", "RoadNetwork", "GroundRaster", "ROAD", "SIDEWALK", "TERRAIN"]

ROAD = 24  # flat.driveable_surface
SIDEWALK = 26  # flat.sidewalk
TERRAIN = 27  # flat.terrain
PAINT_WHITE, PAINT_YELLOW = 1, 2


@dataclass
class Road:
    """A two-way road along a centreline polyline.

    Attributes:
        points: [P, 2] centreline, metres, scene frame; traffic keeps right.
        lanes: lanes per direction.
        lane_width: metres.
        parking: width of the kerb-side parking strip on each side, metres.
        sidewalk: sidewalk width on each side, metres.
    """

    points: np.ndarray
    lanes: int = 2
    lane_width: float = 3.5
    parking: float = 2.5
    sidewalk: float = 3.0

    @property
    def half_width(self) -> float:
        """Kerb-to-centre distance, metres."""
        return self.lanes * self.lane_width + self.parking

    def lane_offset(self, lane: int) -> float:
        """Signed lateral offset (left +) of a lane centre; lane 0 = innermost right-hand lane,
        negative lanes are the opposite direction (-1 innermost)."""
        if lane >= 0:
            return -(lane + 0.5) * self.lane_width
        return (-lane - 0.5) * self.lane_width

    def parking_offset(self, side: int) -> float:
        """Offset of the parking strip centre on ``side`` (+1 left, -1 right)."""
        return side * (self.lanes * self.lane_width + 0.5 * self.parking)


@dataclass
class Junction:
    """A junction of axis-aligned roads at ``centre`` with arms in ``arms`` ('+x', '-x', ...)."""

    centre: tuple[float, float]
    arms: tuple[str, ...]
    half_width_x: float  # half width of the road along x (extent in y)
    half_width_y: float  # half width of the road along y (extent in x)
    kerb_radius: float = 7.0


@dataclass
class RoadNetwork:
    """Roads plus junctions."""

    roads: list[Road]
    junctions: list[Junction] = field(default_factory=list)


class GroundRaster:
    """Class and paint raster of the flat ground, 0.1 m cells, scene frame.

    Args:
        network: the roads.
        bounds: (xmin, ymin, xmax, ymax) metres covered; outside is terrain.
        cell: cell size, metres.
    """

    def __init__(self, network: RoadNetwork, bounds: tuple[float, float, float, float], cell=0.1):
        self.cell = float(cell)
        self.x0, self.y0 = float(bounds[0]), float(bounds[1])
        nx = int(np.ceil((bounds[2] - bounds[0]) / cell))
        ny = int(np.ceil((bounds[3] - bounds[1]) / cell))
        self.shape = (nx, ny)
        self.classes = np.full((nx, ny), TERRAIN, dtype=np.uint8)
        self.paint = np.zeros((nx, ny), dtype=np.uint8)
        self._rasterise(network)

    # ---------------------------------------------------------------- lookups
    def _cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ix = np.floor((xy[..., 0] - self.x0) / self.cell).astype(np.int64)
        iy = np.floor((xy[..., 1] - self.y0) / self.cell).astype(np.int64)
        inside = (ix >= 0) & (ix < self.shape[0]) & (iy >= 0) & (iy < self.shape[1])
        return np.clip(ix, 0, self.shape[0] - 1), np.clip(iy, 0, self.shape[1] - 1), inside

    def classify(self, xy: np.ndarray) -> np.ndarray:
        """lidarseg ground class (uint8) of points [..., 2]; terrain outside the raster."""
        ix, iy, inside = self._cells(np.asarray(xy, dtype=np.float64))
        return np.where(inside, self.classes[ix, iy], TERRAIN).astype(np.uint8)

    def paint_at(self, xy: np.ndarray) -> np.ndarray:
        """Paint code (0 none, 1 white, 2 yellow) of points [..., 2]."""
        ix, iy, inside = self._cells(np.asarray(xy, dtype=np.float64))
        return np.where(inside, self.paint[ix, iy], 0).astype(np.uint8)

    # ---------------------------------------------------------------- building
    def _centres(self, sl: tuple[slice, slice]) -> tuple[np.ndarray, np.ndarray]:
        xs = self.x0 + (np.arange(sl[0].start, sl[0].stop) + 0.5) * self.cell
        ys = self.y0 + (np.arange(sl[1].start, sl[1].stop) + 0.5) * self.cell
        return np.meshgrid(xs.astype(np.float32), ys.astype(np.float32), indexing="ij")

    def _window(self, lo: np.ndarray, hi: np.ndarray) -> tuple[slice, slice] | None:
        i0 = max(int((lo[0] - self.x0) / self.cell), 0)
        j0 = max(int((lo[1] - self.y0) / self.cell), 0)
        i1 = min(int((hi[0] - self.x0) / self.cell) + 1, self.shape[0])
        j1 = min(int((hi[1] - self.y0) / self.cell) + 1, self.shape[1])
        if i1 <= i0 or j1 <= j0:
            return None
        return slice(i0, i1), slice(j0, j1)

    def _road_fields(self, road: Road) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-cell distance to the centreline, signed offset (left +) and arc length."""
        dist = np.full(self.shape, np.inf, dtype=np.float32)
        off = np.zeros(self.shape, dtype=np.float32)
        arc = np.zeros(self.shape, dtype=np.float32)
        reach = road.half_width + road.sidewalk + 0.5
        pts = np.asarray(road.points, dtype=np.float64)
        s0 = 0.0
        for a, b in zip(pts[:-1], pts[1:]):
            seg = b - a
            length = float(np.hypot(*seg))
            sl = self._window(np.minimum(a, b) - reach, np.maximum(a, b) + reach)
            if sl is not None and length > 0:
                px, py = self._centres(sl)
                rx, ry = px - a[0], py - a[1]
                t = np.clip((rx * seg[0] + ry * seg[1]) / length**2, 0.0, 1.0)
                d = np.hypot(rx - t * seg[0], ry - t * seg[1])
                better = d < dist[sl]
                dist[sl] = np.where(better, d, dist[sl])
                off[sl] = np.where(better, (seg[0] * ry - seg[1] * rx) / length, off[sl])
                arc[sl] = np.where(better, s0 + t * length, arc[sl])
            s0 += length
        return dist, off, arc

    def _rasterise(self, network: RoadNetwork) -> None:
        fields = [self._road_fields(r) for r in network.roads]
        on_road = np.zeros(self.shape, dtype=bool)
        on_walk = np.zeros(self.shape, dtype=bool)
        for road, (dist, _, _) in zip(network.roads, fields):
            on_road |= dist <= road.half_width
            on_walk |= dist <= road.half_width + road.sidewalk
        self.classes[on_walk] = SIDEWALK
        self.classes[on_road] = ROAD
        for j in network.junctions:
            self._kerb_fillets(j, network.roads[0].sidewalk)
        # Paint: lane lines per road, not inside the other roads' carriageways.
        for r, (road, (dist, off, arc)) in enumerate(zip(network.roads, fields)):
            others = np.zeros(self.shape, dtype=bool)
            for q, (road_q, (dist_q, _, _)) in enumerate(zip(network.roads, fields)):
                if q != r:
                    others |= dist_q <= road_q.half_width + 0.5
            mine = (dist <= road.half_width) & ~others
            a = np.abs(off)
            dashed = np.mod(arc, 9.0) < 3.0
            lw = road.lane_width
            yellow = mine & (np.abs(a - 0.12) < 0.06)
            white = mine & (np.abs(a - road.lanes * lw) < 0.07)
            for k in range(1, road.lanes):
                white |= mine & dashed & (np.abs(a - k * lw) < 0.07)
            self.paint[white] = PAINT_WHITE
            self.paint[yellow] = PAINT_YELLOW
        for j in network.junctions:
            self._crosswalks(j, network.roads)

    def _kerb_fillets(self, j: Junction, sidewalk: float) -> None:
        rc = j.kerb_radius
        for sx in (-1, 1):
            for sy in (-1, 1):
                if ("+x" if sx > 0 else "-x") not in j.arms or (
                    "+y" if sy > 0 else "-y"
                ) not in j.arms:
                    continue
                cx = j.centre[0] + sx * j.half_width_y
                cy = j.centre[1] + sy * j.half_width_x
                lo = np.array([min(cx, cx + sx * rc), min(cy, cy + sy * rc)])
                sl = self._window(lo, lo + rc)
                if sl is None:
                    continue
                px, py = self._centres(sl)
                u, v = sx * (px - cx), sy * (py - cy)
                rho = np.hypot(u - rc, v - rc)
                sq = (u >= 0) & (v >= 0) & (u < rc) & (v < rc)
                cls = np.where(rho > rc, ROAD, np.where(rho > rc - sidewalk, SIDEWALK, TERRAIN))
                self.classes[sl] = np.where(sq, cls, self.classes[sl]).astype(np.uint8)

    def _crosswalks(self, j: Junction, roads: list[Road]) -> None:
        for arm in j.arms:
            axis = 0 if arm[1] == "x" else 1
            sign = 1.0 if arm[0] == "+" else -1.0
            hw_other = j.half_width_y if axis == 0 else j.half_width_x
            hw_arm = j.half_width_x if axis == 0 else j.half_width_y
            park = roads[0].parking
            near, far = hw_other + 1.0, hw_other + 4.0
            c = np.asarray(j.centre, dtype=np.float64)
            lo, hi = c.copy(), c.copy()
            lo[axis], hi[axis] = c[axis] + sign * near, c[axis] + sign * far
            lo[1 - axis], hi[1 - axis] = c[1 - axis] - hw_arm + park, c[1 - axis] + hw_arm - park
            sl = self._window(np.minimum(lo, hi), np.maximum(lo, hi))
            if sl is None:
                continue
            px, py = self._centres(sl)
            across = (py if axis == 0 else px) - c[1 - axis]
            stripe = np.mod(across, 1.2) < 0.6
            self.paint[sl] = np.where(stripe, PAINT_WHITE, self.paint[sl])
