"""The ``world_model`` stage: train the temporal world model on a frozen tokenizer's tokens.

Data: windows of ``history + future`` keyframes (``OccSequenceDataset``) from the dataset's
Occ3D gts (``stage.occ_root: null``, the "3D-Occ" setting) or exported Img2Occ pseudo labels
(``stage.occ_root``, the "Camera" setting). Every frame is encoded by the frozen tokenizer of
``stage.tokenizer_ckpt`` (no grad, 32-bit), and its codes are cached in memory by sample token,
so each keyframe is encoded once per run. The tokenizer lives on the stage, never in the trained
module: checkpoints hold the world model only.

Loss (paper Eq. 6.20): token cross-entropy + ``lambda_l2`` x L2 of the trajectory accumulated
from the last history frame (``cumulative_from = history - 1``, as a rollout plans).

Evaluation (``val/``): for each window, roll out ``future`` frames from the history tokens,
the history displacements and the **current** command; decode the forecast; forecast mIoU/IoU
per step (full volume, OccWorld protocol; and inside the camera mask, ``cam/``), planning L2
(both conventions) and collision rates vs GT boxes and GT object occupancy, and the same for the
baselines Copy&Paste, constant-velocity warp and constant-velocity trajectory (see
:mod:`renderworld.training.stages.world_model_eval`). ``val/loss`` is the teacher-forced loss.
"""

from __future__ import annotations

import os
import warnings
from contextlib import nullcontext
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf
from torch import nn
from torch.utils.data import Dataset

from renderworld.constants import FUTURE_FRAMES
from renderworld.data import load_infos
from renderworld.metrics import PlanningMetric
from renderworld.planning import register_tokenizer, save_planner_bundle
from renderworld.tokenizer import SceneTokenizer, Tokens, build_tokenizer
from renderworld.training.checkpoint import CheckpointError, load_checkpoint
from renderworld.training.registry import Stage, register_stage, sum_count
from renderworld.training.stages import world_model_eval as wme
from renderworld.training.stages.common import grid_of, infos_dir
from renderworld.training.stages.tokenizer import load_tokenizer
from renderworld.world import (
    WorldModel,
    WorldModelConfig,
    constant_velocity_trajectory,
    copy_paste_forecast,
    teacher_forcing_split,
    warp_constant_velocity_forecast,
    world_model_loss,
)

__all__ = [
    "WorldModelStage",
    "world_model_config",
    "export_planner_bundle",
    "TOKENIZER_KIND",
]

#: Name of :class:`SceneTokenizer` in planner bundles.
TOKENIZER_KIND = "scene_tokenizer"
register_tokenizer(TOKENIZER_KIND, SceneTokenizer, from_config=build_tokenizer)

# WorldModelConfig fields that come from the tokenizer and the stage, not from stage.model.
_DERIVED = ("codebook_sizes", "token_grid", "history_frames", "future_frames")
_ENCODE_CHUNK = 16  # frames per tokenizer call (bounds memory on the Occ3D grid)


@dataclass(frozen=True)
class _Settings:
    tokenizer_ckpt: str
    history: int
    future: int
    lambda_l2: float
    cache_tokens: bool


def _settings(cfg: Any) -> _Settings:
    s = cfg.stage
    history, future, lam = s.get("history"), s.get("future"), s.get("lambda_l2")
    if not isinstance(history, int) or isinstance(history, bool) or history < 2:
        raise ValueError(
            f"stage.history: expected an int >= 2 (the constant-velocity baselines need one "
            f"displacement), got {history!r}"
        )
    if not isinstance(future, int) or isinstance(future, bool) or not 1 <= future <= FUTURE_FRAMES:
        raise ValueError(f"stage.future: expected an int in 1..{FUTURE_FRAMES}, got {future!r}")
    if not isinstance(lam, (int, float)) or isinstance(lam, bool) or not lam >= 0:
        raise ValueError(f"stage.lambda_l2: expected a number >= 0, got {lam!r}")
    ckpt = s.get("tokenizer_ckpt")
    if not ckpt:
        raise ValueError(
            "stage.tokenizer_ckpt: required; pass the tokenizer run's checkpoint, e.g. "
            "stage.tokenizer_ckpt=outputs/train/tokenizer/<time>/checkpoints/best.pt"
        )
    return _Settings(str(ckpt), history, future, float(lam), bool(s.get("cache_tokens", True)))


