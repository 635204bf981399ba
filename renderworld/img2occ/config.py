"""Configuration of the Img2Occ model (paper Section 6.2.1).

Every accuracy knob (grid, image and render sizes, channels, views rendered per step, pruning
threshold, adjacent-frame supervision, loss weights) is a field here, validated on
construction with ``ValueError`` messages that name the field
(docs/conventions.md#errors-and-data-safety).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from renderworld.constants import GridSpec, get_grid
from renderworld.img2occ.mirror import check_mirror_grid

__all__ = ["Img2OccConfig"]


def _positive_int(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{name}: expected a positive int, got {value!r}")


def _size(name: str, value) -> tuple[int, int]:
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        raise ValueError(f"{name}: expected (height, width), got {value!r}")
    for v in value:
        _positive_int(name, v)
    return (int(value[0]), int(value[1]))


#: Loss weights: each must be a finite number >= 0 (0 turns its term off).
_WEIGHTS = (
    "semantic_weight",
    "depth_weight",
    "depth_l1_weight",
    "backproject_weight",
    "adjacent_weight",
    "lift_depth_weight",
    "lift_semantic_weight",
    "fine_semantic_weight",
    "occupancy_3d_weight",
    "semantic_3d_weight",
)


@dataclass
class Img2OccConfig:
    """Img2Occ hyper-parameters.

    Attributes:
        grid: the voxel grid, a :class:`GridSpec` or a name in ``renderworld.constants.GRIDS``
            (default ``"coarse"``, 50x50x4 over the Occ3D range). Resolved to a GridSpec.
        input_size: (H_in, W_in) of the images the encoder sees, pixels; divisible by
            ``feature_stride``.
        render_size: (H_r, W_r) of the rendered / label maps, pixels.
        encoder_channels: channels of the CNN stages at strides 2, 4, 8, 16, ...; stages
            at and below ``feature_stride`` are merged top-down (FPN-like) into the output.
        feature_stride: 4, 8 or 16, stride of the FPN-merged feature map.
        feature_channels: D, channels of the image features lifted into the voxels.
        timm_backbone: optional timm model name used instead of the CNN (needs timm).
        timm_weights: local file with that backbone's state dict (never downloaded); needs
            ``timm_backbone``.
        head_channels: channels of the BEV head (height folded into channels).
        head_blocks: residual 3x3 blocks in the BEV head.
        lift_near: voxels closer than this camera z (metres) are not seen by that camera.
        lift_sparse: sample each camera's features only at the voxels it sees (same values;
            False: every voxel, the reference twin of ``lift_features``).
        scale_range: (s_min, s_max) Gaussian scales as fractions of the smallest voxel edge
            (GaussianFormer's [0.08, 0.32] m at 0.4 m voxels is (0.2, 0.8)).
        init_opacity: opacity of every Gaussian at initialisation (head bias).
        views_per_step: cameras rendered per sample while training (a random subset of the
            C cameras; ``None`` renders all). Evaluation renders all.
        prune_opacity: Gaussians with opacity <= this are not rendered (selection detached).
            1/255 is lossless: the rasterizer skips alpha < 1/255 and alpha <= opacity.
            0 disables pruning.
        adjacent_frames: supervise with the neighbouring keyframes' cameras (``adj_*`` batch
            fields) when present.
        adjacent_views_per_step: adjacent views rendered per sample while training (``None``
            = all).
        semantic_weight: weight of the rendered-semantics cross-entropy.
        depth_weight: weight of the Pearson depth loss.
        depth_l1_weight: weight of an absolute relative-depth L1 term, mean of
            |d_rendered - d_lidar| / d_lidar over LiDAR pixels. Not in the paper (0 = paper):
            Pearson correlation is blind to an affine change of depth, so it cannot tell a
            veil of half-opaque "air" Gaussians in front of a surface from the surface itself;
            this term can (see the overfitting test).
        carve_margin: metres (> 0): a voxel whose centre lies more than this in front of a
            pixel's LiDAR depth is seen through, hence a free target of ``backproject_weight``.
        backproject_weight: weight of the voxel loss (opacity BCE + class CE) against the
            targets back-projected from the 2-D label maps (``renderworld.img2occ.
            backproject``): voxels holding labelled pixels' points are occupied with their
            most frequent class, voxels the depth maps see through (``carve_margin``) are
            free. 0 = off (the paper). Not in the paper; no 3-D label is read.
        backproject_adjacent: also back-project the adjacent keyframes' points of static
            classes (needs ``adjacent_frames`` in the batch).
        backproject_class_balance: p in [0, 1]: the back-projected targets weigh each
            voxel by its class's frequency among them to the power -p; 0 = unweighted.
        adjacent_weight: weight of the adjacent-frame losses relative to the keyframe's.
        mirror_prob: probability that a training batch is replaced by its mirror image
            across the ego x-z plane (images and label maps flipped left-right, poses and
            intrinsics mirrored: ``renderworld.img2occ.mirror``); 0 = off. Needs a grid
            symmetric in y.
        mirror_readout: readout (eval, threshold search, export) averages the opacities and
            class probabilities of the scene and of its mirror image (flipped back): two
            encoder passes per sample. Needs a grid symmetric in y.
        near: rasterizer near plane, metres (camera z).
        far: rasterizer far plane, metres.
        render_backend: the rasterizer backend ("auto", "reference", "torch", "gsplat").
        occupancy_threshold: initial opacity threshold of the readout (``choose_threshold``
            replaces it; it is stored in the model's state).
        prob_eps: epsilon inside the log of the rendered class distribution.
        depth_bins: D > 0 turns on depth-aware lifting: the image branch also predicts a
            categorical depth distribution over D bins and class logits per feature pixel
            (supervised by the LiDAR-projected 2-D depth / semantic maps), and each voxel
            takes a camera's feature weighted by the predicted probability that the
            camera's surface lies inside the voxel (``renderworld.img2occ.depth_lift``).
            0: every voxel along a ray gets the same (mean) feature.
        depth_range: (d_min, d_max) metres of camera z covered by the D equal-width bins.
        lift_depth_weight: weight of the per-pixel depth-bin cross-entropy (needs depth_bins).
        lift_semantic_weight: weight of the per-pixel class cross-entropy (needs depth_bins).
        fine_semantics: add the fine per-pixel semantic head (``renderworld.img2occ.
            fine_semantics``, needs depth_bins): class logits at the encoder's first stage,
            supervised by the 2-D semantic maps, lifted instead of the coarse ones and added
            to the Gaussians' logits through a learned skip. Not in the paper.
        fine_semantic_weight: weight of the fine head's pixel cross-entropy.
        fine_class_balance: p in [0, 1], class balancing of that cross-entropy.
        class_balance: p in [0, 1]: the semantic cross-entropies (rendered and per-pixel)
            weigh each label by its frequency in the batch to the power -p (mean weight 1);
            0 = unweighted (the paper).
        supervision: "2d" (the paper: rendered semantics + depth vs LiDAR-projected 2-D
            labels) or "3d" (an upper reference: voxel losses against Occ3D GT inside the
            camera mask, nothing rendered while training).
        occupancy_3d_weight: weight of the opacity BCE (occupied vs free) of "3d" supervision.
        semantic_3d_weight: weight of the class cross-entropy of occupied voxels ("3d").
    """

    grid: GridSpec | str = "coarse"
    input_size: tuple[int, int] = (256, 704)
    render_size: tuple[int, int] = (225, 400)
    encoder_channels: tuple[int, ...] = (32, 64, 128, 128)
    feature_stride: int = 8
    feature_channels: int = 64
    timm_backbone: str | None = None
    timm_weights: str | None = None
    head_channels: int = 128
    head_blocks: int = 2
    lift_near: float = 0.1
    lift_sparse: bool = True
    scale_range: tuple[float, float] = (0.2, 0.8)
    init_opacity: float = 0.1
    views_per_step: int | None = 3
    prune_opacity: float = 1.0 / 255.0
    adjacent_frames: bool = False
    adjacent_views_per_step: int | None = 3
    semantic_weight: float = 1.0
    depth_weight: float = 1.0
    depth_l1_weight: float = 0.0
    carve_margin: float = 1.6
    backproject_weight: float = 0.0
    backproject_adjacent: bool = False
    backproject_class_balance: float = 0.0
    adjacent_weight: float = 0.5
    mirror_prob: float = 0.0
    mirror_readout: bool = False
    near: float = 0.1
    far: float = 100.0
    render_backend: str = "auto"
    occupancy_threshold: float = 0.5
    prob_eps: float = 1e-6
    depth_bins: int = 0
    depth_range: tuple[float, float] = (1.0, 61.0)
    lift_depth_weight: float = 1.0
    lift_semantic_weight: float = 1.0
    fine_semantics: bool = False
    fine_semantic_weight: float = 1.0
    fine_class_balance: float = 0.5
    class_balance: float = 0.0
    supervision: str = "2d"
    occupancy_3d_weight: float = 1.0
    semantic_3d_weight: float = 1.0

    def __post_init__(self) -> None:
        self._check_network()
        self._check_gaussians_and_rendering()
        self._check_losses_and_options()

    def _check_network(self) -> None:
        """Grid, image sizes, encoder and head."""
        if isinstance(self.grid, str):
            self.grid = get_grid(self.grid)
        if not isinstance(self.grid, GridSpec):
            raise ValueError(f"grid: expected a GridSpec or a grid name, got {self.grid!r}")
        self.input_size = _size("input_size", self.input_size)
        self.render_size = _size("render_size", self.render_size)
        if self.feature_stride not in (4, 8, 16):
            raise ValueError(f"feature_stride: expected 4, 8 or 16, got {self.feature_stride!r}")
        if any(v % self.feature_stride for v in self.input_size):
            raise ValueError(
                f"input_size: expected sizes divisible by feature_stride {self.feature_stride} "
                f"(the stride-2 convs then keep pixel centres aligned), got {self.input_size}"
            )
        need = {4: 2, 8: 3, 16: 4}[self.feature_stride]
        if not isinstance(self.encoder_channels, (tuple, list)) or len(self.encoder_channels) < (
            need
        ):
            raise ValueError(
                f"encoder_channels: expected at least {need} stage widths for feature_stride "
                f"{self.feature_stride}, got {self.encoder_channels!r}"
            )
        self.encoder_channels = tuple(self.encoder_channels)
        for c in self.encoder_channels:
            _positive_int("encoder_channels", c)
        for name in ("feature_channels", "head_channels"):
            _positive_int(name, getattr(self, name))
        if isinstance(self.head_blocks, bool) or not isinstance(self.head_blocks, int):
            raise ValueError(f"head_blocks: expected an int >= 0, got {self.head_blocks!r}")
        if self.head_blocks < 0:
            raise ValueError(f"head_blocks: expected an int >= 0, got {self.head_blocks!r}")
        if self.timm_weights is not None and self.timm_backbone is None:
            raise ValueError("timm_weights: given without timm_backbone (name the timm model)")

    def _check_gaussians_and_rendering(self) -> None:
        """Gaussian parameters, pruning, views per step, clipping planes."""
        lo_hi = tuple(float(v) for v in self.scale_range)
        if len(lo_hi) != 2 or not (0 < lo_hi[0] < lo_hi[1]):
            raise ValueError(f"scale_range: expected 0 < s_min < s_max, got {self.scale_range!r}")
        self.scale_range = lo_hi
        for name in ("init_opacity", "occupancy_threshold"):
            v = getattr(self, name)
            if not (0.0 < float(v) < 1.0):
                raise ValueError(f"{name}: expected a value in (0, 1), got {v!r}")
        if not (0.0 <= float(self.prune_opacity) < 1.0):
            raise ValueError(
                f"prune_opacity: expected a value in [0, 1), got {self.prune_opacity!r}"
            )
        for name in ("views_per_step", "adjacent_views_per_step"):
            v = getattr(self, name)
            if v is not None:
                _positive_int(name, v)
        if not (0 < self.near < self.far):
            raise ValueError(f"near/far: expected 0 < near < far, got {self.near}, {self.far}")
        if not (self.lift_near > 0):
            raise ValueError(f"lift_near: expected > 0 metres, got {self.lift_near!r}")

    def _check_losses_and_options(self) -> None:
        """Loss weights, depth-aware lifting, class balancing, back-projection, mirroring."""
        for name in _WEIGHTS:
            v = getattr(self, name)
            if not (math.isfinite(float(v)) and float(v) >= 0):
                raise ValueError(f"{name}: expected a finite weight >= 0, got {v!r}")
        if not (math.isfinite(float(self.carve_margin)) and float(self.carve_margin) > 0):
            raise ValueError(f"carve_margin: expected > 0 metres, got {self.carve_margin!r}")
        if isinstance(self.depth_bins, bool) or not isinstance(self.depth_bins, int):
            raise ValueError(f"depth_bins: expected an int >= 0, got {self.depth_bins!r}")
        if self.depth_bins < 0 or self.depth_bins == 1:
            raise ValueError(f"depth_bins: expected 0 (off) or >= 2, got {self.depth_bins!r}")
        rng = tuple(float(v) for v in self.depth_range)
        if len(rng) != 2 or not (0 < rng[0] < rng[1]):
            raise ValueError(f"depth_range: expected 0 < d_min < d_max, got {self.depth_range!r}")
        self.depth_range = rng
        for name in ("class_balance", "fine_class_balance", "backproject_class_balance"):
            v = getattr(self, name)
            if not (0.0 <= float(v) <= 1.0):
                raise ValueError(f"{name}: expected a value in [0, 1], got {v!r}")
        if not isinstance(self.fine_semantics, bool):
            raise ValueError(f"fine_semantics: expected a bool, got {self.fine_semantics!r}")
        if self.fine_semantics and not self.depth_bins:
            raise ValueError("fine_semantics: needs depth-aware lifting (depth_bins >= 2)")
        if not isinstance(self.backproject_adjacent, bool):
            raise ValueError(
                f"backproject_adjacent: expected a bool, got {self.backproject_adjacent!r}"
            )
        if not (0.0 <= float(self.mirror_prob) <= 1.0):
            raise ValueError(f"mirror_prob: expected a value in [0, 1], got {self.mirror_prob!r}")
        if not isinstance(self.mirror_readout, bool):
            raise ValueError(f"mirror_readout: expected a bool, got {self.mirror_readout!r}")
        if self.mirror_prob > 0 or self.mirror_readout:
            try:
                check_mirror_grid(self.grid)
            except ValueError as err:
                raise ValueError(f"mirror_prob / mirror_readout: {err}") from None
        if self.supervision not in ("2d", "3d"):
            raise ValueError(f"supervision: expected '2d' or '3d', got {self.supervision!r}")
        if not (0 < self.prob_eps < 1e-2):
            raise ValueError(f"prob_eps: expected a value in (0, 0.01), got {self.prob_eps!r}")

    @property
    def feature_size(self) -> tuple[int, int]:
        """(h, w) of the lifted feature map: input size / feature_stride."""
        h, w = self.input_size
        return (h // self.feature_stride, w // self.feature_stride)
