"""Export Img2Occ pseudo labels (Occ3D layout) from a trained checkpoint.

    python tools/export_occ.py ckpt=PATH data_root=DIR [version=v1.0-mini] [out=DIR]
        [split=all|train|val] [device=auto] [batch_size=1] [threads=N]

Writes ``<out>/gts/<scene>/<sample_token>/labels.npz`` for every keyframe of the chosen splits
and ``<out>/export_info.json``; train the tokenizer on them with ``stage.occ_root=<out>``.
Thin Hydra wrapper around
:func:`renderworld.training.stages.img2occ.export.export_pseudo_labels` (configs/export_occ.yaml).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a clone without install

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from renderworld.training.stages.img2occ.export import export_pseudo_labels  # noqa: E402


@hydra.main(config_path="../configs", config_name="export_occ", version_base=None)
def main(cfg: DictConfig) -> dict:
    """Run the export and print its summary; returns the files written per split."""
    if cfg.get("threads"):
        import torch

        torch.set_num_threads(int(cfg.threads))
    summary = export_pseudo_labels(
        ckpt=cfg.ckpt,
        data_root=cfg.data_root,
        version=str(cfg.version),
        out=cfg.out,
        split=str(cfg.split),
        infos_dir=cfg.infos_dir,
        batch_size=int(cfg.batch_size),
        num_workers=int(cfg.num_workers),
        device=str(cfg.device),
        progress=bool(cfg.progress),
    )
    print(summary, flush=True)
    return dict(summary.files_per_split)


if __name__ == "__main__":
    main()