def world_model_config(cfg: Any, tokenizer_cfg: Any) -> WorldModelConfig:
    """The :class:`WorldModelConfig` of a run config on a tokenizer.

    Args:
        cfg: run config (``stage.model`` fields, ``stage.history``, ``stage.future``).
        tokenizer_cfg: the tokenizer's ``TokenizerConfig`` (codebook sizes, latent grid).

    Raises:
        ValueError: unknown ``stage.model`` keys, or keys that the tokenizer / stage set.
    """
    st = _settings(cfg)
    model = OmegaConf.to_container(cfg.stage.model, resolve=True) if cfg.stage.model else {}
    known = {f.name for f in fields(WorldModelConfig)} - set(_DERIVED)
    for key in model:
        if key in _DERIVED:
            raise ValueError(
                f"stage.model.{key}: set by the tokenizer / stage.history / stage.future, "
                "remove it from stage.model"
            )
        if key not in known:
            raise ValueError(f"stage.model.{key}: unknown key; expected one of {sorted(known)}")
    return WorldModelConfig(
        codebook_sizes=tuple(tokenizer_cfg.codebook_sizes),
        token_grid=tuple(tokenizer_cfg.latent_shape),
        history_frames=st.history,
        future_frames=st.future,
        **model,
    )


def _no_autocast(device: torch.device):
    if device.type == "cuda":
        return torch.autocast(device_type="cuda", enabled=False)
    return nullcontext()


