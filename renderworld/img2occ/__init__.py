"""Img2Occ (paper §6.2.1): semantic Gaussians anchored in voxels, trained from 2-D labels."""

from renderworld.img2occ.config import Img2OccConfig
from renderworld.img2occ.depth_lift import (
    DepthSemanticHead,
    depth_bin_edges,
    image_label_losses,
    occupancy_3d_loss,
)
from renderworld.img2occ.encoder import ImageEncoder
from renderworld.img2occ.export import export_occupancy
from renderworld.img2occ.head import AnchorGaussians, GaussianHead
from renderworld.img2occ.lifting import LiftResult, lift_features
from renderworld.img2occ.losses import (
    IGNORE_LABEL,
    balanced_class_weights,
    pearson_depth_loss,
    relative_depth_l1_loss,
    rendered_distribution,
    semantic_nll_loss,
)
from renderworld.img2occ.model import Img2Occ, Img2OccOutput
from renderworld.img2occ.readout import (
    ThresholdSearch,
    choose_threshold,
    confusion_matrix,
    geometry_iou_from_confusion,
    miou_from_confusion,
    readout_occupancy,
)
from renderworld.img2occ.render import RenderedViews, render_views
from renderworld.img2occ.viz import colorize_semantics, draw_views

__all__ = [
    "IGNORE_LABEL",
    "AnchorGaussians",
    "DepthSemanticHead",
    "GaussianHead",
    "ImageEncoder",
    "Img2Occ",
    "Img2OccConfig",
    "Img2OccOutput",
    "LiftResult",
    "RenderedViews",
    "ThresholdSearch",
    "balanced_class_weights",
    "choose_threshold",
    "colorize_semantics",
    "confusion_matrix",
    "depth_bin_edges",
    "draw_views",
    "export_occupancy",
    "geometry_iou_from_confusion",
    "image_label_losses",
    "miou_from_confusion",
    "lift_features",
    "occupancy_3d_loss",
    "pearson_depth_loss",
    "readout_occupancy",
    "relative_depth_l1_loss",
    "render_views",
    "rendered_distribution",
    "semantic_nll_loss",
]
