"""Model layers of a recording: Img2Occ Gaussians and read-out, tokenizer reconstruction,
world-model forecasts and planned vs GT trajectories.

Entity layout (below ``world``, see ``data_layers.py``)::

    world/ego/img2occ/gaussians         Img2Occ's Gaussians (splats, ellipsoids or points),
                                        class colour, alpha = opacity
    world/ego/img2occ/occupancy         its read-out occupancy (occupied voxels as boxes)
    world/ego/tokenizer/reconstruction  decode(encode(GT occupancy)) on the tokenizer's grid
    world/ego/plan/planned              planned trajectory t+0.5 ... t+3 s (line + waypoints)
    world/ego/plan/gt                   the GT future ego positions
    world/ego/movers                    each road user's forecast path over 3 s (pose-warp
                                        models: the movers the forecast and the checked plan move)
    world/forecast/<s>s                 forecast occupancy at t + s seconds, placed at the
                                        planned pose of that frame (heading from the trajectory)

Model layers read the converter's infos (``tools/create_data.py``) for their inputs; each
layer is a small class built once per scene whose ``log(rec, rr, frames, i)`` writes keyframe
``i`` and returns ``{entity: instances}`` (empty when the keyframe has no input, e.g. the first
frames of a scene lack the world model's history).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import torch

from renderworld.constants import COMMANDS, FUTURE_FRAMES
from renderworld.data import load_infos
from renderworld.metrics.collision import trajectory_headings
from renderworld.viewer._rerun import transform
from renderworld.viewer.blueprint import forecast_entity
from renderworld.viewer.data_layers import log_voxels
from renderworld.viewer.scene import SceneFrames
from renderworld.viewer.voxels import gaussian_arrays, grid_for_shape

__all__ = [
    "GAUSSIAN_MODES",
    "scene_infos",
    "Img2OccLayer",
    "TokenizerLayer",
    "ForecastLayer",
    "forecast_entity",
]

#: How Gaussians are drawn: Rerun's Gaussian splats, 1-sigma ellipsoids, or points.
GAUSSIAN_MODES = ("splats", "ellipsoids", "points")


def scene_infos(infos_dir, scene: str) -> pd.DataFrame:
    """The infos rows of ``scene`` from every ``infos_<split>.parquet`` in ``infos_dir``.

    Raises:
        ValueError: no infos file in the folder, or no row of that scene.
    """
    files = sorted(Path(infos_dir).glob("infos_*.parquet"))
    if not files:
        raise ValueError(f"infos_dir: no infos_<split>.parquet in {infos_dir}")
    parts = [load_infos(f) for f in files]
    rows = [p[p["scene_name"] == scene] for p in parts]
    df = pd.concat([r for r in rows if len(r)] or [parts[0].iloc[:0]], ignore_index=True)
    if len(df) == 0:
        raise ValueError(f"scene: {scene!r} has no keyframe in the infos of {infos_dir}")
    df.attrs = dict(parts[0].attrs)  # infos_dir: base of the out-relative 2-D label paths
    return df


def _batch(item: dict, device) -> dict:
    return {k: v[None].to(device) for k, v in item.items() if isinstance(v, torch.Tensor)}


class Img2OccLayer:
    """Img2Occ's Gaussians and read-out occupancy per keyframe.

    Args:
        model: an ``Img2Occ`` (eval mode; its config gives input size and grid).
        infos: the scene's infos rows (:func:`scene_infos`).
        data_root: the dataset folder.
        gaussians: one of :data:`GAUSSIAN_MODES`.
        min_opacity: Gaussians fainter than this are not drawn (every voxel has one).
        device: where the model runs.
        surface_only: draw only the read-out voxels a viewer can see (``occupancy_boxes``).
    """

    def __init__(
        self,
        model,
        infos,
        data_root,
        gaussians="splats",
        min_opacity=0.05,
        device="cpu",
        surface_only=True,
    ):
        from renderworld.data import Img2OccDataset

        if gaussians not in GAUSSIAN_MODES:
            raise ValueError(f"gaussians: expected one of {GAUSSIAN_MODES}, got {gaussians!r}")
        self.model, self.mode, self.min_opacity = model, gaussians, float(min_opacity)
        self.surface_only = surface_only
        self.device = torch.device(device)
        cfg = model.cfg
        self.data = Img2OccDataset(
            infos, data_root, input_size=cfg.input_size, grid=cfg.grid, load_occ=False
        )
        self.rows = {t: r for r, t in enumerate(self.data.text["sample_token"])}

    def log(self, rec, rr, frames: SceneFrames, i: int) -> dict[str, int]:
        row = self.rows.get(frames.sample_tokens[i])
        if row is None:
            return {}
        with torch.inference_mode():
            out = self.model(_batch(self.data[row], self.device), render=False)
            occ = self.model.readout(out)[0].cpu().numpy()
        g = out.gaussians
        arr = gaussian_arrays(
            g.means[0], g.quats[0], g.scales[0], g.opacities[0], g.logits[0], self.min_opacity
        )
        entity = "world/ego/img2occ/gaussians"
        if self.mode == "splats":
            rec.log(
                entity,
                rr.GaussianSplats3D(
                    arr["centres"], scales=arr["scales"], quaternions=arr["quats_xyzw"],
                    colors=arr["rgba"],
                ),
            )  # fmt: skip
        elif self.mode == "ellipsoids":
            rec.log(
                entity,
                rr.Ellipsoids3D(
                    centers=arr["centres"], half_sizes=arr["scales"],
                    quaternions=arr["quats_xyzw"], colors=arr["rgba"],
                    fill_mode=rr.components.FillMode.Solid,
                ),
            )  # fmt: skip
        else:
            rec.log(
                entity,
                rr.Points3D(arr["centres"], colors=arr["rgba"], radii=arr["scales"].mean(axis=1)),
            )
        n_occ = log_voxels(
            rec, rr, "world/ego/img2occ/occupancy", occ, self.model.cfg.grid,
            surface_only=self.surface_only,
        )  # fmt: skip
        return {entity: len(arr["centres"]), "world/ego/img2occ/occupancy": n_occ}


class TokenizerLayer:
    """The tokenizer's reconstruction ``decode(encode(occ))`` of the GT occupancy (or of the
    labels under ``occ_root``) on the tokenizer's grid, per keyframe."""

    def __init__(self, tokenizer, infos, data_root, occ_root=None, device="cpu", surface_only=True):
        from renderworld.data import OccSequenceDataset

        self.tokenizer, self.device = tokenizer, torch.device(device)
        self.surface_only = surface_only
        self.grid = grid_for_shape(tokenizer.cfg.grid_shape)
        self.data = OccSequenceDataset(
            infos, data_root, history=1, future=0, grid=self.grid, occ_root=occ_root
        )
        tokens = self.data.text["sample_token"]
        self.rows = {tokens[int(s)]: w for w, s in enumerate(self.data.starts)}

    def log(self, rec, rr, frames: SceneFrames, i: int) -> dict[str, int]:
        w = self.rows.get(frames.sample_tokens[i])
        if w is None:
            return {}
        occ = self.data[w]["occ"].to(self.device)
        with torch.inference_mode():
            rec_occ = self.tokenizer.decode(self.tokenizer.encode(occ))[0].cpu().numpy()
        rec_occ = rec_occ.astype(np.uint8)
        entity = "world/ego/tokenizer/reconstruction"
        n = log_voxels(rec, rr, entity, rec_occ, self.grid, None, self.surface_only)
        return {entity: n}


