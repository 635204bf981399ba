"""The ``world_model`` stage: train the temporal world model on a frozen tokenizer's tokens.

Data: windows of ``history + future`` keyframes (``OccSequenceDataset``) from the dataset's
Occ3D gts (``stage.occ_root: null``, the "3D-Occ" setting) or exported Img2Occ pseudo labels
(``stage.occ_root``, the "Camera" setting). Every frame is encoded by the frozen tokenizer of
``stage.tokenizer_ckpt`` (no grad, 32-bit), and its codes are cached in memory by data root and
sample token, so each keyframe is encoded once per run. The tokenizer lives on the stage, never
in the trained module: checkpoints hold the world model only.

Forecaster (``stage.forecaster``): ``tokens`` (below: the autoregressive token model) or
``pose_warp`` (predicted future poses carry the current frame, tokens fill newly revealed space;
:mod:`renderworld.training.stages.world_model.pose_warp`, docs/world_model.md). Evaluating a
checkpoint uses its own forecaster.

Loss (paper Eq. 6.20, ``tokens``): token cross-entropy + ``lambda_l2`` x L2 of the trajectory
accumulated from the last history frame (``cumulative_from = history - 1``, as a rollout plans).

Evaluation (``val/``): for each window, roll out ``future`` frames from the history tokens,
the history displacements and the **current** command (derived from the GT future; the row
"model, command from history" gives the model the command derived from the history instead:
every figure of the model, heading included, in both forms); decode the forecast; forecast
mIoU/IoU per step (full volume, OccWorld protocol; and inside the camera mask, ``cam/``),
planning L2 (both conventions) and collision rates vs GT boxes and GT object occupancy, and the
same for the baselines Copy&Paste, constant-velocity warp and constant-velocity trajectory (see
:mod:`renderworld.training.stages.world_model.evaluation`) and the references that read the
future (:mod:`renderworld.training.stages.world_model.references`). ``val/loss`` is the
teacher-forced loss.
Training validates the run's own setting; ``tools/eval.py ... pseudo_labels=DIR
[camera_ckpt=PATH] [camera_tokenizer_ckpt=PATH]`` scores the 3D-Occ and the Camera setting in
one pass and one table (see
:mod:`renderworld.training.stages.world_model.settings`); ``on_eval_end`` draws the pictures
(:mod:`renderworld.training.stages.world_model.pictures`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.utils.data import ConcatDataset, Dataset

from renderworld.data import load_infos
from renderworld.metrics import PlanningMetric
from renderworld.tokenizer import SceneTokenizer
from renderworld.training.registry import Stage, register_stage, sum_count
from renderworld.training.stages.common import grid_of, infos_dir
from renderworld.training.stages.world_model import evaluation as wme
from renderworld.training.stages.world_model import heading as wmh
from renderworld.training.stages.world_model import pose_warp as wmp
from renderworld.training.stages.world_model.checkpoints import CheckpointModels
from renderworld.training.stages.world_model.forecasts import stage_forecast
from renderworld.training.stages.world_model.frozen_tokenizers import FrozenTokenizers
from renderworld.training.stages.world_model.motion import (
    add_motion_stats,
    empty_motion_stats,
    motion_from_stats,
    write_motion,
)
from renderworld.training.stages.world_model.mover_fit import fit_mover_head
from renderworld.training.stages.world_model.pose_warmup import warm_up_pose_head
from renderworld.training.stages.world_model.references import reference_forecasts
from renderworld.training.stages.world_model.report import HISTORY_COMMAND, MODEL_MOVERS
from renderworld.training.stages.world_model.settings import (
    EvalSetting,
    eval_settings,
    extra_train_roots,
    forecaster_of,
    frame_cache_dir,
    setting_header,
    stage_settings,
)
from renderworld.training.stages.world_model.windows import WorldModelWindows
from renderworld.world import (
    teacher_forcing_split,
    world_model_loss,
)

__all__ = ["WorldModelStage"]

log = logging.getLogger("renderworld.training")


@register_stage("world_model")
class WorldModelStage(FrozenTokenizers, CheckpointModels, Stage):
    """World model on frozen tokenizer codes (see the module docstring)."""

    def __init__(self, cfg: Any) -> None:
        super().__init__(cfg)
        self.settings = stage_settings(cfg)
        self.grid = grid_of(cfg)
        #: "tokens" (WorldModel: autoregressive codes) or "pose_warp" (PoseWarpWorldModel); when
        #: evaluating a checkpoint, its own.
        self.forecaster = forecaster_of(cfg)
        self.horizons = wme.horizons_for(self.settings.future)
        #: Frozen tokenizers by checkpoint path (``stage.tokenizer_ckpt``, and a setting's own).
        self._tokenizers: dict[str, SceneTokenizer] = {}
        #: Codes by (tokenizer checkpoint, source, frame key = data root + sample token, see
        #: ``windows.frame_keys``); pose_warp keys add fields.
        self._codes: dict[tuple[str, ...], torch.Tensor] = {}
        self.eval_settings, self._val_occ_root = eval_settings(cfg)
        #: Models of settings evaluated with their own checkpoint (``camera_ckpt``), by key.
        self.setting_models: dict[str, nn.Module] = {}
        self._val_set: Dataset | None = None
        self._train_set: Dataset | None = None
        #: Model-free rows' stats by validation set id: (the set, its stats) (see ``evaluate``).
        self._fixed_stats: dict[int, tuple[Any, dict[str, torch.Tensor]]] = {}
        #: How the evaluated model moves others (its own ``movers``, read at each evaluation).
        self.model_movers = self.settings.movers

    @property
    def forecasters(self) -> tuple[str, ...]:
        """Forecast rows of this evaluation: the model (and its variants) and the baselines."""
        extra = wmp.POSE_METHODS if self.forecaster == "pose_warp" else ()
        if self.forecaster == "pose_warp" and self.model_movers == "learned":
            extra = (*extra, MODEL_MOVERS)
        only = (*wmp.POSE_METHODS, MODEL_MOVERS)
        return tuple(m for m in wme.FORECASTERS if m not in only or m in extra)

    @property
    def planners(self) -> tuple[str, ...]:
        """Planning rows of this evaluation (the checked plans with the pose head only)."""
        extra = wmp.POSE_PLANNERS if self.forecaster == "pose_warp" else ()
        return tuple(p for p in wme.PLANNERS if p not in wmp.POSE_PLANNERS or p in extra)

    # ------------------------------------------------------------------ Stage API
    def lr_scales(self) -> dict[str, float]:
        """The pose head's learning-rate factor in the joint training (pose_warp only)."""
        scale = self.settings.joint_pose_lr_scale
        return {"pose.": scale} if self.forecaster == "pose_warp" and scale not in (0, 1) else {}

    def _windows(self, cfg: Any, split: str, occ_root, gt_targets: bool) -> WorldModelWindows:
        st = self.settings
        return WorldModelWindows(
            load_infos(infos_dir(cfg), split), str(cfg.dataset.data_root), self.grid, st.history,
            st.future, occ_root, gt_targets, frame_cache_dir(cfg),
        )  # fmt: skip

    def build_val_dataset(self, cfg: Any) -> Dataset:
        """Validation windows only: a held-out dataset (all scenes in val) has no train split."""
        _ = self.tokenizer  # a wrong stage.tokenizer_ckpt fails before any data is read
        self._val_set = self._windows(cfg, cfg.dataset.val_split, self._val_occ_root, True)
        return self._val_set

    def build_datasets(self, cfg: Any) -> tuple[Dataset, Dataset | None]:
        _ = self.tokenizer  # a wrong stage.tokenizer_ckpt fails before any data is read
        st, cache = self.settings, frame_cache_dir(cfg)

        def windows(split: str, occ_root, gt_targets: bool) -> WorldModelWindows:
            return self._windows(cfg, split, occ_root, gt_targets)

        # Camera setting: train on pseudo labels; validate pseudo-label inputs against GT (with
        # pseudo_labels=DIR at eval, the same windows give both settings' inputs).
        train = windows(cfg.dataset.train_split, cfg.stage.get("occ_root"), False)
        extra = [
            WorldModelWindows(load_infos(infos, cfg.dataset.train_split), extra_root,
                                  self.grid, st.history, st.future, None, False, cache)
            for extra_root, infos in extra_train_roots(cfg)
        ]  # fmt: skip
        if extra:
            parts = [train, *extra]
            most = max(p.seq.max_boxes for p in parts)
            for p in parts:  # one box count M for the whole batch (default collate)
                p.seq.max_boxes = most
            train = ConcatDataset(parts)
        self._val_set = windows(cfg.dataset.val_split, self._val_occ_root, True)
        self._train_set = train
        return train, self._val_set

    def warm_start(self, model: nn.Module) -> None:
        """Fit the pose head alone for ``stage.pose_warmup_steps`` first, then the mover head
        for ``stage.mover_fit_steps`` (pose_warp only)."""
        steps, st, cfg = self.settings.pose_warmup_steps, self.settings, self.cfg
        if self.forecaster != "pose_warp" or steps + st.mover_fit_steps == 0:
            return
        if self._train_set is None:
            raise RuntimeError(
                f"stage.pose_warmup_steps={steps}, stage.mover_fit_steps={st.mover_fit_steps}: "
                "no training windows (call build_datasets first)"
            )
        if st.mover_fit_steps:
            logs = fit_mover_head(
                model.mover_head, self._train_set, st.history, st.future, self.grid,
                st.mover_fit_steps, st.mover_lr, st.mover_batch, seed=int(cfg.get("seed") or 0),
                progress=bool(cfg.trainer.get("progress_bar", True)),
            )  # fmt: skip
            log.info(f"mover head fitted alone for {st.mover_fit_steps} steps: {logs}")
        if steps == 0:
            return
        logs = warm_up_pose_head(
            self, model, self._train_set, steps,
            lr=float(cfg.optimizer.lr) * self.settings.pose_lr_scale,
            weight_decay=float(cfg.optimizer.weight_decay),
            batch_size=int(cfg.trainer.batch_size), seed=int(cfg.get("seed") or 0),
            progress=bool(cfg.trainer.get("progress_bar", True)),
        )  # fmt: skip
        log.info(f"pose head fitted alone for {steps} steps: pose loss {logs}")

    def _teacher_forced(self, model: nn.Module, batch: dict, tokens: torch.Tensor):
        st = self.settings
        fut = batch["future_mask"].bool()
        hist = torch.ones(fut.shape[0], st.history, dtype=torch.bool, device=fut.device)
        valid = torch.cat([hist, fut], dim=1)
        disp = batch["ego_displacements"].float()
        (tok_in, disp_in), targets = teacher_forcing_split(tokens, disp, valid)
        out = model(tok_in, disp_in, batch["command"].long())
        return world_model_loss(out, targets, st.lambda_l2, cumulative_from=st.history - 1)

    def loss(self, model: nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, Any]]:
        device = batch["ego_displacements"].device
        if self.forecaster == "pose_warp":
            terms = wmp.pose_teacher_forced(self, model, batch)
        else:
            tokens = self.window_tokens(batch, batch["occ"].shape[1], device)
            terms = self._teacher_forced(model, batch, tokens)
        logs = {k: v.detach() for k, v in terms.items() if k != "loss"}
        return terms["loss"], logs

    @torch.no_grad()
    def forecast(
        self,
        model: nn.Module,
        batch: dict,
        setting: EvalSetting,
        tokens: torch.Tensor | None,
        headings: dict[str, torch.Tensor] | None = None,
        baselines: bool = True,
    ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """Forecasts and plans of the model and the baselines for one setting's inputs
        (:func:`~renderworld.training.stages.world_model.forecasts.stage_forecast`)."""
        return stage_forecast(self, model, batch, setting, tokens, headings, baselines)

    def references(self, batch: dict, setting: EvalSetting) -> dict[str, torch.Tensor]:
        """Forecasts [B, S, X, Y, Z] that read the future (reported as references, never as
        methods) of the setting's inputs: ``warp_gt_pose``, ``warp_gt_object_cv``,
        ``warp_gt_movers`` (:func:`~.references.reference_forecasts`)."""
        return reference_forecasts(batch, setting.inputs, self.settings.history, self.grid)

    @property
    def _heading_planners(self) -> tuple[str, ...]:
        """Planners whose plan carries a heading (the model's, both commands, with the pose
        head only)."""
        pose = ("model", HISTORY_COMMAND, *wmp.POSE_PLANNERS)
        return ("cv_traj", "ctr_traj", *(pose if self.forecaster == "pose_warp" else ()))

    def setting_model(self, model: nn.Module, setting: EvalSetting) -> nn.Module:
        """The model a setting is scored with: its own checkpoint's, else ``model``."""
        raw = model.module if hasattr(model, "module") else model
        own = self.setting_models.get(setting.key)
        if own is None:
            return raw
        device = next(raw.parameters()).device
        if next(own.parameters()).device != device:
            self.setting_models[setting.key] = own = own.to(device)
        return own

    def evaluate(self, model: nn.Module, loader: Any) -> dict[str, torch.Tensor]:
        raw = model.module if hasattr(model, "module") else model
        device = next(raw.parameters()).device
        st, hs = self.settings, self.horizons
        h, f = st.history, st.future
        self.model_movers = getattr(raw, "movers", "static")
        pose = self.forecaster == "pose_warp"
        stats: dict[str, torch.Tensor] = {}
        plan: dict[str, PlanningMetric] = {}
        for s in self.eval_settings:
            stats.update(wme.empty_forecast_stats(f, device, s.prefix, self.forecasters))
            if pose:
                stats.update(empty_motion_stats(f, device, s.prefix))
            for p in self.planners:
                plan[f"{s.prefix}{p}"] = PlanningMetric(f, hs, occupancy_grid=self.grid)
                for split in wme.SPLITS:
                    for name, shape in (("l2_sum", (f,)), ("l2_count", (f,)), ("windows", ())):
                        stats[f"{s.prefix}{p}/{split}/{name}"] = torch.zeros(
                            shape, dtype=torch.float64, device=device
                        )
            stats.update(wmh.empty_heading_stats(self._heading_planners, f, device, s.prefix))
        sums: dict[str, list[torch.Tensor]] = {"loss": [], "token_ce": [], "l2": []}
        first = self.eval_settings[0]
        # The baselines and references read no model: scored once per validation set, reused by
        # every later validation of the run. The set is held with them: its id is never reused.
        data = getattr(loader, "dataset", loader)
        held = self._fixed_stats.get(id(data))
        known = held[1] if held is not None and held[0] is data else None
        for batch in loader:
            batch = self.transfer_batch(batch, device)
            occ = batch[first.inputs]
            # Teacher-forced loss of the first setting's model on its whole window.
            tokens = self.window_tokens(
                batch, occ.shape[1], device, first.inputs, first.source, first.tokenizer
            )
            if self.forecaster == "pose_warp":
                terms = wmp.pose_teacher_forced(
                    self, self.setting_model(raw, first), batch, first.inputs, first.source,
                    first.tokenizer,
                )  # fmt: skip
            else:
                terms = self._teacher_forced(self.setting_model(raw, first), batch, tokens)
            for k in sums:
                sums[k].append(terms[k].detach().double().cpu().expand(occ.shape[0]))
            valid = batch["future_mask"].bool()
            target = batch.get("occ_target", occ)[:, h:]
            target_mask = batch.get("mask_camera_target", batch["mask_camera"])[:, h:]
            turning = wme.turning_windows(batch["future_poses"], valid)
            for s in self.eval_settings:
                yaws: dict[str, torch.Tensor] = {}
                forecasts, trajs = self.forecast(
                    self.setting_model(raw, s), batch, s, tokens if s is first else None, yaws,
                    baselines=known is None,
                )  # fmt: skip
                wmh.add_heading_stats(stats, yaws, batch["future_poses"][..., 2], valid, s.prefix)
                if known is None:
                    forecasts.update(self.references(batch, s))
                wme.add_forecast_stats(
                    stats, forecasts, target, target_mask, valid, s.prefix, turning
                )
                mine = {p: plan[f"{s.prefix}{p}"] for p in self.planners}
                wme.update_planning(mine, trajs, batch, target, valid)
                wme.add_split_l2(stats, trajs, batch["future_traj"], valid, turning, s.prefix)
                if pose:
                    sm = self.setting_model(raw, s)
                    add_motion_stats(stats, sm, batch, s.inputs, h, self.grid, s.prefix)
        for k, vals in sums.items():
            stats.update(sum_count(k, torch.cat(vals) if vals else torch.zeros(0)))
        for key, metric in plan.items():
            stats.update(wme.planning_to_stats(metric, f"{key}/plan"))
        fixed = tuple(f"{s.prefix}{m}/" for s in self.eval_settings for m in wme.MODEL_FREE_METHODS)
        if known is None:
            mine = {k: v.clone() for k, v in stats.items() if k.startswith(fixed)}
            self._fixed_stats[id(data)] = (data, mine)
        else:
            stats.update({k: v.to(device) for k, v in known.items()})
        return stats

    def compute_metrics(self, stats: dict[str, torch.Tensor]) -> dict[str, float]:
        out = {
            k: float(stats[f"{k}/sum"] / stats[f"{k}/count"])
            if float(stats[f"{k}/count"])
            else float("nan")
            for k in ("loss", "token_ce", "l2")
        }
        out["num_windows"] = float(stats["loss/count"])
        for s in self.eval_settings:
            out.update(wme.setting_metrics(stats, s.prefix, self.horizons, self.grid))
            out.update(motion_from_stats(stats, self.horizons, s.prefix))
        return out

    def write_report(self, metrics: dict[str, float], run_dir: str) -> str | None:
        """Write ``world_model_eval.csv`` / ``.md`` into ``run_dir``; return the table text."""
        if not any(k.endswith("model/miou_avg") for k in metrics):
            return None
        n = metrics.get("val/num_windows", metrics.get("num_windows", float("nan")))
        header = [
            f"World model evaluation: split {self.cfg.dataset.val_split!r} of "
            f"{Path(str(self.cfg.dataset.data_root)).name} ({self.cfg.dataset.version}), "
            f"{int(n)} windows, history {self.settings.history}, "
            f"future {self.settings.future}; grid {self.grid.name}",
            setting_header(self.eval_settings, self.cfg.get("ckpt"), self.settings.tokenizer_ckpt),
            "Forecast: mIoU over classes 0..16, full volume (OccWorld protocol); IoU = occupied "
            "vs free; percent. Camera-mask values in CSV",
            "Planning: L2 at horizon (UniAD); mean-to-horizon in CSV. L2 in metres; Col = "
            "collision rate vs GT boxes at horizon, percent (vs GT occupancy in CSV)",
        ]
        settings = [(s.label, s.prefix) for s in self.eval_settings]
        motion = write_motion(metrics, run_dir, self.horizons, settings)
        return wme.write_report(metrics, run_dir, self.horizons, header, settings, motion)

    def on_eval_end(self, model: nn.Module, metrics: dict[str, float], run_dir: str) -> None:
        """Pictures of the evaluation into ``run_dir``: BEV forecasts and planned trajectories."""
        if self._val_set is None or len(self._val_set) == 0:
            return
        from renderworld.training.stages.world_model.pictures import write_pictures

        write_pictures(self, model, self._val_set, Path(run_dir))
