"""Size and write time of scene recordings (``renderworld.viewer``), per layer set.

Writes one scene several ways and prints a table: keyframes, boxes / points / Gaussians
written, file size and wall time of ``write_scene_recording`` (models included). The datasets'
GT occupancy is the full Occ3D grid (200 x 200 x 16); the model layers use models of the main
job's sizes on the coarse grid (``experiment=*_mini``), untrained unless checkpoints are given
(their cost per keyframe is the same; the number of boxes they produce is not).

    python benchmarks/bench_viewer.py --data DIR [--scene scene-0103] [--out outputs/bench_viewer]
        [--infos-dir DIR] [--img2occ-ckpt P --tokenizer-ckpt P --world-model-ckpt P]

Needs the converter's infos for the model layers (tools/create_data.py data_root=DIR).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def untrained_models():
    """Img2Occ / tokenizer / planner of the main job's mini sizes, coarse grid, random weights."""
    import torch

    from renderworld.constants import GRIDS
    from renderworld.img2occ import Img2Occ, Img2OccConfig
    from renderworld.planning import Planner
    from renderworld.tokenizer import TokenizerConfig, build_tokenizer
    from renderworld.world import WorldModel, WorldModelConfig

    torch.manual_seed(0)
    img2occ = Img2Occ(
        Img2OccConfig(grid=GRIDS["coarse"], input_size=(128, 224), render_size=(56, 100),
                      encoder_channels=(16, 32, 64), feature_channels=32, head_channels=64,
                      head_blocks=1)
    ).eval()  # fmt: skip
    tok = build_tokenizer(
        TokenizerConfig(grid_shape=(50, 50, 4), latent_shape=(50, 50), latent_channels=64)
    ).eval()
    wm = WorldModel(
        WorldModelConfig(codebook_sizes=tuple(tok.cfg.codebook_sizes), token_grid=(50, 50))
    )
    return {"img2occ": img2occ, "tokenizer": tok, "planner": Planner(tok, wm)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="dataset root (nuScenes format)")
    parser.add_argument("--version", default="v1.0-mini")
    parser.add_argument("--scene", default=None, help="scene name (default: the first)")
    parser.add_argument("--infos-dir", default=None, help="converter infos (model layers)")
    parser.add_argument("--out", default="outputs/bench_viewer")
    parser.add_argument("--img2occ-ckpt")
    parser.add_argument("--tokenizer-ckpt")
    parser.add_argument("--world-model-ckpt")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1: comparable)")
    args = parser.parse_args()

    import numpy as np
    import torch

    from renderworld.constants import FREE_ID
    from renderworld.data import NuScenesReader
    from renderworld.viewer import DATA_LAYERS, LAYERS, write_scene_recording
    from renderworld.viewer.checkpoints import load_viewer_models

    torch.set_num_threads(args.threads)
    reader = NuScenesReader(args.data, args.version)
    scene = args.scene or reader.scene_names()[0]
    tokens = reader.scene_samples(scene)
    occ = [reader.occ3d(t) for t in tokens]
    shapes = {o.semantics.shape for o in occ if o is not None}
    frac = np.mean([(o.semantics != FREE_ID).mean() for o in occ if o is not None])
    print(f"scene {scene}: {len(tokens)} keyframes, GT grid {shapes}, {100 * frac:.1f} % occupied")
    if args.img2occ_ckpt or args.tokenizer_ckpt or args.world_model_ckpt:
        models = load_viewer_models(args.img2occ_ckpt, args.tokenizer_ckpt, args.world_model_ckpt)
        what = "checkpoints"
    else:
        models, what = untrained_models(), "untrained mini-size models"
    out = Path(args.out)
    runs = [
        ("data layers, voxels=surface", DATA_LAYERS, "surface", {}),
        ("data layers, voxels=all", DATA_LAYERS, "all", {}),
        (f"all layers ({what}), voxels=surface", LAYERS, "surface", models),
    ]
    rows = ["| recording | keyframes | GT boxes | LiDAR points | Gaussians | MiB | s |",
            "|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, layers, voxels, m in runs:
        s = write_scene_recording(
            args.data, out / f"{scene}_{len(rows)}.rrd", scene=scene, version=args.version,
            layers=layers, voxels=voxels, log=None, reader=reader, infos_dir=args.infos_dir, **m,
        )  # fmt: skip
        n = s.instances
        rows.append(
            f"| {name} | {s.frames} | {n.get('world/ego/occupancy/gt', 0)} | "
            f"{n.get('world/ego/lidar', 0)} | {n.get('world/ego/img2occ/gaussians', 0)} | "
            f"{s.bytes / 2**20:.1f} | {s.seconds:.1f} |"
        )
        print(rows[-1], flush=True)
    print("\n".join(rows))


if __name__ == "__main__":
    main()