@register_stage("world_model")
class WorldModelStage(Stage):
    """World model on frozen tokenizer codes (see the module docstring)."""

    def __init__(self, cfg: Any) -> None:
        super().__init__(cfg)
        self.settings = _settings(cfg)
        self.grid = grid_of(cfg)
        self.horizons = wme.horizons_for(self.settings.future)
        self._tokenizer: SceneTokenizer | None = None
        self._codes: dict[str, torch.Tensor] = {}

    # ------------------------------------------------------------------ tokenizer
    @property
    def tokenizer(self) -> SceneTokenizer:
        """The frozen tokenizer (loaded once from ``stage.tokenizer_ckpt``, eval mode)."""
        if self._tokenizer is None:
            path = self.settings.tokenizer_ckpt
            try:
                tok = load_tokenizer(path, "cpu")
            except CheckpointError as err:
                raise CheckpointError(f"stage.tokenizer_ckpt: {err}") from err
            if tuple(tok.cfg.grid_shape) != tuple(self.grid.shape):
                raise ValueError(
                    f"stage.tokenizer_ckpt: the tokenizer {path!r} was trained on a "
                    f"{tuple(tok.cfg.grid_shape)} grid, this run uses grid {self.grid.name!r} "
                    f"{tuple(self.grid.shape)}; pass grid=<the tokenizer's grid>"
                )
            self._tokenizer = tok
        return self._tokenizer

    def _tokenizer_on(self, device: torch.device) -> SceneTokenizer:
        tok = self.tokenizer
        if next(tok.parameters()).device != device:
            self._tokenizer = tok = tok.to(device)
        return tok

    @torch.no_grad()
    def window_tokens(self, batch: dict, frames: int, device: torch.device) -> torch.Tensor:
        """Codes [B, frames, G, h, w] int64 on ``device`` of a batch's first ``frames`` frames.

        Frames already encoded (same sample token) come from the in-memory cache.
        """
        occ = batch["occ"]
        b = occ.shape[0]
        keys = [row[:frames] for row in wme.frame_keys(batch, b, occ.shape[1])]
        tok = self._tokenizer_on(device)
        cache = self._codes if self.settings.cache_tokens else {}
        todo: dict[str, tuple[int, int]] = {}
        for i, row in enumerate(keys):
            for j, key in enumerate(row):
                if key not in cache and key not in todo:
                    todo[key] = (i, j)
        names, where = list(todo), list(todo.values())
        for c in range(0, len(names), _ENCODE_CHUNK):
            chunk = where[c : c + _ENCODE_CHUNK]
            x = torch.stack([occ[i, j] for i, j in chunk]).to(device)
            with _no_autocast(device):
                idx = tok.encode(x).indices
            store = torch.int16 if max(tok.cfg.codebook_sizes) <= 2**15 else torch.int32
            for key, codes in zip(names[c : c + _ENCODE_CHUNK], idx.to("cpu", store)):
                cache[key] = codes
        codes = torch.stack([torch.stack([cache[k] for k in row]) for row in keys])
        return codes.to(device).long()

    # ------------------------------------------------------------------ Stage API
    def build_model(self, cfg: Any) -> nn.Module:
        """The world model; when evaluating (``ckpt`` set) its architecture is the checkpoint's.

        ``stage.model`` keys that differ from the checkpoint's are taken from it with a warning
        (they are architecture only); a different ``stage.history`` / ``stage.future`` is an
        error (they define the evaluation protocol and the model's window).
        """
        mine = world_model_config(cfg, self.tokenizer.cfg)
        ckpt = cfg.get("ckpt") if cfg.get("task") == "eval" else None
        if not ckpt or not Path(str(ckpt)).is_file():
            return WorldModel(mine)
        stored = OmegaConf.create(load_checkpoint(ckpt, expected_stage="world_model")["config"])
        _check_same_tokenizer(stored, self.settings.tokenizer_ckpt)
        theirs = world_model_config(stored, self.tokenizer.cfg)
        diff = [
            f.name
            for f in fields(WorldModelConfig)
            if getattr(mine, f.name) != getattr(theirs, f.name)
        ]
        for key, name in (("history_frames", "history"), ("future_frames", "future")):
            if key in diff:
                raise ValueError(
                    f"stage.{name}: the checkpoint {str(ckpt)!r} was trained with "
                    f"{getattr(theirs, key)}, this run has {getattr(mine, key)}; pass "
                    f"stage.{name}={getattr(theirs, key)}"
                )
        if diff:
            warnings.warn(
                "stage.model: "
                + ", ".join(f"{k}={getattr(theirs, k)} (not {getattr(mine, k)})" for k in diff)
                + f" taken from the checkpoint {str(ckpt)!r}",
                UserWarning,
                stacklevel=2,
            )
        return WorldModel(theirs)

    def build_datasets(self, cfg: Any) -> tuple[Dataset, Dataset | None]:
        _ = self.tokenizer  # a wrong stage.tokenizer_ckpt fails before any data is read
        folder = infos_dir(cfg)
        occ_root, root = cfg.stage.get("occ_root"), str(cfg.dataset.data_root)
        st = self.settings

        def windows(split: str, gt_targets: bool) -> wme.WorldModelWindows:
            infos = load_infos(folder, split)
            return wme.WorldModelWindows(
                infos, root, self.grid, st.history, st.future, occ_root, gt_targets
            )

        # Camera setting: train on pseudo labels; validate pseudo-label inputs against GT.
        return windows(cfg.dataset.train_split, False), windows(cfg.dataset.val_split, True)

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
        tokens = self.window_tokens(batch, batch["occ"].shape[1], device)
        terms = self._teacher_forced(model, batch, tokens)
        logs = {k: v.detach() for k, v in terms.items() if k != "loss"}
        return terms["loss"], logs

    def evaluate(self, model: nn.Module, loader: Any) -> dict[str, torch.Tensor]:
        raw = model.module if hasattr(model, "module") else model
        device = next(raw.parameters()).device
        st, hs = self.settings, self.horizons
        h, f = st.history, st.future
        tok = self._tokenizer_on(device)
        stats = wme.empty_forecast_stats(f, device)
        plan = {p: PlanningMetric(f, hs, occupancy_grid=self.grid) for p in wme.PLANNERS}
        sums: dict[str, list[torch.Tensor]] = {"loss": [], "token_ce": [], "l2": []}
        for batch in loader:
            batch = self.transfer_batch(batch, device)
            occ, disp, cmd = batch["occ"], batch["ego_displacements"].float(), batch["command"]
            tokens = self.window_tokens(batch, occ.shape[1], device)
            terms = self._teacher_forced(raw, batch, tokens)
            b = occ.shape[0]
            for k in sums:
                sums[k].append(terms[k].detach().double().cpu().expand(b))

            ro = raw.rollout(tokens[:, :h], disp[:, : h - 1], cmd.long(), steps=f)
            with _no_autocast(device):
                frames = [
                    tok.decode(
                        Tokens(ro.tokens[:, k], tok.cfg.codebook_sizes, tok.cfg.codebook_names)
                    )
                    for k in range(f)
                ]
            current = occ[:, h - 1]
            forecasts = {
                "model": torch.stack(frames, dim=1),
                "copy_paste": copy_paste_forecast(current, f),
                "warp_cv": warp_constant_velocity_forecast(current, disp[:, h - 2], f, self.grid),
            }
            valid = batch["future_mask"].bool()
            target = batch.get("occ_target", occ)[:, h:]
            target_mask = batch.get("mask_camera_target", batch["mask_camera"])[:, h:]
            wme.add_forecast_stats(stats, forecasts, target, target_mask, valid)
            trajs = {
                "model": ro.trajectory,
                "cv_traj": constant_velocity_trajectory(disp[:, : h - 1], f),
            }
            wme.update_planning(plan, trajs, batch, target, valid)
        for k, vals in sums.items():
            stats.update(sum_count(k, torch.cat(vals) if vals else torch.zeros(0)))
        for p in plan:
            stats.update(wme.planning_to_stats(plan[p], f"{p}/plan"))
        return stats

    def compute_metrics(self, stats: dict[str, torch.Tensor]) -> dict[str, float]:
        out = {
            k: float(stats[f"{k}/sum"] / stats[f"{k}/count"])
            if float(stats[f"{k}/count"])
            else float("nan")
            for k in ("loss", "token_ce", "l2")
        }
        out["num_windows"] = float(stats["loss/count"])
        for p, _, has_occ, has_traj in wme.METHODS:
            if has_occ:
                full = wme.forecast_from_stats(stats, f"{p}/full", self.horizons)
                cam = wme.forecast_from_stats(stats, f"{p}/cam", self.horizons, "camera")
                out.update({f"{p}/{k}": v for k, v in full.items()})
                out.update({f"{p}/cam/{k}": v for k, v in cam.items() if "step" not in k})
            if has_traj:
                res = wme.planning_from_stats(stats, f"{p}/plan", self.horizons, self.grid)
                out.update({f"{p}/{k}": v for k, v in res.items()})
        return out

    def write_report(self, metrics: dict[str, float], run_dir: str) -> str | None:
        """Write ``world_model_eval.csv`` / ``.md`` into ``run_dir``; return the table text."""
        if not any(k.endswith("model/miou_avg") for k in metrics):
            return None
        occ_root = self.cfg.stage.get("occ_root")
        source = (
            "inputs and targets: GT occupancy (3D-Occ setting)"
            if not occ_root
            else f"inputs: pseudo labels {occ_root}, targets: GT occupancy (Camera setting)"
        )
        n = metrics.get("val/num_windows", metrics.get("num_windows", float("nan")))
        header = [
            f"World model evaluation: split {self.cfg.dataset.val_split!r} of "
            f"{self.cfg.dataset.name}, {int(n)} windows, history {self.settings.history}, "
            f"future {self.settings.future}; {source}; grid {self.grid.name}",
            "Forecast: mIoU over classes 0..16, full volume (OccWorld protocol); IoU = occupied "
            "vs free; percent. Camera-mask values in CSV",
            "Planning: L2 at horizon (UniAD); mean-to-horizon in CSV. L2 in metres; Col = "
            "collision rate vs GT boxes at horizon, percent (vs GT occupancy in CSV)",
        ]
        return wme.write_report(metrics, run_dir, self.horizons, header)


