"""Time the world model's joint training step, against another checkout measured in the same run.

Usage::

    PYTHONPATH=. python benchmarks/bench_world_model_step.py \
        --data-root data/sim_mini --tokenizer-ckpt outputs/demo/tokenizer/checkpoints/last.pt \
        [--reference-tree /tmp/older] [--rounds 3] [--steps 7] [--threads 1]

One step = the stage's loss on a fixed batch of four training windows of ``experiment=
world_model_mini`` (pose-warp forecaster, learned movers; the frozen tokenizer's codes cached
after the first call, as from the second epoch of a training on), its backward and an AdamW
update. Each round runs this tree and then ``--reference-tree`` (e.g. ``git worktree add
/tmp/older <commit>``) in fresh processes, alternately, so both see the same load; the table
gives each tree's median over its rounds' median steps, and the ratio.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]

_CHILD = """
import json, statistics, sys, time
sys.path.insert(0, {tree!r})
import torch
from hydra import compose, initialize_config_dir
from torch.utils.data import default_collate
from renderworld.training.registry import get_stage
torch.set_num_threads({threads}); torch.manual_seed(0)
with initialize_config_dir({tree!r} + "/configs", version_base="1.3"):
    cfg = compose("train", overrides=["experiment=world_model_mini", "run_dir=/tmp/bench_wm_step",
        "dataset.data_root=" + {data!r}, "stage.tokenizer_ckpt=" + {tok!r},
        "stage.mover_fit_steps=1", "stage.pose_warmup_steps=0"])
stage = get_stage("world_model", cfg.stage.get("_target_module_"))(cfg)
train, _ = stage.build_datasets(cfg)
model = stage.build_model(cfg).train()
opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
items = [train[i * (len(train) - 1) // 3] for i in range(4)]
batch = stage.transfer_batch((stage.collate_fn() or default_collate)(items), torch.device("cpu"))
def step():
    loss, _ = stage.loss(model, batch)
    opt.zero_grad(); loss.backward(); opt.step()
step(); step()
times = []
for _ in range({steps}):
    t = time.perf_counter(); step(); times.append(time.perf_counter() - t)
print("RESULT", json.dumps({{"median_s": statistics.median(times)}}))
"""


def _point(tree: Path, args: argparse.Namespace) -> float:
    code = _CHILD.format(
        tree=str(tree), threads=args.threads, steps=args.steps, data=str(args.data_root),
        tok=str(args.tokenizer_ckpt),
    )  # fmt: skip
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode or not lines:
        raise SystemExit(f"{tree}: the step failed\n{proc.stderr[-3000:]}")
    return json.loads(lines[-1][7:])["median_s"]


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data-root", type=Path, default=Path("data/sim_mini"))
    p.add_argument("--tokenizer-ckpt", type=Path,
                   default=Path("outputs/demo/tokenizer/checkpoints/last.pt"))  # fmt: skip
    p.add_argument("--reference-tree", type=Path, help="another checkout of the package")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--steps", type=int, default=7, help="timed steps per process")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    for name in ("data_root", "tokenizer_ckpt"):
        if not getattr(args, name).exists():
            p.error(f"--{name.replace('_', '-')}: {getattr(args, name)} does not exist")
    if args.reference_tree and not (args.reference_tree / "renderworld").is_dir():
        p.error(f"--reference-tree: no renderworld/ package in {args.reference_tree}")
    trees = {"this tree": HERE}
    if args.reference_tree:
        trees["reference"] = args.reference_tree.resolve()
    got: dict[str, list[float]] = {k: [] for k in trees}
    for r in range(args.rounds):
        for name, tree in trees.items():
            got[name].append(_point(tree, args))
            print(f"round {r + 1}/{args.rounds} {name}: {got[name][-1]:.3f} s a step", flush=True)
    print(f"\n| tree | step (s), median of {args.rounds} rounds | rounds |\n|---|---:|---|")
    for name, tree in trees.items():
        row = ", ".join(f"{x:.3f}" for x in got[name])
        print(f"| {name} ({tree}) | {statistics.median(got[name]):.3f} | {row} |")
    if args.reference_tree:
        ratio = statistics.median(got["this tree"]) / statistics.median(got["reference"])
        print(f"\nthis tree / reference: {ratio:.2f}")


if __name__ == "__main__":
    main()
