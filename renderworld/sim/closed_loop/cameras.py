"""Camera-only observation in closed loop: the six cameras rendered at the ego's actual pose,
turned into occupancy by a trained Img2Occ.

The Camera setting's planner sees no ground-truth occupancy: at every keyframe the simulator
renders the six cameras at the pose the ego actually reached (the fixture's rig; the scene's
weather and night; one exposure time, the keyframe's) directly at Img2Occ's input size, or at a
given size resized bilinearly to it as its training data were (the same occupancy within 0.2 %
of the GT-occupied voxels for twice the time, docs/closed_loop.md); Img2Occ's readout (its
stored thresholds and offsets, no rendering) gives the occupancy frame, down-sampled by the
datasets' rule when the planner's grid is coarser
(:func:`renderworld.data.downsample.downsample_occupancy`). :class:`CameraObserver` has the
:class:`~renderworld.sim.closed_loop.observe.OccupancyRenderer` interface, so a planner with
``observer`` set drives on it.
"""

from __future__ import annotations

import numpy as np
import torch
from PIL import Image

from renderworld.constants import CAMERA_NAMES, GridSpec
from renderworld.data.downsample import downsample_occupancy, grid_factor
from renderworld.geometry.camera import scale_intrinsics
from renderworld.precision import autocast_off, exact_float32
from renderworld.sim.effects import EffectReport
from renderworld.sim.layout import World
from renderworld.sim.render import render_camera
from renderworld.sim.sensors import SensorRig

__all__ = ["CameraObserver"]


class CameraObserver:
    """Occupancy [X, Y, Z] uint8 of a world seen through its cameras at any ego pose.

    Args:
        img2occ: a trained :class:`renderworld.img2occ.Img2Occ` (eval mode; its ``cfg`` gives
            the input size and its grid).
        grid: the planner's grid (the Img2Occ grid, or an integer down-sampling of it).
        image_size: (width, height) of the rendered images (resized to the input size), or
            None: rendered at Img2Occ's input size.
        seed: the seed of the camera effects' noise (rain, sensor noise).

    Raises:
        ValueError: naming ``grid`` when it is not Img2Occ's grid or a down-sampling of it.
    """

    def __init__(
        self, img2occ, grid: GridSpec, image_size: tuple[int, int] | None = None, seed: int = 0
    ):
        self.model = img2occ.eval()
        self.grid = grid
        h_in, w_in = (int(v) for v in img2occ.cfg.input_size)
        w, h = (w_in, h_in) if image_size is None else (int(v) for v in image_size)
        self.rig = SensorRig.build(w, h)
        self.input_size = (h_in, w_in)
        own = tuple(img2occ.cfg.grid.shape)
        try:
            self.factor = grid_factor(own, grid)
        except ValueError as err:
            raise ValueError(
                f"grid: the planner's grid {tuple(grid.shape)} is not Img2Occ's {own} or a "
                f"down-sampling of it ({err})"
            ) from None
        sx, sy = w_in / self.rig.width, h_in / self.rig.height
        k = [scale_intrinsics(self.rig.intrinsics[c], sx, sy) for c in CAMERA_NAMES]
        self._k = torch.from_numpy(np.stack(k).astype(np.float32))[None]
        self._c2e = torch.from_numpy(
            np.stack([self.rig.sensor_to_ego[c] for c in CAMERA_NAMES]).astype(np.float32)
        )[None]
        self._caster = None
        self._world = None
        self._rng = np.random.default_rng(seed)
        self._report = EffectReport()

    def images(self, world: World, t: float, pose: np.ndarray) -> torch.Tensor:
        """[1, 6, 3, H_in, W_in] float32 in [0, 1]: the cameras at time ``t`` (s) from ``pose``
        ([4, 4] ego -> scene), resized to Img2Occ's input size."""
        from renderworld.sim.meshes import Raycaster

        if self._world is not world:  # one ray-casting scene per world (as the simulator's)
            r = world.raster
            ext = (r.x0 - 400, r.y0 - 400, r.x0 + r.shape[0] * r.cell + 400,
                   r.y0 + r.shape[1] * r.cell + 400)  # fmt: skip
            self._caster, self._world = Raycaster(world.objects, ext), world
        h_in, w_in = self.input_size
        out = np.empty((len(CAMERA_NAMES), h_in, w_in, 3), dtype=np.uint8)
        for c, ch in enumerate(CAMERA_NAMES):
            img = render_camera(world, self._caster, self.rig, ch, t, pose, self._rng,
                                self._report)  # fmt: skip
            if img.shape[:2] != (h_in, w_in):
                img = Image.fromarray(img).resize((w_in, h_in), Image.Resampling.BILINEAR)
            out[c] = np.asarray(img)
        return torch.from_numpy(out).permute(0, 3, 1, 2).float().div_(255.0)[None]

    @torch.no_grad()
    def render(self, world: World, t: float, pose: np.ndarray) -> np.ndarray:
        """Img2Occ's occupancy of the cameras at time ``t`` from ``pose``, on the planner's grid."""
        batch = {"images": self.images(world, t, pose), "intrinsics": self._k,
                 "cam_to_ego": self._c2e}  # fmt: skip
        with exact_float32(), autocast_off():
            sem = self.model.readout(self.model(batch, render=False))[0].cpu().numpy()
        if self.factor != (1, 1, 1):
            sem = downsample_occupancy(sem, self.factor)
        return sem.astype(np.uint8)
