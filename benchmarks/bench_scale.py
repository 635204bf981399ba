"""Paper-scale training steps of every stage: step time and peak memory at the Occ3D grid.

Each stage's paper experiment (``configs/experiment/paper_<stage>.yaml``: Img2Occ with 640k
voxel-anchored Gaussians, 6 cameras at 256x704, 3 views rendered at 225x400; the AM-VAE with a
50x50x128 latent and 512 codes; the world model on its 50x50 tokens, 5 + 6 frames) runs in a
fresh subprocess on real batches of a converted dataset (the full-grid simulated preset,
``configs/sim/preset/full.yaml``, or real nuScenes). One step = the trainer's step: the
stage's loss under the precision's autocast, backward, AdamW. Reported: median wall time of
``--repeats`` steps after one warm-up step (the world model's codes are then cached, as from
its second epoch on), and peak memory: ``ru_maxrss`` growth over the process after building
the model and loading the batches (CPU), or ``torch.cuda.max_memory_allocated`` (CUDA).

Usage (the dataset converted with create_data.py; see configs/sim/preset/full.yaml):
    PYTHONPATH=. python benchmarks/bench_scale.py --data-root data/sim_full \\
        [--stages img2occ,tokenizer,world_model] [--device cpu] [--precision 32] \\
        [--threads 2] [--repeats 3] [--batch-size N] [--override key=value ...]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
STAGES = ("img2occ", "tokenizer", "world_model")


def _compose(stage: str, args, run_dir: Path, extra: list[str]):
    from hydra import compose, initialize_config_dir

    overrides = [
        f"experiment=paper_{stage}",
        f"dataset.data_root={args.data_root}",
        f"trainer.device={args.device}",
        f"trainer.precision={args.precision}",
        "trainer.num_workers=0",
        "trainer.pin_memory=false",
        f"run_dir={run_dir}",
        *([f"stage.infos_dir={args.infos_dir}"] if args.infos_dir else []),
        *([f"trainer.batch_size={args.batch_size}"] if args.batch_size else []),
        *extra,
        *args.override,
    ]
    with initialize_config_dir(str(REPO / "configs"), version_base="1.3"):
        return compose("train", overrides=overrides)


def _tokenizer_checkpoint(args, run_dir: Path) -> Path:
    """A paper tokenizer (initial weights) saved as a ``tokenizer`` checkpoint for the WM."""
    from omegaconf import OmegaConf

    from renderworld.training.checkpoint import save_checkpoint
    from renderworld.training.stages.tokenizer import TokenizerStage

    cfg = _compose("tokenizer", args, run_dir / "tok", [])
    model = TokenizerStage(cfg).build_model(cfg)
    path = run_dir / "tokenizer.pt"
    state = {
        "schema_version": 1,
        "stage": "tokenizer",
        "step": 0,
        "epoch": 0,
        "config": OmegaConf.to_yaml(cfg, resolve=True),
        "model": model.state_dict(),
    }
    save_checkpoint(state, path)
    return path


def run_one(args) -> dict:
    """One stage's steps, in this (fresh) process."""
    import torch
    from steptime import time_steps
    from torch.utils.data import DataLoader

    from renderworld.training.registry import get_stage
    from renderworld.training.validation import autocast_context

    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    run_dir = Path(tempfile.mkdtemp(prefix="bench_scale_"))
    extra = []
    if args.stage == "world_model":
        extra.append(f"stage.tokenizer_ckpt={_tokenizer_checkpoint(args, run_dir)}")
    cfg = _compose(args.stage, args, run_dir, extra)
    stage = get_stage(args.stage, cfg.stage.get("_target_module_"))(cfg)
    train_set, _ = stage.build_datasets(cfg)
    model = stage.build_model(cfg).to(device).train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-6)
    bs = int(cfg.trainer.batch_size)
    loader = DataLoader(train_set, batch_size=bs, shuffle=False, collate_fn=stage.collate_fn())
    batches = []
    for b in loader:
        batches.append(stage.transfer_batch(b, device))
        if len(batches) == args.repeats:
            break

    def step(batch) -> None:
        opt.zero_grad(set_to_none=True)
        with autocast_context(args.precision, device):
            loss, _ = stage.loss(model, batch)
        loss.backward()
        opt.step()
        if device.type == "cuda":
            torch.cuda.synchronize()

    timing = time_steps(lambda i: step(batches[i % len(batches)]), args.repeats, device)
    return {
        "stage": args.stage,
        "experiment": f"paper_{args.stage}",
        "grid": list(cfg.grid.shape),
        "batch_size": bs,
        "params": sum(p.numel() for p in model.parameters()),
        "first_step_s": timing.first_s,
        "step_s": timing.step_s,
        "peak_mb": timing.peak_mb,
        "device": args.device,
        "precision": args.precision,
        "threads": args.threads,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data-root", required=True, help="converted dataset (v1.0-trainval layout)")
    p.add_argument("--infos-dir", default=None, help="default <data-root>/renderworld_infos/...")
    p.add_argument("--stages", default=",".join(STAGES))
    p.add_argument("--device", default="cpu")
    p.add_argument("--precision", default="32", choices=("32", "bf16", "fp16"))
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--batch-size", type=int, default=0, help="0: the experiment's")
    p.add_argument("--override", action="append", default=[], help="extra Hydra override")
    p.add_argument("--timeout", type=int, default=3600)
    p.add_argument("--stage", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.stage:
        print(json.dumps(run_one(args)))
        return
    from steptime import run_point

    rows = []
    for stage in args.stages.split(","):
        if stage not in STAGES:
            raise SystemExit(f"--stages: unknown stage {stage!r}; expected some of {STAGES}")
        cmd = [sys.executable, __file__, "--stage", stage, "--data-root", args.data_root]
        cmd += ["--device", args.device, "--precision", args.precision]
        cmd += ["--threads", str(args.threads), "--repeats", str(args.repeats)]
        cmd += ["--batch-size", str(args.batch_size)]
        cmd += [f"--override={o}" for o in args.override]
        if args.infos_dir:
            cmd += ["--infos-dir", args.infos_dir]
        row = run_point(cmd, stage, args.timeout, (str(REPO),))
        if row is not None:
            rows.append(row)
    print(
        f"\nPaper-scale training steps (experiment=paper_<stage>), data {args.data_root}, "
        f"device {args.device}, precision {args.precision}, {args.threads} threads"
    )
    print(f"{'stage':12} {'batch':>5} {'params':>10} {'first s':>8} {'step s':>8} {'peak MB':>9}")
    for r in rows:
        print(
            f"{r['stage']:12} {r['batch_size']:>5} {r['params']:>10,} {r['first_step_s']:>8.2f} "
            f"{r['step_s']:>8.2f} {r['peak_mb']:>9.0f}"
        )


if __name__ == "__main__":
    main()
