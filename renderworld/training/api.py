"""``train(cfg)`` and ``evaluate(cfg)``: what ``tools/train.py`` and ``tools/eval.py`` call.

Both take a composed Hydra config (from ``@hydra.main`` or ``hydra.compose``) and return a dict
of metrics, so they are testable without a subprocess. Neither writes into the run directory
before the checkpoint to resume from (and the model it fills) has been validated: a failed
resume leaves the run untouched.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

from renderworld.training.checkpoint import CheckpointError, check_state_dict_keys, load_checkpoint
from renderworld.training.config import (
    OptimizerConfig,
    SchedulerConfig,
    TrainerConfig,
    config_to_yaml,
    validate_group,
)
from renderworld.training.distributed import (
    DistInfo,
    broadcast_object,
    init_distributed,
    shutdown_distributed,
)
from renderworld.training.loggers import MetricLogger, truncate_metrics_csv
from renderworld.training.loop import Trainer
from renderworld.training.registry import Stage, get_stage
from renderworld.training.seed import seed_everything
from renderworld.training.validation import build_val_loader, effective_precision, run_validation

__all__ = ["train", "evaluate", "objective", "hydra_argv"]

log = logging.getLogger("renderworld.training")


def train(cfg: DictConfig) -> dict[str, float]:
    """Train the stage selected by ``cfg.stage`` and return its final metrics.

    Args:
        cfg: Composed config (``configs/train.yaml``): ``stage``, ``optimizer``, ``scheduler``,
            ``trainer``, ``seed``, ``run_dir``, ``resume``, ``init_from``.

    Returns:
        ``{"train/loss", "val/<metric>"..., "best/<monitor>", "step", "epoch",
        "stopped_early"}``.

    Raises:
        ValueError: invalid config, missing ``???`` key, a run directory that already holds
            a checkpoint without ``resume=true``.
        CheckpointError: ``resume=true`` with an unusable ``last.pt``; an ``init_from``
            checkpoint that is unusable, of another stage or of another architecture.
    """
    tcfg, ocfg, scfg = _validated_groups(cfg)
    _set_torch_flags(tcfg)
    info = init_distributed(tcfg.device)
    try:
        # The Trainer (its DDP reducer, its loaders) lives in _fit's frame only, so it is freed
        # before the group is torn down: a gloo work still referenced then aborts the process.
        return _fit(cfg, info, tcfg, ocfg, scfg)
    finally:
        shutdown_distributed(info)


def _fit(
    cfg: DictConfig,
    info: DistInfo,
    tcfg: TrainerConfig,
    ocfg: OptimizerConfig,
    scfg: SchedulerConfig,
) -> dict[str, float]:
    """:func:`train`'s body, inside the process group (validated trainer, optimizer and
    scheduler groups given)."""
    cfg, run_dir = _resolve(cfg, info)
    _quiet_other_ranks(info)
    stage_name = str(cfg.stage.name)
    last = run_dir / "checkpoints" / "last.pt"
    ckpt = None
    if cfg.get("resume", False):
        ckpt = load_checkpoint(last, expected_stage=stage_name, for_training=True)
    elif last.exists():
        raise ValueError(
            f"run_dir {str(run_dir)!r} already holds {last.name}: pass resume=true to "
            "continue it, or choose another run_dir"
        )
    init = _init_checkpoint(cfg, stage_name) if ckpt is None else None
    stage = _build_stage(cfg)
    yaml_text = config_to_yaml(cfg)
    trainer = Trainer(stage, cfg, run_dir, info, tcfg, ocfg, scfg, _seed(cfg), yaml_text)
    if ckpt is not None:
        trainer.load_state_dict(ckpt, source=f"checkpoint {str(last)!r}")
    elif init is not None:
        _init_weights(trainer, init, source=f"init_from {str(cfg.init_from)!r}")
        log.info("%s starts from the weights of %s", stage_name, cfg.init_from)
    # Only now, with everything validated, write into the run directory.
    if info.is_main:
        run_dir.mkdir(parents=True, exist_ok=True)
        if ckpt is None:
            (run_dir / "config.yaml").write_text(yaml_text)
        else:
            (run_dir / f"config.resume-step{trainer.step}.yaml").write_text(yaml_text)
            truncate_metrics_csv(run_dir / "metrics.csv", trainer.step)
            log.info("resuming %s from step %d (%s)", stage_name, trainer.step, last)
    logger = MetricLogger(run_dir, enabled=info.is_main, tensorboard=tcfg.tensorboard)
    try:
        metrics = trainer.fit(logger)
    finally:
        logger.close()
    if info.is_main:
        log.info("finished %s at step %d: %s", stage_name, trainer.step, metrics)
        _print_report(stage, metrics, run_dir)
    return metrics


def _init_checkpoint(cfg: DictConfig, stage_name: str) -> dict[str, Any] | None:
    """The checkpoint of ``init_from`` (None: unset), loaded and checked before anything runs.

    Raises:
        CheckpointError: an unusable file or one of another stage; the message names
            ``init_from``.
    """
    path = cfg.get("init_from")
    if not path:
        return None
    try:
        return load_checkpoint(Path(str(path)), expected_stage=stage_name)
    except CheckpointError as err:
        raise CheckpointError(f"init_from: {err}") from err


def _init_weights(trainer: Trainer, ckpt: dict[str, Any], source: str) -> None:
    """Fill a new run's model from a checkpoint's ``model`` entry (the average, where it was
    written with an EMA), strict on keys and shapes; restart the run's EMA, if any, there.
    Optimizer, schedule, step and data order start fresh, as in any new run."""
    check_state_dict_keys(trainer.model, ckpt["model"], source=source)
    trainer.model.load_state_dict(ckpt["model"], strict=True)
    if trainer.ema is not None:
        trainer.ema.load(ckpt["model"], None)


#: Top-level eval keys read by the world_model stage only (configs/eval.yaml).
_WORLD_MODEL_EVAL_KEYS = ("pseudo_labels", "camera_ckpt", "camera_tokenizer_ckpt")


def evaluate(cfg: DictConfig) -> dict[str, float]:
    """Evaluate checkpoint ``cfg.ckpt`` on the stage's validation set.

    The model is built by the stage from ``cfg.stage`` (the tokenizer, Img2Occ and world-model
    stages take the checkpoint's architecture) and filled strictly from the checkpoint, which
    must come from the same stage. Rank 0 writes ``eval_metrics.json`` into ``cfg.run_dir``.

    Returns:
        ``{"val/<metric>": value, ..., "step": checkpoint step}``.

    Raises:
        ValueError: invalid config, missing ``ckpt``, a stage without a validation set.
        CheckpointError: unusable checkpoint or one that does not match the model.
    """
    tcfg = validate_group(cfg.get("trainer"), TrainerConfig, "trainer")
    _set_torch_flags(tcfg)
    info = init_distributed(tcfg.device)
    try:
        cfg, run_dir = _resolve(cfg, info)
        _quiet_other_ranks(info)
        ckpt_path = Path(str(cfg.ckpt))
        ckpt = load_checkpoint(ckpt_path, expected_stage=str(cfg.stage.name))
        stage = _build_stage(cfg)
        for key in _WORLD_MODEL_EVAL_KEYS:
            if cfg.get(key) and stage.name != "world_model":
                raise ValueError(
                    f"{key}: only stage=world_model reads it (the Camera setting); "
                    f"stage {stage.name!r} does not, remove {key}={cfg.get(key)}"
                )
        seed_everything(_seed(cfg))
        val_set = stage.build_val_dataset(cfg)
        if val_set is None:
            raise ValueError(f"stage {stage.name!r}: build_datasets returned no validation set")
        model = stage.build_model(cfg)
        check_state_dict_keys(model, ckpt["model"], source=f"checkpoint {str(ckpt_path)!r}")
        model.load_state_dict(ckpt["model"], strict=True)
        model.to(info.device)
        stage.on_eval_start(model)
        loader = build_val_loader(stage, val_set, tcfg, info, _seed(cfg))
        precision = effective_precision(tcfg.precision, info.device)
        metrics = run_validation(stage, model, loader, info, precision, tcfg.progress_bar)
        metrics["step"] = float(ckpt["step"])
        if info.is_main:
            run_dir.mkdir(parents=True, exist_ok=True)
            (run_dir / "config.yaml").write_text(config_to_yaml(cfg))
            out = {"checkpoint": str(ckpt_path.resolve()), "stage": stage.name, **metrics}
            (run_dir / "eval_metrics.json").write_text(json.dumps(out, indent=2) + "\n")
            log.info("evaluated %s: %s", ckpt_path, metrics)
            stage.on_eval_end(model, dict(metrics), str(run_dir))
            _print_report(stage, metrics, run_dir)
        return metrics
    finally:
        shutdown_distributed(info)


def objective(cfg: DictConfig, metrics: dict[str, float]) -> float | None:
    """The value a hyper-parameter sweeper optimises: ``metrics[cfg.optimized_metric]``.

    Returns None when ``optimized_metric`` is unset.

    Raises:
        ValueError: the metric is not among ``metrics``.
    """
    name = cfg.get("optimized_metric")
    if not name:
        return None
    if name not in metrics:
        raise ValueError(f"optimized_metric: {name!r} not in the run's metrics {sorted(metrics)}")
    return float(metrics[name])


def hydra_argv(argv: list[str], env: dict[str, str] | None = None) -> list[str]:
    """Adjust a tool's command line before Hydra parses it.

    * ``run_dir=X`` also sets ``hydra.run.dir=X``, so Hydra's own record of the invocation
      (``.hydra/<time>/``, the log file) lands in the run it belongs to.
    * Under torchrun, ranks other than 0 write nothing of Hydra's: rank 0's run directory is
      shared with them by the training code.
    """
    env = dict(os.environ) if env is None else env
    args = list(argv)
    overrides = [a for a in args[1:] if "=" in a and not a.startswith("-")]
    keys = {a.split("=", 1)[0].lstrip("+~") for a in overrides}
    run_dir = next((a.split("=", 1)[1] for a in overrides if a.startswith("run_dir=")), None)
    if int(env.get("RANK", "0")) != 0:
        args = [a for a in args if not a.startswith("hydra.run.dir=")]
        args += ["hydra.run.dir=.", "hydra.output_subdir=null", "hydra/job_logging=stdout"]
    elif run_dir is not None and "hydra.run.dir" not in keys:
        args.append(f"hydra.run.dir={run_dir}")
    return args


# ---------------------------------------------------------------------- helpers
def _validated_groups(cfg: Any) -> tuple[TrainerConfig, OptimizerConfig, SchedulerConfig]:
    if not isinstance(cfg, (DictConfig, dict)):
        raise TypeError(f"cfg: expected a DictConfig, got {type(cfg).__name__}")
    return (
        validate_group(cfg.get("trainer"), TrainerConfig, "trainer"),
        validate_group(cfg.get("optimizer"), OptimizerConfig, "optimizer"),
        validate_group(cfg.get("scheduler"), SchedulerConfig, "scheduler"),
    )


def _set_torch_flags(tcfg: TrainerConfig) -> None:
    if tcfg.num_threads:
        torch.set_num_threads(tcfg.num_threads)
    if tcfg.deterministic:
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True)


def _resolve(cfg: Any, info: DistInfo) -> tuple[DictConfig, Path]:
    """A fully resolved copy of ``cfg`` with an absolute ``run_dir`` shared by all ranks."""
    c = OmegaConf.create(OmegaConf.to_container(OmegaConf.create(cfg), resolve=False))
    try:
        run_dir = c.get("run_dir")
    except OmegaConfBaseException as err:
        raise ValueError(
            "run_dir: cannot be resolved outside a Hydra app "
            f"({str(err).splitlines()[0]}); pass run_dir=PATH"
        ) from None
    if not run_dir:
        raise ValueError(f"run_dir: expected a directory path, got {run_dir!r}")
    run_dir = broadcast_object(str(Path(str(run_dir)).resolve()), info)
    c.run_dir = run_dir
    try:
        resolved = OmegaConf.to_container(c, resolve=True, throw_on_missing=True)
    except MissingMandatoryValue as err:
        key = getattr(err, "full_key", "?")
        raise ValueError(
            f"{key}: required config value is missing (???); set it on the command line, "
            f"e.g. {key}=..."
        ) from None
    except OmegaConfBaseException as err:
        raise ValueError(f"config cannot be resolved: {str(err).splitlines()[0]}") from None
    out = OmegaConf.create(resolved)
    OmegaConf.set_struct(out, True)
    if "stage" not in out or "name" not in out.stage:
        raise ValueError("stage: no stage selected; pass stage=<name> (see configs/README.md)")
    return out, Path(run_dir)


def _seed(cfg: DictConfig) -> int:
    seed = cfg.get("seed")
    if not isinstance(seed, int) or isinstance(seed, bool) or not 0 <= seed < 2**31:
        raise ValueError(f"seed: expected an int in [0, 2**31), got {seed!r}")
    return seed


def _build_stage(cfg: DictConfig) -> Stage:
    module = cfg.stage.get("_target_module_")
    cls = get_stage(str(cfg.stage.name), str(module) if module else None)
    return cls(cfg)


def _print_report(stage: Stage, metrics: dict[str, float], run_dir: Path) -> None:
    """The stage's optional report (``Stage.write_report``), printed for the user."""
    report = stage.write_report(metrics, str(run_dir))
    if report:
        print(report, flush=True)


def _quiet_other_ranks(info: DistInfo) -> None:
    if not info.is_main:
        log.setLevel(logging.WARNING)
