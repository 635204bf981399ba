"""The Img2Occ model: images → voxel-anchored semantic Gaussians → rendered views → losses.

``forward(batch)`` encodes the C images, lifts their features into the voxel grid, predicts
one Gaussian per voxel and (unless ``render=False``) renders class probabilities and depth
into the cameras (a random subset of them while training). ``loss(batch, output)`` compares
those renders with the LiDAR-projected 2-D labels; ``readout(output)`` gives the 3-D
occupancy with the threshold stored in the model's state (``occupancy_threshold`` buffer).
Batches follow the ``Img2OccDataset`` item format (docs/formats.md#dataset-items), stacked on B.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import nn

from renderworld.constants import NUM_SEMANTIC_CLASSES
from renderworld.geometry import VoxelGrid, scale_intrinsics
from renderworld.img2occ.backproject import backprojected_loss
from renderworld.img2occ.config import Img2OccConfig
from renderworld.img2occ.depth_lift import (
    DepthSemanticHead,
    depth_bin_edges,
    depth_cdf,
    image_label_losses,
    occupancy_3d_loss,
)
from renderworld.img2occ.encoder import ImageEncoder
from renderworld.img2occ.fine_semantics import FineSemanticHead, pixel_class_loss
from renderworld.img2occ.head import AnchorGaussians, GaussianHead
from renderworld.img2occ.lifting import lift_features
from renderworld.img2occ.losses import (
    balanced_class_weights,
    pearson_depth_loss,
    relative_depth_l1_loss,
    semantic_nll_loss,
)
from renderworld.img2occ.mirror import average_with_mirror, mirror_batch
from renderworld.img2occ.output import Img2OccOutput, _gather_views
from renderworld.img2occ.readout import readout_occupancy
from renderworld.img2occ.render import RenderedViews, render_views
from renderworld.precision import autocast_off, caller_autocast, float32_boundary, to_float32

__all__ = ["Img2Occ", "Img2OccOutput"]

_KEY_INPUTS = ("images", "intrinsics", "cam_to_ego")
_KEY_TARGETS = ("render_intrinsics", "depth", "semantics")


class Img2Occ(nn.Module):
    """Semantic Gaussians anchored in voxels, supervised by rendered 2-D labels.

    Args:
        cfg: :class:`Img2OccConfig` (default config when None).
        render_fn: rasterizer with ``renderworld.splat.rasterize``'s signature; default that
            function, imported on first use.
    """

    #: State keys older checkpoints may lack (the load pre-hook fills in their defaults).
    optional_state_keys = ("class_thresholds", "class_offsets")

    def __init__(self, cfg: Img2OccConfig | None = None, render_fn: Callable | None = None):
        super().__init__()
        self.cfg = cfg if cfg is not None else Img2OccConfig()
        self.render_fn = render_fn
        self.encoder = ImageEncoder(self.cfg)
        self.head = GaussianHead(self.cfg)
        self.depth_head = None
        if self.cfg.depth_bins:
            self.depth_head = DepthSemanticHead(self.cfg.feature_channels, self.cfg.depth_bins)
            edges = depth_bin_edges(self.cfg.depth_bins, self.cfg.depth_range).float()
            self.register_buffer("depth_edges", edges, persistent=False)
        self.fine_head = None
        if self.cfg.fine_semantics:
            self.fine_head = FineSemanticHead(self.encoder.fine_channels, self.cfg.feature_channels)
            # Weight of the lifted fine class distribution added to the Gaussians' logits.
            self.semantic_skip = nn.Parameter(torch.tensor(1.0))
        self.grid = grid = VoxelGrid(self.cfg.grid)
        centres = torch.as_tensor(grid.centres(), dtype=torch.float32).view(-1, 3)
        self.register_buffer("centres", centres, persistent=False)
        lo = torch.as_tensor(grid.range_min, dtype=torch.float32)
        hi = torch.as_tensor(grid.range_max, dtype=torch.float32)
        self.register_buffer("position", 2 * (centres - lo) / (hi - lo) - 1, persistent=False)
        # The readout threshold is state: choose_threshold sets it, checkpoints carry it.
        self.register_buffer(
            "occupancy_threshold", torch.tensor(float(self.cfg.occupancy_threshold))
        )
        # Optional per-class thresholds (negative = unset: the single one applies).
        self.register_buffer("class_thresholds", torch.full((NUM_SEMANTIC_CLASSES,), -1.0))
        # Per-class logit offsets of the readout's argmax (0 = plain argmax; calibration).
        self.register_buffer("class_offsets", torch.zeros(NUM_SEMANTIC_CLASSES))
        self._register_load_state_dict_pre_hook(_default_class_thresholds)

    # ------------------------------------------------------------------ inputs
    def _check_batch(self, batch: dict, keys) -> None:
        if not isinstance(batch, dict):
            raise TypeError(f"batch: expected a dict of tensors, got {type(batch).__name__}")
        missing = [k for k in keys if k not in batch]
        if missing:
            raise ValueError(f"batch: missing key(s) {missing}; got {sorted(batch)}")

    def encode(self, batch: dict) -> tuple:
        """Images → ``(gaussians, count, image_logits, fine_logits)``: the Gaussians,
        per-voxel camera visibility counts [B, V], the per-pixel depth/class logits
        [B, C, D + K, h, w] of depth-aware lifting and the fine class logits
        [B, C, K, h_f, w_f] of ``fine_semantics`` (each None when off). The networks run under
        the caller's autocast, the rest in float32 (:mod:`renderworld.precision`)."""
        self._check_batch(batch, _KEY_INPUTS)
        images = batch["images"]
        h_in, w_in = self.cfg.input_size
        if images.ndim != 5 or images.shape[2:] != (3, h_in, w_in):
            raise ValueError(
                f"images: expected [B, C, 3, {h_in}, {w_in}] (cfg.input_size), "
                f"got {tuple(images.shape)}"
            )
        nets = caller_autocast(images.device.type)
        with autocast_off():
            return self._encode(batch, images, nets)

    def _encode(self, batch: dict, images: torch.Tensor, nets: torch.autocast) -> tuple:
        b, c = images.shape[:2]
        fine_logits = None
        with nets:
            if self.fine_head is not None:
                feats, fine = self.encoder(images.flatten(0, 1), return_fine=True)
                fine_logits = self.fine_head(fine, feats)
                fine_logits = fine_logits.view(b, c, *fine_logits.shape[1:])
            else:
                feats = self.encoder(images.flatten(0, 1))
            image_logits = None
            if self.depth_head is not None:
                image_logits = self.depth_head(feats)
                image_logits = image_logits.view(b, c, *image_logits.shape[1:])
        # Lifted into voxels at projected (float32) positions; depth-bin softmax / cumsum and
        # the pixel cross-entropies of these logits need float32 as well.
        feats, fine_logits = to_float32(feats), to_float32(fine_logits)
        image_logits = to_float32(image_logits)
        feats = feats.view(b, c, *feats.shape[1:])
        stride = self.cfg.feature_stride
        k_feat = scale_intrinsics(batch["intrinsics"].to(feats.dtype), 1.0 / stride)
        extra = {}
        if self.depth_head is not None:
            d = self.cfg.depth_bins
            extra = {
                "depth_cdf": depth_cdf(image_logits[:, :, :d].flatten(0, 1)).view(
                    b, c, d + 1, *image_logits.shape[-2:]
                ),
                "class_probs": torch.softmax(
                    image_logits[:, :, d:] if fine_logits is None else fine_logits, dim=2
                ),
                "edges": self.depth_edges,
                "radius": 0.5 * float(sum(self.cfg.grid.voxel_size)) / 3.0,
            }
        lift = lift_features(
            feats, batch["cam_to_ego"], k_feat, self.centres, self.cfg.lift_near,
            sparse=self.cfg.lift_sparse, **extra,
        )  # fmt: skip
        seen = (lift.count > 0).to(feats.dtype)
        enc = torch.cat(
            [
                seen[:, None],
                torch.log1p(lift.depth)[:, None] / math.log1p(self.cfg.far),
                lift.view_dir.transpose(1, 2),
                self.position.T[None].expand(b, -1, -1).to(feats.dtype),
            ],
            dim=1,
        )
        parts = [lift.features, enc] + ([lift.extras] if lift.extras is not None else [])
        vox = torch.cat(parts, dim=1).view(b, -1, *self.cfg.grid.shape)
        with nets:
            g = self.head(vox, self.centres)
        if self.fine_head is not None:
            # Skip: log of the lifted (mass-weighted, renormalised) class distribution; voxels
            # no camera's surface reaches get a constant, which leaves their argmax alone.
            p = lift.extras[:, 2:].transpose(1, 2)  # [B, V, K]
            p = p / p.sum(-1, keepdim=True).clamp_min(1e-6)
            g.logits = g.logits + self.semantic_skip * torch.log(p + 1e-3)
        return g, lift.count, image_logits, fine_logits

    def _pick(self, b: int, c: int, k: int | None, device) -> torch.Tensor:
        if not self.training or k is None or k >= c:
            return torch.arange(c, device=device).expand(b, c)
        return torch.stack([torch.randperm(c)[:k].sort().values for _ in range(b)]).to(device)

    def _render(self, g: AnchorGaussians, cam_to_ego, intrinsics) -> RenderedViews:
        h, w = self.cfg.render_size
        with autocast_off():  # poses and rendering in float32 (see renderworld.splat)
            return render_views(
                g, cam_to_ego, intrinsics, width=w, height=h,
                render_fn=self.render_fn, prune_opacity=self.cfg.prune_opacity,
                near=self.cfg.near, far=self.cfg.far, backend=self.cfg.render_backend,
            )  # fmt: skip

    @float32_boundary
    def augment(self, batch: dict) -> dict:
        """Training: the batch's mirror image with probability ``cfg.mirror_prob``, else it."""
        p = self.cfg.mirror_prob
        if self.training and p > 0 and float(torch.rand(())) < p:
            return mirror_batch(batch)
        return batch

    # ------------------------------------------------------------------ forward
    def forward(self, batch: dict, render: bool | None = None) -> Img2OccOutput:
        """Predict Gaussians and (optionally) render them into the cameras.

        Args:
            batch: Img2OccDataset items stacked on B: images [B, C, 3, H_in, W_in],
                intrinsics [B, C, 3, 3], cam_to_ego [B, C, 4, 4], render_intrinsics
                [B, C, 3, 3] (needed to render), ``adj_*`` for adjacent-frame views.
            render: render into cameras (training); False for readout/export only; None:
                render unless training with ``supervision = "3d"`` (voxel losses only).

        Returns:
            :class:`Img2OccOutput`.
        """
        g, count, image_logits, fine_logits = self.encode(batch)
        b = count.shape[0]
        out = Img2OccOutput(g, count.view(b, *self.cfg.grid.shape), self.cfg.grid.shape)
        out.image_logits = image_logits
        out.fine_logits = fine_logits
        if render is None:
            render = not (self.training and self.cfg.supervision == "3d")
        if not render:
            if self.cfg.mirror_readout and not self.training:
                mirrored = self.encode(mirror_batch(batch))[0]
                average_with_mirror(out.gaussians, mirrored, self.cfg.grid.shape)
            return out
        g, device = out.gaussians, count.device
        self._check_batch(batch, ("render_intrinsics",))
        c = batch["cam_to_ego"].shape[1]
        idx = self._pick(b, c, self.cfg.views_per_step, device)
        out.view_index = idx
        out.views = self._render(
            g,
            _gather_views(batch["cam_to_ego"], idx),
            _gather_views(batch["render_intrinsics"], idx),
        )
        if self.cfg.adjacent_frames and "adj_cam_to_ego" in batch:
            ca = batch["adj_cam_to_ego"].shape[1]
            if ca > 0:
                aidx = self._pick(b, ca, self.cfg.adjacent_views_per_step, device)
                out.adj_index = aidx
                out.adj_views = self._render(
                    g,
                    _gather_views(batch["adj_cam_to_ego"], aidx),
                    _gather_views(batch["adj_render_intrinsics"], aidx),
                )
        return out

    # ------------------------------------------------------------------ losses
    def _view_losses(self, views: RenderedViews, depth, semantics, weights=None) -> tuple:
        h, w = self.cfg.render_size
        if depth.shape[-2:] != (h, w) or semantics.shape[-2:] != (h, w):
            raise ValueError(
                f"depth/semantics: expected maps of cfg.render_size {(h, w)}, got "
                f"{tuple(depth.shape)} and {tuple(semantics.shape)}"
            )
        sem = semantic_nll_loss(
            views.features.flatten(0, 1),
            views.alpha.flatten(0, 1),
            semantics.flatten(0, 1).to(views.alpha.device),
            eps=self.cfg.prob_eps,
            class_weights=weights,
        )
        rendered, target = views.depth.flatten(0, 1), depth.flatten(0, 1).to(views.depth)
        dep = pearson_depth_loss(rendered, target)
        l1 = relative_depth_l1_loss(rendered, target)
        # One weighted sum per view set: semantics, Pearson depth and depth L1 terms.
        total = (
            self.cfg.semantic_weight * sem
            + self.cfg.depth_weight * dep
            + self.cfg.depth_l1_weight * l1
        )
        return total, sem, dep, l1

    @float32_boundary
    def loss(self, batch: dict, output: Img2OccOutput) -> tuple[torch.Tensor, dict[str, float]]:
        """The training loss of ``cfg.supervision``, plus the depth-aware lifting's 2-D losses.

        "2d" (the paper): rendered-semantics NLL + Pearson depth loss (Eq. 6.7) (+ the
        optional relative-depth L1), plus adjacent frames. "3d" (upper reference): opacity
        BCE + class CE of occupied voxels against Occ3D GT inside the camera mask. With
        ``depth_bins`` both add the per-pixel depth-bin and class cross-entropies against
        the 2-D LiDAR labels.

        Args:
            batch: as for ``forward``, with depth [B, C, H_r, W_r] (metres, 0 = no point)
                and semantics [B, C, H_r, W_r] (int64, 255 = no label); ``adj_depth`` and
                ``adj_semantics`` for adjacent views; "3d": occ [B, X, Y, Z] and
                mask_camera [B, X, Y, Z].
            output: ``forward(batch)``'s result (rendered for "2d").

        Returns:
            ``(total, logs)``: scalar loss with a graph and a dict of detached 0-d tensors
            (no host sync per step; the trainer averages them on the device).
        """
        self._check_batch(batch, _KEY_TARGETS)
        cfg = self.cfg
        weights = None
        if cfg.class_balance > 0:
            weights = balanced_class_weights(batch["semantics"], cfg.class_balance)
        if cfg.supervision == "3d":
            self._check_batch(batch, ("occ", "mask_camera"))
            g = output.gaussians
            bce, ce = occupancy_3d_loss(
                g.opacities, g.logits, batch["occ"], batch["mask_camera"], cfg.prob_eps
            )
            total = cfg.occupancy_3d_weight * bce + cfg.semantic_3d_weight * ce
            logs = {"loss_occ3d": bce.detach(), "loss_sem3d": ce.detach()}
        else:
            total, logs = self._loss_2d(batch, output, weights)
        if output.image_logits is not None:
            k_feat = scale_intrinsics(
                batch["intrinsics"].to(output.image_logits.dtype), 1.0 / cfg.feature_stride
            )
            dce, sce = image_label_losses(
                output.image_logits,
                k_feat,
                batch["render_intrinsics"],
                batch["depth"],
                batch["semantics"],
                self.depth_edges,
                weights,
            )
            total = total + cfg.lift_depth_weight * dce + cfg.lift_semantic_weight * sce
            logs.update(loss_pixel_depth=dce.detach(), loss_pixel_sem=sce.detach())
        if output.fine_logits is not None:
            fs = self.encoder.fine_stride
            fce = pixel_class_loss(
                output.fine_logits,
                scale_intrinsics(batch["intrinsics"].to(output.fine_logits.dtype), 1.0 / fs),
                batch["render_intrinsics"],
                batch["semantics"],
                cfg.fine_class_balance,
            )
            total = total + cfg.fine_semantic_weight * fce
            logs["loss_fine_sem"] = fce.detach()
        logs["loss"] = total.detach()
        logs["mean_opacity"] = output.gaussians.opacities.detach().mean()
        return total, logs

    def _loss_2d(self, batch: dict, output: Img2OccOutput, weights) -> tuple[torch.Tensor, dict]:
        if output.views is None:
            raise ValueError("output: has no rendered views; call forward(batch, render=True)")
        cfg = self.cfg
        idx = output.view_index
        total, sem, dep, l1 = self._view_losses(
            output.views,
            _gather_views(batch["depth"], idx),
            _gather_views(batch["semantics"], idx),
            weights,
        )
        logs = {
            "loss_sem": sem.detach(),
            "loss_depth": dep.detach(),
            "loss_depth_l1": l1.detach(),
        }
        g = output.gaussians
        if cfg.backproject_weight > 0:
            bce, ce, _ = backprojected_loss(
                g.opacities, g.logits, self.centres, self.grid, batch, cfg.carve_margin,
                cfg.near, cfg.backproject_adjacent, cfg.prob_eps, cfg.backproject_class_balance,
            )  # fmt: skip
            total = total + cfg.backproject_weight * (bce + ce)
            logs.update(loss_bp_occ=bce.detach(), loss_bp_sem=ce.detach())
        if output.adj_views is not None:
            self._check_batch(batch, ("adj_depth", "adj_semantics"))
            a_total, a_sem, a_dep, _ = self._view_losses(
                output.adj_views,
                _gather_views(batch["adj_depth"], output.adj_index),
                _gather_views(batch["adj_semantics"], output.adj_index),
                weights,
            )
            total = total + cfg.adjacent_weight * a_total
            logs.update(loss_adj_sem=a_sem.detach(), loss_adj_depth=a_dep.detach())
        logs["gaussians_rendered"] = output.views.num_rendered.float().mean()
        return total, logs

    # ------------------------------------------------------------------ readout
    def set_threshold(self, threshold: float) -> None:
        """Store the readout opacity threshold in the model's state (goes into checkpoints)."""
        if not (0.0 <= float(threshold) < 1.0):
            raise ValueError(f"threshold: expected a value in [0, 1), got {threshold!r}")
        self.occupancy_threshold.fill_(float(threshold))

    def set_class_thresholds(self, thresholds) -> None:
        """Store per-class readout thresholds ([K] values in [0, 1)) in the model's state."""
        t = torch.as_tensor(thresholds, dtype=torch.float32).reshape(-1)
        if t.numel() != NUM_SEMANTIC_CLASSES or not bool(((t >= 0) & (t < 1)).all()):
            raise ValueError(
                f"thresholds: expected {NUM_SEMANTIC_CLASSES} values in [0, 1), got {t.tolist()}"
            )
        self.class_thresholds.copy_(t)

    def set_class_offsets(self, offsets) -> None:
        """Store per-class logit offsets ([K] finite values) of the readout's argmax."""
        o = torch.as_tensor(offsets, dtype=torch.float32).reshape(-1)
        if o.numel() != NUM_SEMANTIC_CLASSES or not bool(torch.isfinite(o).all()):
            raise ValueError(f"offsets: expected {NUM_SEMANTIC_CLASSES} finite values, got {o}")
        self.class_offsets.copy_(o)

    def readout(self, output: Img2OccOutput) -> torch.Tensor:
        """3-D semantic occupancy [B, X, Y, Z] uint8 (``FREE_ID`` = free), ego frame: the
        per-class thresholds when set, else the single one; the class is the argmax of the
        logits plus the stored per-class offsets (0 unless calibrated)."""
        g = output.gaussians
        t = self.class_thresholds
        threshold = t if bool((t >= 0).all()) else float(self.occupancy_threshold)
        return readout_occupancy(
            g.opacities, g.logits, threshold, output.grid_shape, self.class_offsets
        )


def _default_class_thresholds(state_dict, prefix, *args, **kwargs) -> None:
    # Checkpoints written before per-class thresholds existed: unset (-1), single threshold;
    # before class offsets existed: 0 (plain argmax).
    state_dict.setdefault(prefix + "class_thresholds", torch.full((NUM_SEMANTIC_CLASSES,), -1.0))
    state_dict.setdefault(prefix + "class_offsets", torch.zeros(NUM_SEMANTIC_CLASSES))
