"""AM-VAE ablation (the paper's Table 6.6): four tokenizer variants at equal code budget.

Trains ``plain``, ``air_mask``, ``separate`` and ``am_vae`` with the main job's schedule
(``experiment=tokenizer_mini``: same steps / minutes budget, same data, same code budget K —
two-codebook variants split it K/2 + K/2), evaluates each on mini_val and prints and saves the
reconstruction table (mIoU over classes 0..16 and IoU, full volume, OccWorld protocol; and
inside the camera mask).

    python benchmarks/ablation_tokenizer.py [--data data/sim_mini] [--out outputs/ablation]
        [--reuse-am-vae outputs/demo/tokenizer] [--extra trainer.max_minutes=6 ...]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
VARIANTS = (
    ("plain", "plain VQ-VAE (one codebook)"),
    ("air_mask", "+ air mask only"),
    ("separate", "+ separate air / non-air codebooks only"),
    ("am_vae", "AM-VAE (both)"),
)


def run(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    print("$", " ".join(cmd), flush=True)
    subprocess.run(cmd, cwd=REPO, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO / "data" / "sim_mini")
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "ablation")
    ap.add_argument(
        "--reuse-am-vae",
        type=Path,
        default=None,
        help="an existing am_vae run dir (the main job's) to evaluate instead of training",
    )
    ap.add_argument("--extra", nargs="*", default=[], help="extra Hydra overrides for training")
    args = ap.parse_args()
    py = sys.executable
    rows = []
    for variant, label in VARIANTS:
        run_dir = args.out / variant
        ckpt = run_dir / "checkpoints" / "best.pt"
        train_s = None
        if variant == "am_vae" and args.reuse_am_vae:
            ckpt = args.reuse_am_vae / "checkpoints" / "best.pt"
        elif not ckpt.is_file():
            cmd = [py, "tools/train.py", "experiment=tokenizer_mini", f"run_dir={run_dir}"]
            cmd += [f"dataset.data_root={args.data}", f"stage.model.variant={variant}"]
            train_s = run([*cmd, "trainer.progress_bar=false", *args.extra])
        eval_dir = args.out / f"eval_{variant}"
        run([py, "tools/eval.py", "experiment=tokenizer_mini", f"dataset.data_root={args.data}",
             f"stage.model.variant={variant}", f"ckpt={ckpt}", f"run_dir={eval_dir}"])  # fmt: skip
        m = json.loads((eval_dir / "eval_metrics.json").read_text())
        rows.append((label, variant, m, train_s, m.get("step")))
    head = (
        "| variant | recon. mIoU (0..16, full volume) | IoU | mIoU (camera mask) "
        "| IoU (camera mask) | steps | train s |\n|---|---|---|---|---|---|---|"
    )
    lines = [head]
    for label, _, m, train_s, step in rows:
        lines.append(
            f"| {label} | {100 * m['val/miou']:.2f} | {100 * m['val/iou']:.2f} | "
            f"{100 * m['val/cam/miou']:.2f} | {100 * m['val/cam/iou']:.2f} | {step:.0f} | "
            f"{'reused' if train_s is None else f'{train_s:.0f}'} |"
        )
    table = "\n".join(lines)
    print("\nTokenizer ablation on mini_val (GT occupancy, coarse grid, equal code budget):\n")
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ablation.md").write_text(table + "\n")
    print(f"\nsaved {args.out / 'ablation.md'}")


if __name__ == "__main__":
    main()
