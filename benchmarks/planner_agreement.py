"""The bundled planner against the ``world_model`` stage's own evaluation, on a run's val split.

    PYTHONPATH=. python benchmarks/planner_agreement.py \\
        --world-model outputs/demo/world_model/checkpoints/best.pt \\
        --tokenizer outputs/demo/tokenizer/checkpoints/best.pt [--data-root DIR] [--fast 0|1]

Bundles the two checkpoints (``export_planner_bundle``), loads the bundle with
``load_planner``, and for every val window of the run's config compares ``plan_batch`` on
requests built from the window's **history only** (occupancy, ``history_poses``, command) with
the stage's ``forecast`` (the evaluation's ``model`` row): trajectories and forecast voxels.
Prints how many trajectories are bit-equal, the largest difference and the share of equal
voxels. Either forecaster (``tokens`` or ``pose_warp``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omegaconf import OmegaConf  # noqa: E402
from torch.utils.data import DataLoader  # noqa: E402

from renderworld.constants import COMMANDS  # noqa: E402
from renderworld.planning import PlanRequest, load_planner  # noqa: E402
from renderworld.training.checkpoint import load_checkpoint  # noqa: E402
from renderworld.training.stages.world_model import WorldModelStage, export_planner_bundle  # noqa: E402


def requests(batch: dict, history: int) -> list[PlanRequest]:
    """One request per window from its history frames, poses and command."""
    poses = batch["history_poses"].double().numpy()
    return [
        PlanRequest(batch["occ"][i, :history].numpy(), np.diff(poses[i, :, :2], axis=0),
                    COMMANDS[int(batch["command"][i])], ego_yaws=poses[i, :, 2])
        for i in range(len(poses))
    ]  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world-model", type=Path, required=True)
    ap.add_argument("--tokenizer", type=Path, required=True)
    ap.add_argument("--data-root", default=None, help="override the run's dataset.data_root")
    ap.add_argument("--fast", type=int, choices=(0, 1), default=1, help="planner codec")
    ap.add_argument("--batch-size", type=int, default=4)
    args = ap.parse_args()
    torch.set_num_threads(1)
    ckpt = load_checkpoint(args.world_model, expected_stage="world_model")
    cfg = OmegaConf.create(ckpt["config"])
    if args.data_root:
        cfg.dataset.data_root = args.data_root
    with tempfile.TemporaryDirectory() as tmp:
        cfg.run_dir = tmp
        stage = WorldModelStage(cfg)
        _, val = stage.build_datasets(cfg)
        model = stage.build_model(cfg)
        model.load_state_dict(ckpt["model"], strict=True)
        model.eval()
        bundle = export_planner_bundle(args.world_model, args.tokenizer, Path(tmp) / "p.pt")
        planner = load_planner(bundle, fast=bool(args.fast))
        h = stage.settings.history
        same_traj, worst, same_vox, voxels = 0, 0.0, 0, 0
        for batch in DataLoader(val, batch_size=args.batch_size):
            with torch.no_grad():
                fc, traj = stage.forecast(model, batch, stage.eval_settings[0], None)
            for i, r in enumerate(planner.plan_batch(requests(batch, h))):
                want = traj["model"][i].numpy()
                same_traj += int(np.array_equal(r.trajectory, want))
                worst = max(worst, float(np.abs(r.trajectory - want).max()))
                same_vox += int((r.occupancy_forecast == fc["model"][i].numpy()).sum())
                voxels += r.occupancy_forecast.size
    print(
        f"{args.world_model} ({planner.kind}, fast={bool(args.fast)}): {len(val)} val windows; "
        f"trajectories bit-equal {same_traj}/{len(val)}, max |planner - stage| {worst:.2e} m; "
        f"forecast voxels equal {same_vox}/{voxels} = {same_vox / max(voxels, 1):.6f}"
    )


if __name__ == "__main__":
    main()
