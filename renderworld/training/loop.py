"""The training loop: one ``Trainer`` drives any registered ``Stage``.

Per optimizer step: ``grad_accum`` micro-batches (DDP gradient sync only on the last), autocast
(bf16, or fp16 with a gradient scaler; CUDA or CPU), gradient clipping, optimizer and scheduler
step. Every ``log_every`` steps the rank-summed training loss and throughput are logged; every
``val_every`` steps the stage's metrics are computed over the rank-sharded validation set;
``last.pt`` every ``ckpt_every`` steps and at the end, ``best.pt`` when the monitored metric
improves. A time budget stops the run cleanly.
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from contextlib import nullcontext
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import Subset
from tqdm.auto import tqdm

from renderworld.training.checkpoint import (
    CHECKPOINT_SCHEMA_VERSION,
    check_state_dict_keys,
    save_checkpoint,
)
from renderworld.training.config import OptimizerConfig, SchedulerConfig, TrainerConfig
from renderworld.training.data import SeededDataset, ShardedSampler, make_loader
from renderworld.training.distributed import (
    DistInfo,
    all_gather_object,
    all_reduce_sum,
    any_rank,
)
from renderworld.training.ema import WeightEMA
from renderworld.training.loggers import MetricLogger, MetricWindow
from renderworld.training.optim import build_optimizer, build_scheduler, default_param_groups
from renderworld.training.registry import Stage
from renderworld.training.schedule import write_schedule
from renderworld.training.seed import get_rng_state, rng_isolated, seed_everything, set_rng_state
from renderworld.training.validation import (
    autocast_context,
    build_val_loader,
    effective_precision,
    run_validation,
)

__all__ = ["Trainer"]
log = logging.getLogger("renderworld.training")


class Trainer:
    """Builds the model, data, optimizer and schedule for a stage and runs the loop.

    Args:
        stage: The stage instance.
        cfg: The full resolved config.
        run_dir: Run directory (checkpoints/, metrics.csv).
        info: Distributed info.
        tcfg, ocfg, scfg: Validated trainer / optimizer / scheduler configs.
        seed: Run seed.
        config_yaml: Resolved config as YAML, stored in checkpoints.
    """

    def __init__(
        self,
        stage: Stage,
        cfg: Any,
        run_dir: Path,
        info: DistInfo,
        tcfg: TrainerConfig,
        ocfg: OptimizerConfig,
        scfg: SchedulerConfig,
        seed: int,
        config_yaml: str,
    ) -> None:
        self.stage, self.cfg, self.run_dir, self.info = stage, cfg, run_dir, info
        self.tcfg, self.seed, self.config_yaml = tcfg, seed, config_yaml
        self.ckpt_dir = run_dir / "checkpoints"
        self.precision = effective_precision(tcfg.precision, info.device)

        # Same seed on every rank for data and model construction: identical replicas.
        seed_everything(seed)
        train_set, val_set = stage.build_datasets(cfg)
        if tcfg.overfit_samples:
            train_set = Subset(train_set, range(min(tcfg.overfit_samples, len(train_set))))
            val_set = train_set
        self.train_set = SeededDataset(train_set, seed)
        self.model = stage.build_model(cfg).to(info.device)
        self.ema = WeightEMA(self.model, tcfg.ema_decay) if tcfg.ema_decay else None
        self.ddp_model: nn.Module = self.model
        if info.distributed:
            self.ddp_model = DistributedDataParallel(
                self.model,
                device_ids=[info.device.index] if info.device.type == "cuda" else None,
                find_unused_parameters=tcfg.find_unused_parameters,
            )
        groups = stage.param_groups(self.model)
        if groups is None:
            groups = default_param_groups(self.model, ocfg, stage.lr_scales())
        self.optimizer = build_optimizer(self.model, ocfg, groups)
        # fp16 overflows where bf16 does not: its loss is scaled, and a step whose gradients
        # overflow is skipped (the scale halves) instead of raising below.
        self.scaler = torch.amp.GradScaler(info.device.type, enabled=self.precision == "fp16")

        self.sampler = ShardedSampler(
            len(self.train_set),
            num_replicas=info.world_size,
            rank=info.rank,
            shuffle=True,
            seed=seed if tcfg.data_seed is None else tcfg.data_seed,
            drop_last=True,
        )
        per_rank = len(self.sampler.shard())
        self.steps_per_epoch = per_rank // tcfg.batch_size // tcfg.grad_accum
        if self.steps_per_epoch < 1:
            raise ValueError(
                f"training set too small: {len(self.train_set)} samples over "
                f"{info.world_size} rank(s) give {per_rank} per rank, fewer than one optimizer "
                f"step of batch_size={tcfg.batch_size} x grad_accum={tcfg.grad_accum}"
            )
        limits = []
        if tcfg.max_steps is not None:
            limits.append(tcfg.max_steps)
        if tcfg.max_epochs is not None:
            limits.append(tcfg.max_epochs * self.steps_per_epoch)
        self.total_steps = min(limits)
        self.scheduler = build_scheduler(self.optimizer, scfg, self.total_steps)
        self.val_loader = (
            build_val_loader(stage, val_set, tcfg, info, seed) if val_set is not None else None
        )

        self.step = self.epoch = self.samples_in_epoch = 0
        self.elapsed_s = 0.0
        self.best: dict[str, Any] = {"metric": tcfg.monitor, "value": None, "step": None}
        self.val_metrics: dict[str, float] = {}
        # Training stream: per-rank seed (dropout differs across ranks, as it should).
        seed_everything(seed + info.rank)

    @property
    def eval_model(self) -> nn.Module:
        """The weights validated, checkpointed as ``model`` and read out: the EMA when on."""
        return self.ema.module if self.ema is not None else self.model

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """Checkpoint dict; collective (every rank must call it: RNG states are gathered)."""
        rng = all_gather_object(get_rng_state(), self.info)
        return {
            "schema_version": CHECKPOINT_SCHEMA_VERSION,
            "stage": self.stage.name,
            "step": self.step,
            "epoch": self.epoch,
            "samples_in_epoch": self.samples_in_epoch,
            "elapsed_s": self.elapsed_s,
            "world_size": self.info.world_size,
            "config": self.config_yaml,
            "model": self.eval_model.state_dict(),
            **(
                {"model_raw": self.model.state_dict(), "ema": self.ema.state()}
                if self.ema is not None
                else {}
            ),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "grad_scaler": self.scaler.state_dict() if self.scaler.is_enabled() else {},
            "rng": rng,
            "best": dict(self.best),
            "metrics": dict(self.val_metrics),
        }

    def load_state_dict(self, ckpt: dict[str, Any], source: str) -> None:
        """Restore everything from a training checkpoint; strict on model keys.

        With ``model_raw`` in the checkpoint (written with an EMA) the optimizer's weights come
        from it and ``model`` is the average; without, ``model`` is both and an EMA turned on
        for the resume starts its average there.
        """
        raw = ckpt.get("model_raw", ckpt["model"])
        check_state_dict_keys(self.model, raw, source=source)
        self.model.load_state_dict(raw, strict=True)
        if self.ema is not None:
            has_ema = "model_raw" in ckpt
            self.ema.load(ckpt["model"], ckpt.get("ema") if has_ema else None)
        self.optimizer.load_state_dict(ckpt["optimizer"])
        self.scheduler.load_state_dict(ckpt["scheduler"])
        if self.scaler.is_enabled() and ckpt.get("grad_scaler"):
            self.scaler.load_state_dict(ckpt["grad_scaler"])
        self.step, self.epoch = int(ckpt["step"]), int(ckpt["epoch"])
        self.samples_in_epoch = int(ckpt["samples_in_epoch"])
        self.elapsed_s = float(ckpt.get("elapsed_s", 0.0))
        self.best = dict(ckpt.get("best") or self.best)
        self.val_metrics = dict(ckpt.get("metrics") or {})
        rng = ckpt["rng"]
        if len(rng) == self.info.world_size:
            set_rng_state(rng[self.info.rank])
        else:
            warnings.warn(
                f"{source}: saved with {len(rng)} rank(s), resuming with "
                f"{self.info.world_size}: the data position is kept but RNG streams are "
                "re-seeded, so the resume is not bit-exact",
                RuntimeWarning,
                stacklevel=2,
            )
            seed_everything(self.seed + self.info.rank + 7919 * self.step)

    def save(self, name: str) -> None:
        """Write ``checkpoints/<name>`` on rank 0 (collective: call on every rank)."""
        state = self.state_dict()
        if self.info.is_main:
            save_checkpoint(state, self.ckpt_dir / name)

    # ------------------------------------------------------------------ loop
    def _optimizer_step(self, batches: Any) -> tuple[dict[str, torch.Tensor], float]:
        tcfg, info = self.tcfg, self.info
        self.optimizer.zero_grad(set_to_none=True)
        sums: dict[str, torch.Tensor] = {}
        for i in range(tcfg.grad_accum):
            batch = self.stage.transfer_batch(next(batches), info.device)
            last = i == tcfg.grad_accum - 1
            sync = nullcontext() if (last or not info.distributed) else self.ddp_model.no_sync()
            with sync:
                with autocast_context(self.precision, info.device):
                    loss, logs = self.stage.loss(self.ddp_model, batch)
                if not (isinstance(loss, torch.Tensor) and loss.ndim == 0):
                    raise TypeError(
                        f"{type(self.stage).__name__}.loss: expected a scalar tensor, got "
                        f"{getattr(loss, 'shape', type(loss))}"
                    )
                self.scaler.scale(loss / tcfg.grad_accum).backward()
            for k, v in {"loss": loss, **dict(logs)}.items():
                v = torch.as_tensor(v).detach().float().to(info.device)
                sums[f"train/{k}"] = sums.get(f"train/{k}", 0) + v / tcfg.grad_accum
        self.scaler.unscale_(self.optimizer)
        max_norm = tcfg.grad_clip if tcfg.grad_clip else math.inf
        norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), max_norm)
        norm_f = float(norm)
        if not math.isfinite(norm_f) and self.precision != "fp16":
            # Gradients are synchronized, so every rank raises here together.
            raise FloatingPointError(
                f"non-finite gradient norm ({norm_f}) at step {self.step + 1} "
                f"(loss {float(sums['train/loss']):.6g}); last checkpoint: "
                f"{self.ckpt_dir / 'last.pt'}"
            )
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.scheduler.step()
        if self.ema is not None:
            self.ema.update(self.model)
        return sums, norm_f

    def validate(self) -> dict[str, float]:
        """Validation metrics (``val/...``), or {} without a validation set."""
        if self.val_loader is None:
            return {}
        return run_validation(
            self.stage, self.eval_model, self.val_loader, self.info, self.precision,
            self.tcfg.progress_bar,
        )  # fmt: skip

    def _after_validation(self, metrics: dict[str, float]) -> None:
        self.val_metrics = metrics
        monitor = self.tcfg.monitor
        if not monitor or not metrics:
            return
        if monitor not in metrics:
            raise ValueError(
                f"trainer.monitor: metric {monitor!r} not produced; validation gave "
                f"{sorted(metrics)}"
            )
        value = metrics[monitor]
        best = self.best.get("value")
        better = math.isfinite(value) and (
            best is None or (value < best if self.tcfg.monitor_mode == "min" else value > best)
        )
        if better:
            self.best = {"metric": monitor, "value": value, "step": self.step}
            self.save("best.pt")

    def fit(self, logger: MetricLogger) -> dict[str, float]:
        """Train until max_steps / max_epochs; return final metrics.

        ``trainer.max_minutes`` is a guard, not a schedule: when it fires, the run stops,
        checkpoints, and ``schedule.json`` in the run dir says at which step of how many.
        """
        tcfg, info = self.tcfg, self.info
        self._announce()
        self.model.train()
        if self.step == 0:
            with rng_isolated():
                self.stage.warm_start(self.model)
        self.stage.on_train_start(self.model, str(self.run_dir))
        bar = tqdm(
            total=self.total_steps,
            initial=self.step,
            disable=not (info.is_main and tcfg.progress_bar),
            desc=f"{self.stage.name}",
            dynamic_ncols=True,
        )
        t0, base_elapsed = time.monotonic(), self.elapsed_s
        window = MetricWindow()
        validated_at = saved_at = -1
        stopped_early = False
        samples_per_step = tcfg.batch_size * tcfg.grad_accum * info.world_size
        max_epochs = tcfg.max_epochs if tcfg.max_epochs is not None else math.inf

        while self.step < self.total_steps and self.epoch < max_epochs and not stopped_early:
            batches, steps_left = self._epoch_batches()
            for _ in range(steps_left):
                if tcfg.max_minutes is not None:
                    # Checked before a step, so a resumed run whose budget is spent does none.
                    elapsed = base_elapsed + time.monotonic() - t0
                    stopped_early = any_rank(elapsed >= tcfg.max_minutes * 60.0, info)
                    if stopped_early:
                        break
                sums, norm = self._optimizer_step(batches)
                self.step += 1
                self.samples_in_epoch += samples_per_step
                self.elapsed_s = base_elapsed + time.monotonic() - t0
                window.add(sums)
                bar.update(1)
                if self.step % tcfg.log_every == 0 or self.step == self.total_steps:
                    self._log_window(window, norm, samples_per_step, logger, bar)
                if tcfg.val_every and self.step % tcfg.val_every == 0:
                    self._validate_and_log(logger)
                    validated_at = self.step
                if tcfg.ckpt_every and self.step % tcfg.ckpt_every == 0:
                    self.save("last.pt")
                    saved_at = self.step
                if self.step >= self.total_steps:
                    break
            else:
                self.epoch += 1
                self.samples_in_epoch = 0
        bar.close()
        self._write_schedule(stopped_early)
        if validated_at != self.step:
            self._validate_and_log(logger)
        if saved_at != self.step:
            self.save("last.pt")
        final = self.stage.on_train_end(self.eval_model, str(self.run_dir))
        if final:  # the stage re-scored the final weights (Img2Occ: with its chosen readout)
            self.val_metrics = {**self.val_metrics, **final}
        out: dict[str, float] = {k: v for k, v in window.last.items() if k == "train/loss"}
        out.update(self.val_metrics)
        out["step"] = float(self.step)
        out["epoch"] = float(self.epoch)
        out["stopped_early"] = float(stopped_early)
        if self.best.get("value") is not None:
            out[f"best/{self.best['metric']}"] = float(self.best["value"])
        return out

    def _announce(self) -> None:
        t, i = self.tcfg, self.info
        if i.is_main:
            log.info(
                f"training {self.stage.name} in {self.run_dir}: step {self.step}/"
                f"{self.total_steps}, {self.steps_per_epoch} steps/epoch, {i.world_size} rank(s) "
                f"on {i.device}, global batch {t.batch_size * t.grad_accum * i.world_size}, "
                f"precision {self.precision}"
            )

    def _epoch_batches(self) -> tuple[Any, int]:
        """An iterator over this epoch's remaining batches and how many steps they make."""
        tcfg = self.tcfg
        # Global position: a resume may even change the number of ranks or the batch size.
        self.sampler.set_epoch(self.epoch, start=self.samples_in_epoch)
        steps_left = len(self.sampler) // tcfg.batch_size // tcfg.grad_accum
        self.train_set.epoch = self.epoch
        loader = make_loader(
            self.train_set,
            self.sampler,
            batch_size=tcfg.batch_size,
            num_workers=tcfg.num_workers,
            collate_fn=self.stage.collate_fn(),
            drop_last=True,
            pin_memory=tcfg.pin_memory and self.info.device.type == "cuda",
            seed=self.seed,
        )
        return iter(loader), steps_left

    def _log_window(self, window: MetricWindow, norm, samples_per_step: int, logger, bar) -> None:
        """Reduce the window's sums over ranks, log their means and throughput, reset it."""
        stats = {f"{k}/sum": v for k, v in window.sums.items()}
        stats.update({f"{k}/count": torch.tensor(window.steps) for k in window.sums})
        reduced = all_reduce_sum(stats, self.info)
        last = {k: float(reduced[f"{k}/sum"] / reduced[f"{k}/count"]) for k in window.sums}
        dt = max(time.monotonic() - window.t0, 1e-9)
        last["train/samples_per_s"] = window.steps * samples_per_step / dt
        last["train/lr"] = self.scheduler.get_last_lr()[0]
        last["train/grad_norm"] = norm
        logger.log(last, self.step, self.epoch)
        bar.set_postfix(loss=f"{last['train/loss']:.4g}", sps=f"{last['train/samples_per_s']:.1f}")
        window.reset(last)

    def _validate_and_log(self, logger: MetricLogger) -> None:
        metrics = self.validate()
        logger.log(metrics, self.step, self.epoch)
        self._after_validation(metrics)

    def _write_schedule(self, stopped_early: bool) -> None:
        if stopped_early:
            log.warning(
                "time guard of %.3g min fired at step %d of %d: stopped and checkpointed; "
                "results are not those of the full schedule",
                self.tcfg.max_minutes,
                self.step,
                self.total_steps,
            )
        if self.info.is_main:
            write_schedule(
                self.run_dir, self.step, self.total_steps, stopped_early,
                self.tcfg.max_minutes, self.elapsed_s,
            )  # fmt: skip
