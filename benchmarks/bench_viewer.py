"""Size and write time of scene recordings (``renderworld.viewer``), per layer set.

Writes one scene several ways and prints a table: keyframes, boxes / points / Gaussians
written, file size and median wall time of ``write_scene_recording`` over ``--repeat`` writes
(models included). The datasets'
GT occupancy is the full Occ3D grid (200 x 200 x 16); the model layers use models of the main
job's sizes on the coarse grid (``experiment=*_mini``), untrained unless checkpoints are given
(their cost per keyframe is the same; the number of boxes they produce is not).

    python benchmarks/bench_viewer.py --data DIR [--scene scene-0103] [--out outputs/bench_viewer]
        [--infos-dir DIR] [--img2occ-ckpt P --tokenizer-ckpt P --world-model-ckpt P]

Needs the converter's infos for the model layers (tools/create_data.py data_root=DIR).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
VOXEL_ENTITIES = (
    "world/ego/occupancy/gt",
    "world/ego/img2occ/occupancy",
    "world/ego/tokenizer/reconstruction",
)


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


def full_grid_stand_in(reader, scene: str, path: Path, surface: bool) -> tuple:
    """Every voxel layer at the full Occ3D grid: per keyframe the GT volume stands in for the
    Img2Occ read-out, the tokenizer reconstruction and the six forecasts (9 volumes of a
    realistic occupied fraction), plus one Gaussian per occupied voxel. Returns (bytes,
    seconds, boxes written, Gaussians written)."""
    import time

    import numpy as np
    import rerun as rr

    from renderworld.constants import FREE_ID, NUM_SEMANTIC_CLASSES
    from renderworld.viewer import data_layers as dl
    from renderworld.viewer._rerun import transform
    from renderworld.viewer.model_layers import forecast_entity
    from renderworld.viewer.scene import scene_frames
    from renderworld.viewer.voxels import gaussian_arrays, grid_for_shape, occupancy_boxes

    t0 = time.perf_counter()
    frames = scene_frames(reader, scene)
    rec = rr.RecordingStream("renderworld_bench")
    rec.save(path)
    dl.log_static(rec, rr)
    boxes = gaussians = 0
    entities = ["world/ego/occupancy/gt", "world/ego/img2occ/occupancy",
                "world/ego/tokenizer/reconstruction"]  # fmt: skip
    entities += [forecast_entity(k) for k in range(1, 7)]
    for i in range(len(frames)):
        rec.set_time("frame", sequence=i)
        rec.log("world/ego", transform(rr, frames.ego_to_world[i]))
        occ = reader.occ3d(frames.sample_tokens[i]).semantics
        for entity in entities:
            boxes += dl.log_voxels(rec, rr, entity, occ, surface_only=surface)
        grid = grid_for_shape(occ.shape)
        occupied = np.flatnonzero(occ != FREE_ID)
        centres = occupancy_boxes(occ, grid).centres
        n = len(occupied)
        logits = np.zeros((n, NUM_SEMANTIC_CLASSES), np.float32)
        logits[np.arange(n), occ.reshape(-1)[occupied]] = 1.0
        quats = np.tile(np.float32([1, 0, 0, 0]), (n, 1))
        g = gaussian_arrays(centres, quats, np.full((n, 3), 0.2, np.float32),
                            np.full(n, 0.8, np.float32), logits)  # fmt: skip
        gaussians += len(g["centres"])
        rec.log(
            "world/ego/img2occ/gaussians",
            rr.GaussianSplats3D(
                g["centres"], scales=g["scales"], quaternions=g["quats_xyzw"], colors=g["rgba"]
            ),
        )
    rec.flush()
    rec.disconnect()
    return path.stat().st_size, time.perf_counter() - t0, boxes, gaussians


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
    parser.add_argument("--repeat", type=int, default=3, help="writes per row (median time)")
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
    rows = ["| recording | keyframes | voxel boxes | LiDAR points | Gaussians | MiB | s |",
            "|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, layers, voxels, m in runs:
        times = []
        for _ in range(args.repeat):
            s = write_scene_recording(
                args.data, out / f"{scene}_{len(rows)}.rrd", scene=scene, version=args.version,
                layers=layers, voxels=voxels, log=None, reader=reader, infos_dir=args.infos_dir,
                **m,
            )  # fmt: skip
            times.append(s.seconds)
        n = s.instances
        voxel_boxes = sum(v for k, v in n.items() if k in VOXEL_ENTITIES or "forecast/" in k)
        rows.append(
            f"| {name} | {s.frames} | {voxel_boxes} | "
            f"{n.get('world/ego/lidar', 0)} | {n.get('world/ego/img2occ/gaussians', 0)} | "
            f"{s.bytes / 2**20:.1f} | {statistics.median(times):.1f} |"
        )
        print(rows[-1], flush=True)
    for voxels in ("surface", "all"):
        times = []
        for _ in range(args.repeat):
            size, secs, boxes, gaussians = full_grid_stand_in(
                reader, scene, out / f"{scene}_full_{voxels}.rrd", voxels == "surface"
            )
            times.append(secs)
        secs = statistics.median(times)
        rows.append(
            f"| full grid, 9 voxel layers (GT stands in for the models) + Gaussians, "
            f"voxels={voxels} | {len(tokens)} | {boxes} | - | {gaussians} | {size / 2**20:.1f} | "
            f"{secs:.1f} |"
        )
        print(rows[-1], flush=True)
    print(f"median of {args.repeat} writes per row; torch threads {args.threads}")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
