"""The arguments and evaluation of the benchmarks that score a trained world model on a split
with ``tools/eval.py``'s code (``pose_error_split.py``, ``checked_choice.py``)."""

from __future__ import annotations

import argparse
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def add_eval_args(ap: argparse.ArgumentParser, out: str) -> None:
    """The split and checkpoint arguments; ``out``: the default output folder."""
    ap.add_argument("--data-root", required=True)
    ap.add_argument("--version", default="v1.0-mini")
    ap.add_argument("--split", default="all", help="dataset.val_split (dev: all)")
    ap.add_argument("--tokenizer", required=True)
    ap.add_argument("--world-model", required=True)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=out)


def check_files(args: argparse.Namespace) -> None:
    """Exit naming ``--tokenizer`` / ``--world-model`` when the file is missing."""
    for name in ("tokenizer", "world_model"):
        if not Path(getattr(args, name)).is_file():
            raise SystemExit(f"--{name.replace('_', '-')}: no file {getattr(args, name)!r}")


def evaluate_world_model(args: argparse.Namespace, run_dir: Path, *extra: str) -> dict:
    """``tools/eval.py experiment=world_model_mini`` on the arguments' split and checkpoints,
    into ``run_dir``, with ``extra`` overrides; returns its metrics."""
    from hydra import compose, initialize_config_dir

    from renderworld.training import evaluate

    overrides = [
        "experiment=world_model_mini",
        f"dataset.data_root={Path(args.data_root).resolve()}",
        f"dataset.version={args.version}", f"dataset.val_split={args.split}",
        f"stage.tokenizer_ckpt={Path(args.tokenizer).resolve()}",
        f"ckpt={Path(args.world_model).resolve()}",
        f"trainer.num_threads={args.threads}", f"run_dir={Path(run_dir).resolve()}", *extra,
    ]  # fmt: skip
    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        cfg = compose("eval", overrides=overrides)
    return evaluate(cfg)
