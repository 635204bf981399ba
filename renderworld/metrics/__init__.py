"""Metrics (pure functions and accumulators, numpy/torch inputs; docs/protocol.md).

Every accumulator states its protocol in ``compute()["protocol"]`` and in ``format_table()``.
"""

from renderworld.metrics.collision import (
    COLLISION_BEV_GRID,
    BevGrid,
    box_cells,
    collisions_with_boxes,
    collisions_with_occupancy,
    rasterize_boxes,
    trajectory_headings,
)
from renderworld.metrics.forecast import (
    FORECAST_HORIZONS_S,
    ForecastMetric,
    horizon_steps,
    movers_miou,
)
from renderworld.metrics.heading import heading_counts, heading_error_deg, heading_from_counts
from renderworld.metrics.occupancy import (
    OCCUPANCY_PROTOCOL,
    OccupancyMetric,
    confusion_counts,
    confusion_matrix,
    geometry_iou,
    iou_per_class,
    mean_iou,
)
from renderworld.metrics.planning import PLANNING_PROTOCOL, PlanningMetric, l2_errors

__all__ = [
    "COLLISION_BEV_GRID",
    "FORECAST_HORIZONS_S",
    "OCCUPANCY_PROTOCOL",
    "PLANNING_PROTOCOL",
    "BevGrid",
    "ForecastMetric",
    "OccupancyMetric",
    "PlanningMetric",
    "box_cells",
    "collisions_with_boxes",
    "collisions_with_occupancy",
    "confusion_counts",
    "confusion_matrix",
    "geometry_iou",
    "heading_counts",
    "heading_error_deg",
    "heading_from_counts",
    "horizon_steps",
    "movers_miou",
    "iou_per_class",
    "l2_errors",
    "mean_iou",
    "rasterize_boxes",
    "trajectory_headings",
]
