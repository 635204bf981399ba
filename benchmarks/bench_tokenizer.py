"""Tokenizer cost: encode / decode milliseconds per frame and parameter counts.

Settings: the paper default (Occ3D 200x200x16 grid, 50x50 latent, 128 channels, 512 codes,
base 64 channels, 2 res-blocks, attention) and the coarse grid (50x50x4, 25x25 and 50x50
latents), for every variant. Times are medians over ``--reps`` runs after a warm-up, in
eval mode under ``torch.no_grad``, on the chosen device; the ratio column is against the
``plain`` variant of the same setting measured in the same run.

    PYTHONPATH=. python benchmarks/bench_tokenizer.py [--device cpu|cuda] [--reps 5] [--batch 1]
        [--threads N] [--variants plain,am_vae] [--settings coarse/25x25]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from renderworld.constants import FREE_ID, OCC3D_CLASSES
from renderworld.tokenizer import VARIANTS, TokenizerConfig, build_tokenizer

SETTINGS = {
    "occ3d/50x50 (paper)": dict(grid="occ3d", latent_shape=(50, 50)),
    "coarse/25x25": dict(grid="coarse", latent_shape=(25, 25)),
    "coarse/50x50": dict(grid="coarse", latent_shape=(50, 50)),
}


def _scene(shape, batch, device) -> torch.Tensor:
    """A plausible volume: ground plane of road, a few boxes of cars and buildings."""
    occ = torch.full((batch, *shape), FREE_ID, dtype=torch.uint8)
    x, y, z = shape
    occ[..., 0] = OCC3D_CLASSES.index("driveable_surface")
    occ[:, x // 4 : x // 4 + x // 10, y // 3 : y // 3 + y // 20, 1 : max(2, z // 4)] = 4
    occ[:, x // 2 :, : y // 5, 1:] = OCC3D_CLASSES.index("manmade")
    return occ.to(device)


def _time(fn, reps: int, device) -> float:
    fn()  # warm-up
    times = []
    for _ in range(reps):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--threads", type=int, default=0, help="CPU intra-op threads (0: torch's)")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--settings", default=",".join(SETTINGS))
    args = ap.parse_args()
    device = torch.device(args.device)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    print(
        f"device={device} threads={torch.get_num_threads()} batch={args.batch} "
        f"reps={args.reps} (medians, ms per frame)"
    )
    header = (
        f"{'setting':<22}{'variant':<10}{'params':>11}{'encode ms':>11}{'decode ms':>11}"
        f"{'enc ratio':>10}{'dec ratio':>10}{'peak MiB':>10}"
    )
    print(header)
    print("-" * len(header))
    for name in args.settings.split(","):
        s = SETTINGS[name]
        base = None
        for variant in args.variants.split(","):
            cfg = TokenizerConfig.for_grid(
                s["grid"], latent_shape=s["latent_shape"], variant=variant
            )
            model = build_tokenizer(cfg).to(device).eval()
            occ = _scene(cfg.grid_shape, args.batch, device)
            if device.type == "cuda":
                torch.cuda.reset_peak_memory_stats(device)
            with torch.no_grad():
                tokens = model.encode(occ)
                enc = _time(lambda m=model, o=occ: m.encode(o), args.reps, device) / args.batch
                dec = _time(lambda m=model, t=tokens: m.decode(t), args.reps, device) / args.batch
            peak = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else 0
            if base is None:
                base = (enc, dec)
            print(
                f"{name:<22}{variant:<10}{model.num_parameters():>11,}{enc:>11.2f}{dec:>11.2f}"
                f"{enc / base[0]:>10.2f}{dec / base[1]:>10.2f}{peak:>10.0f}"
            )


if __name__ == "__main__":
    main()