def _check_same_tokenizer(trained_cfg: Any, tokenizer_ckpt) -> None:
    """Warn when ``tokenizer_ckpt`` is not the file the world model was trained on."""
    trained_on = trained_cfg.stage.get("tokenizer_ckpt")
    if trained_on and Path(str(trained_on)).resolve() != Path(str(tokenizer_ckpt)).resolve():
        warnings.warn(
            f"tokenizer_ckpt: {str(tokenizer_ckpt)!r} differs from the tokenizer the world "
            f"model was trained on ({trained_on!r}); results are only valid if they hold the "
            "same weights",
            UserWarning,
            stacklevel=3,
        )


def export_planner_bundle(
    world_model_ckpt: str | os.PathLike,
    tokenizer_ckpt: str | os.PathLike,
    out_path: str | os.PathLike,
) -> Path:
    """Write a :mod:`renderworld.planning` bundle from a world-model and a tokenizer checkpoint.

    Args:
        world_model_ckpt: ``last.pt`` / ``best.pt`` of a ``world_model`` run.
        tokenizer_ckpt: the ``tokenizer`` checkpoint that run was trained on.
        out_path: bundle file to write (its folder must exist); load it with
            ``renderworld.planning.load_planner(out_path)`` after importing this module (which
            registers the tokenizer kind ``"scene_tokenizer"``).

    Returns:
        ``out_path``.

    Raises:
        CheckpointError: a checkpoint that is missing, of another stage, or does not fit.
    """
    from renderworld.training.checkpoint import check_state_dict_keys

    ckpt = load_checkpoint(world_model_ckpt, expected_stage="world_model")
    cfg = OmegaConf.create(ckpt["config"])
    _check_same_tokenizer(cfg, tokenizer_ckpt)
    tokenizer = load_tokenizer(tokenizer_ckpt, "cpu")
    model = WorldModel(world_model_config(cfg, tokenizer.cfg))
    check_state_dict_keys(model, ckpt["model"], source=f"checkpoint {str(world_model_ckpt)!r}")
    model.load_state_dict(ckpt["model"], strict=True)
    return save_planner_bundle(out_path, tokenizer, model)
