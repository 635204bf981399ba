"""Write a Rerun recording of one scene and say how to open it.

    python tools/view.py data_root=DIR [scene=NAME] [out=scene.rrd] [img2occ_ckpt=PATH]
        [tokenizer_ckpt=PATH] [world_model_ckpt=PATH | planner_bundle=PATH] [layers=[...]]

Needs the optional extra (``pip install -e '.[viz]'``). Open the file with ``rerun FILE`` or
``rerun --web-viewer FILE``. Thin Hydra wrapper (configs/view.yaml) around
:func:`renderworld.viewer.write_scene_recording`.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a clone without install

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402


@hydra.main(config_path="../configs", config_name="view", version_base=None)
def main(cfg: DictConfig) -> dict:
    """Load the given checkpoints, write the recording, print its summary."""
    from renderworld.viewer import rerun_available, write_scene_recording
    from renderworld.viewer._rerun import INSTALL_HINT
    from renderworld.viewer.checkpoints import load_viewer_models
    from renderworld.viewer.job import split_scene

    if not rerun_available():
        sys.exit(f"tools/view.py needs rerun-sdk: {INSTALL_HINT}")
    models = load_viewer_models(
        img2occ_ckpt=cfg.img2occ_ckpt,
        tokenizer_ckpt=cfg.tokenizer_ckpt,
        world_model_ckpt=cfg.world_model_ckpt,
        planner_bundle=cfg.planner_bundle,
        device=str(cfg.device),
    )
    scene = cfg.scene
    if scene is None and cfg.split is not None:
        infos_dir = cfg.infos_dir or Path(cfg.data_root) / "renderworld_infos" / str(cfg.version)
        scene = split_scene(infos_dir, str(cfg.split))
        if scene is None:
            sys.exit(f"split={cfg.split}: no infos_{cfg.split}.parquet with a scene in {infos_dir}")
    out = cfg.out or f"{scene or 'scene'}.rrd"
    summary = write_scene_recording(
        cfg.data_root,
        out,
        scene=scene,
        version=str(cfg.version),
        infos_dir=cfg.infos_dir,
        layers=list(OmegaConf.to_container(cfg.layers)),
        start=int(cfg.start),
        max_frames=None if cfg.max_frames is None else int(cfg.max_frames),
        occ_mask=str(cfg.occ_mask),
        voxels=str(cfg.voxels),
        gaussians=str(cfg.gaussians),
        min_opacity=float(cfg.min_opacity),
        forecast_steps=None if cfg.forecast_steps is None else int(cfg.forecast_steps),
        occ_root=cfg.occ_root,
        device=str(cfg.device),
        log=lambda m: None if m.startswith("viewer: keyframe") else print(m, flush=True),
        reasons=models.reasons,
        first_view=str(cfg.first_view),
        **models,
    )
    print(f"wrote {summary.describe()}")
    print(f"open it with: rerun {summary.path}  (browser: rerun --web-viewer {summary.path})")
    return summary.instances


if __name__ == "__main__":
    main()