class ForecastLayer:
    """World-model forecasts and planned vs GT trajectories from a ``Planner``.

    At every keyframe t with ``history_frames`` keyframes of history the planner gets the GT
    occupancy history (or ``occ_root``'s labels) on the tokenizer's grid, the ego displacements
    and the current command (the converter's, from that keyframe only; the rollout holds it);
    its forecasts of t+1..t+S and its trajectory are logged at t.
    """

    def __init__(
        self, planner, infos, data_root, occ_root=None, steps: int | None = None, surface_only=True
    ):
        from renderworld.data import OccSequenceDataset

        self.planner, self.surface_only = planner, surface_only
        h = planner.config.history_frames
        s = planner.config.future_frames
        if steps is not None and (isinstance(steps, bool) or not 0 <= int(steps) <= s):
            raise ValueError(f"steps: expected an integer in 0..{s} or None, got {steps!r}")
        self.steps = s if steps is None else int(steps)
        self.grid = grid_for_shape(planner.tokenizer.cfg.grid_shape)
        self.data = OccSequenceDataset(
            infos, data_root, history=h, future=0, grid=self.grid, occ_root=occ_root
        )
        tokens = self.data.text["sample_token"]
        self.rows = {tokens[int(st) + h - 1]: w for w, st in enumerate(self.data.starts)}
        self.future = {
            t: (np.asarray(f, np.float64).reshape(-1, 2), np.asarray(m, bool))
            for t, f, m in zip(
                infos["sample_token"], infos["ego_future"], infos["ego_future_mask"], strict=True
            )
        }

    def log(self, rec, rr, frames: SceneFrames, i: int) -> dict[str, int]:
        from renderworld.planning import PlanRequest

        token = frames.sample_tokens[i]
        w = self.rows.get(token)
        if w is None:
            return {}
        item = self.data[w]
        request = PlanRequest(
            item["occ"].numpy(), item["ego_displacements"].numpy(), COMMANDS[int(item["command"])],
            ego_yaws=item["history_poses"][:, 2].numpy(),  # read by pose-aware models only
        )  # fmt: skip
        result = self.planner.plan(request)
        traj = np.asarray(result.trajectory, dtype=np.float64)
        counts = {"world/ego/plan/planned": len(traj)}
        line = np.vstack([np.zeros((1, 2)), traj])
        self._log_path(rec, rr, "world/ego/plan/planned", line, (255, 64, 64), "planned")
        fut, mask = self.future.get(token, (np.zeros((0, 2)), np.zeros(0, bool)))
        n = int(np.cumprod(mask[:FUTURE_FRAMES]).sum())  # GT positions up to the first gap
        gt = np.vstack([np.zeros((1, 2)), fut[:n]])
        self._log_path(rec, rr, "world/ego/plan/gt", gt, (64, 220, 64), "GT")
        counts["world/ego/plan/gt"] = n
        if self.planner.kind == "pose_warp":
            counts["world/ego/movers"] = self._log_movers(rec, rr, item)
        # Each forecast frame in its own predicted ego frame: the model's headings, or (token
        # models) the direction of travel.
        headings = trajectory_headings(traj) if result.yaws is None else result.yaws
        for k in range(self.steps):
            ego_from_pred = np.eye(4)
            c, s = np.cos(headings[k]), np.sin(headings[k])
            ego_from_pred[:2, :2] = [[c, -s], [s, c]]
            ego_from_pred[:2, 3] = traj[k]
            entity = forecast_entity(k + 1)
            rec.log(entity, transform(rr, frames.ego_to_world[i] @ ego_from_pred))
            counts[entity] = log_voxels(
                rec, rr, entity, result.occupancy_forecast[k], self.grid, None, self.surface_only
            )
        return counts

    def _log_movers(self, rec, rr, item) -> int:
        """The forecast movers' paths (centroid, then its forecast displacement at every
        step) at 1 m above the road, in the current ego frame; returns how many."""
        from renderworld.constants import OCC3D_CLASSES
        from renderworld.planning.scene import forecast_scene, model_forecaster

        wm = self.planner.world_model
        scene = forecast_scene(
            item["occ"].numpy(), item["history_poses"].double().numpy(), self.grid,
            wm.config.future_frames, movers=model_forecaster(wm),
        )  # fmt: skip
        moving = [i for i, tr in enumerate(scene.tracks) if np.abs(scene.displacements[i]).max()]
        strips = [
            np.column_stack([scene.tracks[i].centroid + scene.displacements[i],
                             np.full(len(scene.displacements[i]), 1.0)]).astype(np.float32)
            for i in moving
        ]  # fmt: skip
        labels = [OCC3D_CLASSES[scene.tracks[i].cls] for i in moving]
        rec.log("world/ego/movers", rr.LineStrips3D(strips, colors=[(255, 160, 0)],
                                                     labels=labels, radii=[0.12]))  # fmt: skip
        return len(strips)

    @staticmethod
    def _log_path(rec, rr, entity: str, xy: np.ndarray, colour, label: str) -> None:
        pts = np.column_stack([xy, np.full(len(xy), 0.2)]).astype(np.float32)  # just above road
        rec.log(entity, rr.LineStrips3D([pts], colors=[colour], labels=[label], radii=[0.15]))
