"""Convert a nuScenes-format dataset into RenderWorld infos and LiDAR-projected 2-D labels.

    python tools/create_data.py data_root=data/nuscenes version=v1.0-mini [out=DIR]
        [label_scale=0.25 | label_size=[225,400]] [sweeps=0] [multiframe=0] [overwrite=true]

Thin Hydra wrapper around :func:`data_converters.create_data` (configs/create_data.yaml). A
malformed dataset (or ``labels=true`` on an occupancy-only one) exits with status 1 and the
error naming the file on stderr.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a clone without install

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from data_converters import ConvertOptions, create_data  # noqa: E402
from renderworld.data import DatasetError  # noqa: E402


@hydra.main(config_path="../configs", config_name="create_data", version_base=None)
def main(cfg: DictConfig) -> dict:
    """Run the conversion and print its summary; returns the summary as a dict."""
    label_size = cfg.label_size
    options = ConvertOptions(
        label_scale=None if label_size is not None else float(cfg.label_scale),
        label_size=None if label_size is None else tuple(OmegaConf.to_container(label_size)),
        sweeps=int(cfg.sweeps),
        multiframe=int(cfg.multiframe),
        min_depth=float(cfg.min_depth),
        labels=bool(cfg.labels),
        strict_splits=bool(cfg.strict_splits),
        overwrite=bool(cfg.overwrite),
        workers=int(cfg.workers),
        progress=bool(cfg.progress),
    )
    try:
        summary = create_data(cfg.data_root, cfg.version, cfg.out, options)
    except DatasetError as exc:  # a malformed or unsuitable dataset: its message, no traceback
        print(f"create_data: error: {exc}", file=sys.stderr, flush=True)
        raise SystemExit(1) from None
    print(summary, flush=True)
    return {
        "out_dir": str(summary.out_dir),
        "samples_per_split": summary.samples_per_split,
        "commands": summary.commands,
    }


if __name__ == "__main__":
    main()
