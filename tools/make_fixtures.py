"""Generate simulated nuScenes-format fixtures (Hydra entry point).

    python tools/make_fixtures.py out=DIR preset=tiny|mini [seed=..] [num_scenes=..]
        [keyframes=..] [image_size=WxH] [overwrite=true] [mode=full|occupancy]

The config lives in ``configs/sim`` (``config.yaml`` + ``preset/<name>.yaml``); the library
(:mod:`renderworld.sim`) receives plain dataclasses and never imports Hydra.
:func:`config_from_preset` builds the same :class:`SimConfig` without Hydra (used by tests).
"""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from renderworld.sim import SimConfig, simulate  # noqa: E402

CONFIG_DIR = REPO / "configs" / "sim"
_RUN_KEYS = ("out", "overwrite", "progress", "preset")


def config_from_preset(preset: str = "tiny", **overrides) -> SimConfig:
    """The :class:`SimConfig` of ``configs/sim/preset/<preset>.yaml`` with top-level overrides."""
    path = CONFIG_DIR / "preset" / f"{preset}.yaml"
    if not path.exists():
        known = sorted(p.stem for p in (CONFIG_DIR / "preset").glob("*.yaml"))
        raise ValueError(f"preset: unknown preset {preset!r}; expected one of {known}")
    d = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    d.update(overrides)
    return SimConfig.from_dict(d)


def sim_config(cfg: DictConfig) -> SimConfig:
    """Strip the run keys from a composed Hydra config and build the :class:`SimConfig`."""
    d = OmegaConf.to_container(cfg, resolve=True)
    for k in _RUN_KEYS:
        d.pop(k, None)
    return SimConfig.from_dict(d)


@hydra.main(version_base=None, config_path="../configs/sim", config_name="config")
def main(cfg: DictConfig) -> dict:
    config = sim_config(cfg)
    report = simulate(config, cfg.out, overwrite=bool(cfg.overwrite), progress=bool(cfg.progress))
    mb = report["bytes"] / 2**20
    print(
        f"wrote {report['dataroot']}: {len(report['scenes'])} scenes x "
        f"{report['keyframes_per_scene']} keyframes, {report['files']} files, {mb:.1f} MiB, "
        f"{report['seconds']:.1f} s"
    )
    print(report["summary"])
    return report


if __name__ == "__main__":
    main()
