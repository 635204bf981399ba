"""Planner bundles: one file holding the tokenizer and the world model, loadable safely.

Format (``schema_version`` 2), a plain dict saved with ``torch.save`` and read with
``torch.load(weights_only=True)`` (no pickled code)::

    {
      "schema_version": 2,
      "stage": "planner_bundle",
      "tokenizer":   {"kind": str, "config": dict, "state_dict": {name: Tensor}},
      "world_model": {"kind": "tokens" | "pose_warp",
                      "config": dict (WorldModelConfig.to_dict()), "state_dict": {...},
                      "options": {} (tokens) | {"anchors": str, "movers": str,
                                  "kinematics": bool, "motion_frames": int, "agents": int,
                                  "pose_heads": int, "bev_pool": int, "leader": bool,
                                  "leader_stop": bool,
                                  "grid": {"name": str,
                                  "range_min": [3], "range_max": [3], "shape": [3]}}},
    }

``kind`` ``"tokens"`` is :class:`renderworld.world.WorldModel`, ``"pose_warp"``
:class:`renderworld.world.pose.PoseWarpWorldModel` (its pose head's anchors, how its forecast
moves other road users and the occupancy grid its warps use are the options). Bundles of
``schema_version`` 1 (token world models only, no ``kind`` / ``options``) still load; pose-warp
options without ``movers``, ``kinematics``, ``motion_frames``, ``agents``, ``pose_heads``,
``bev_pool``, ``leader`` or ``leader_stop`` (bundles written before they existed) load as
``"static"``, false, 0, 0, 1, 4, false and false.

The tokenizer is rebuilt through a registry (``register_tokenizer``), never by importing a
class named in the file. Writes are atomic (temp file in the same folder, fsync, rename);
loads are strict (unknown/missing keys and wrong schema raise).

Bundles of ``world_model`` runs (either forecaster):
:func:`renderworld.training.stages.world_model.bundle.export_planner_bundle`
(``tools/export_planner.py``; the main job writes ``<out>/planner/planner.pt``).
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import torch
from torch import nn

from renderworld.constants import GridSpec
from renderworld.planning.api import Planner
from renderworld.planning.pose_warp import default_grid, tokenizer_grid_shape
from renderworld.tokenizer import SceneTokenizer, build_tokenizer
from renderworld.world.config import WorldModelConfig
from renderworld.world.model import WorldModel
from renderworld.world.movers import MOVERS
from renderworld.world.pose import ANCHORS, PoseWarpWorldModel

__all__ = [
    "BUNDLE_SCHEMA_VERSION",
    "BUNDLE_STAGE",
    "load_planner",
    "register_tokenizer",
    "registered_tokenizers",
    "save_planner_bundle",
]

BUNDLE_SCHEMA_VERSION = 2
#: Schema versions :func:`load_planner` reads (1: token world models only).
READABLE_SCHEMA_VERSIONS = (1, 2)
#: World-model kinds of a bundle (``stage.forecaster`` of the run).
WORLD_MODEL_KINDS = ("tokens", "pose_warp")
BUNDLE_STAGE = "planner_bundle"


@dataclasses.dataclass(frozen=True)
class _Entry:
    cls: type
    from_config: Callable[[dict], nn.Module]
    to_config: Callable[[nn.Module], dict]


_REGISTRY: dict[str, _Entry] = {}


def _plain(value):
    """Tuples -> lists recursively, so the config survives a weights-only load."""
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def _default_to_config(module: nn.Module) -> dict:
    for attr in ("config", "cfg"):
        cfg = getattr(module, attr, None)
        if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
            return _plain(dataclasses.asdict(cfg))
        if isinstance(cfg, dict):
            return _plain(dict(cfg))
    raise ValueError(
        f"tokenizer: {type(module).__name__} has no dataclass/dict .config or .cfg; register it "
        "with to_config="
    )


def register_tokenizer(
    kind: str,
    cls: type,
    from_config: Callable[[dict], nn.Module] | None = None,
    to_config: Callable[[nn.Module], dict] | None = None,
) -> None:
    """Make a tokenizer class storable in bundles.

    Args:
        kind: the name written into bundles.
        cls: the ``nn.Module`` subclass (instances of exactly this type are saved as ``kind``).
        from_config: builds a module from the stored config dict (default
            ``cls.from_config(d)`` if it exists, else ``cls(**d)``). The AM-VAE would be
            registered with ``from_config=renderworld.tokenizer.build_tokenizer``.
        to_config: returns a plain dict (default: ``asdict`` of ``.config`` / ``.cfg``).
    """
    if not isinstance(kind, str) or not kind:
        raise ValueError(f"kind: expected a non-empty str, got {kind!r}")
    if not (isinstance(cls, type) and issubclass(cls, nn.Module)):
        raise TypeError(f"cls: expected an nn.Module subclass, got {cls!r}")
    if from_config is None:
        from_config = getattr(cls, "from_config", None) or (lambda d: cls(**d))
    _REGISTRY[kind] = _Entry(cls, from_config, to_config or _default_to_config)


def _register_builtin() -> None:
    """Register the package's own tokenizer as ``"scene_tokenizer"``."""
    if "scene_tokenizer" not in _REGISTRY:
        register_tokenizer("scene_tokenizer", SceneTokenizer, from_config=build_tokenizer)


def registered_tokenizers() -> tuple[str, ...]:
    """Kinds known to :func:`load_planner`."""
    return tuple(sorted(_REGISTRY))


def _kind_of(tokenizer) -> str:
    _register_builtin()
    for kind, entry in _REGISTRY.items():
        if type(tokenizer) is entry.cls:
            return kind
    raise ValueError(
        f"tokenizer: type {type(tokenizer).__name__} is not registered; call "
        f"register_tokenizer(kind, cls) first (known: {registered_tokenizers()})"
    )


def _grid_dict(grid: GridSpec) -> dict:
    return {"name": grid.name, "range_min": [float(v) for v in grid.range_min],
            "range_max": [float(v) for v in grid.range_max],
            "shape": [int(v) for v in grid.shape]}  # fmt: skip


def _grid_of(d, where: str) -> GridSpec:
    _require_keys(d, {"name", "range_min", "range_max", "shape"}, where)
    try:
        lo, hi = tuple(float(v) for v in d["range_min"]), tuple(float(v) for v in d["range_max"])
        shape = tuple(int(v) for v in d["shape"])
    except (TypeError, ValueError) as err:
        raise ValueError(f"{where}: expected numbers, got {d!r}") from err
    if len(lo) != 3 or len(hi) != 3 or len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"{where}: expected 3 ranges and 3 positive sizes, got {d!r}")
    if not all(a < b for a, b in zip(lo, hi)):
        raise ValueError(f"{where}: expected range_min < range_max, got {lo} and {hi}")
    return GridSpec(str(d["name"]), lo, hi, shape)


def _world_model_options(world_model, tokenizer, grid: GridSpec | None) -> tuple[str, dict]:
    if isinstance(world_model, PoseWarpWorldModel):
        if grid is None:
            shape = tokenizer_grid_shape(tokenizer)
            if shape is None:
                raise ValueError(
                    "grid: a pose-warp world model needs the occupancy grid; the tokenizer names "
                    "no grid_shape, pass grid="
                )
            grid = default_grid(shape)
        if not isinstance(grid, GridSpec):
            raise TypeError(f"grid: expected a GridSpec or None, got {type(grid).__name__}")
        options = {
            "anchors": world_model.pose.anchors,
            "movers": world_model.movers,
            "kinematics": world_model.pose.kinematics,
            "motion_frames": world_model.pose.motion_frames,
            "agents": world_model.pose.agents,
            "pose_heads": len(getattr(world_model.pose, "members", (world_model.pose,))),
            "bev_pool": world_model.pose.bev_pool,
            "leader": world_model.pose.leader,
            "leader_stop": world_model.leader_stop,
        }
        return "pose_warp", {**options, "grid": _grid_dict(grid)}
    if isinstance(world_model, WorldModel):
        return "tokens", {}
    raise TypeError(
        f"world_model: expected WorldModel or PoseWarpWorldModel, got {type(world_model).__name__}"
    )


def save_planner_bundle(
    path: str | os.PathLike,
    tokenizer: nn.Module,
    world_model: WorldModel | PoseWarpWorldModel,
    grid: GridSpec | None = None,
) -> Path:
    """Write a planner bundle atomically.

    Args:
        path: destination file (its folder must exist).
        tokenizer: a registered tokenizer module.
        world_model: the token world model or the pose-warp world model.
        grid: the occupancy grid of a pose-warp model's warps (None: the Occ3D range on the
            tokenizer's ``grid_shape``, as every named grid); not stored for a token model.

    Returns:
        The path written.
    """
    wm_kind, options = _world_model_options(world_model, tokenizer, grid)
    kind = _kind_of(tokenizer)
    path = Path(path)
    if not path.parent.is_dir():
        raise ValueError(f"path: folder {path.parent} does not exist")
    bundle = {
        "schema_version": BUNDLE_SCHEMA_VERSION,
        "stage": BUNDLE_STAGE,
        "tokenizer": {
            "kind": kind,
            "config": _REGISTRY[kind].to_config(tokenizer),
            "state_dict": {k: v.detach().cpu() for k, v in tokenizer.state_dict().items()},
        },
        "world_model": {
            "kind": wm_kind,
            "config": world_model.config.to_dict(),
            "state_dict": {k: v.detach().cpu() for k, v in world_model.state_dict().items()},
            "options": options,
        },
    }
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(bundle, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def _require_keys(d, keys: set[str], where: str) -> None:
    if not isinstance(d, dict):
        raise ValueError(f"{where}: expected a dict, got {type(d).__name__}")
    if set(d) != keys:
        raise ValueError(f"{where}: expected keys {sorted(keys)}, got {sorted(map(str, d))}")


def _read_bundle(path: Path) -> dict:
    """``torch.load`` (weights only) that turns every way a file can be unreadable into one
    ``ValueError`` naming the file."""
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # truncated zip, random bytes, JSON, pickled code, ...
        first = str(err).strip().splitlines()[0][:200] if str(err).strip() else ""
        raise ValueError(
            f"ckpt_path {path}: not a readable planner bundle (torch.load with "
            f"weights_only=True failed: {type(err).__name__}: {first})"
        ) from err
    if not isinstance(data, dict) or "stage" not in data:
        got = sorted(map(str, data)) if isinstance(data, dict) else type(data).__name__
        raise ValueError(
            f"ckpt_path {path}: not a planner bundle (expected a dict with keys "
            f"['schema_version', 'stage', 'tokenizer', 'world_model'], got {got})"
        )
    return data


def load_planner(
    ckpt_path: str | os.PathLike, device: str | torch.device = "cpu", **planner_options
) -> Planner:
    """Load a bundle written by :func:`save_planner_bundle` into a :class:`Planner`.

    Loads with ``torch.load(weights_only=True)`` and ``load_state_dict(strict=True)``.

    Args:
        ckpt_path: the bundle file.
        device: where the planner runs.
        **planner_options: passed to :class:`Planner` (``fast``, ``precision``, ``compile``,
            ``pin_memory``).

    Raises:
        ValueError: naming the file, for a missing file, a file torch cannot read (truncated,
            random bytes, JSON, pickled code), a foreign checkpoint (other keys, stage or
            schema), an unregistered tokenizer kind, a config the builders refuse, or state
            dicts that do not match the configs.
    """
    path = Path(ckpt_path)
    if not path.is_file():
        raise ValueError(f"ckpt_path: no such file {path}")
    data = _read_bundle(path)
    if data["stage"] != BUNDLE_STAGE:
        raise ValueError(
            f"ckpt_path {path}: expected stage {BUNDLE_STAGE!r}, got {data['stage']!r}"
        )
    _require_keys(
        data, {"schema_version", "stage", "tokenizer", "world_model"}, f"ckpt_path {path}"
    )
    version = data["schema_version"]
    if type(version) is not int or version not in READABLE_SCHEMA_VERSIONS:
        raise ValueError(
            f"ckpt_path {path}: expected schema_version 1 or {BUNDLE_SCHEMA_VERSION}, "
            f"got {version!r}"
        )
    tok, wm = data["tokenizer"], data["world_model"]
    _require_keys(tok, {"kind", "config", "state_dict"}, f"ckpt_path {path}: tokenizer")
    if version == 1:
        _require_keys(wm, {"config", "state_dict"}, f"ckpt_path {path}: world_model")
        wm = {**wm, "kind": "tokens", "options": {}}
    else:
        _require_keys(
            wm, {"kind", "config", "state_dict", "options"}, f"ckpt_path {path}: world_model"
        )
    wm_kind, options, grid = wm["kind"], wm["options"], None
    if wm_kind not in WORLD_MODEL_KINDS:
        raise ValueError(
            f"ckpt_path {path}: world_model kind: expected one of {WORLD_MODEL_KINDS}, "
            f"got {wm_kind!r}"
        )
    where = f"ckpt_path {path}: world_model options"
    if wm_kind == "pose_warp":
        if isinstance(options, dict):  # bundles written before an option existed
            options = {"movers": "static", "kinematics": False, "motion_frames": 0, "agents": 0,
                       "pose_heads": 1, "bev_pool": 4, "leader": False, "leader_stop": False,
                       **options}  # fmt: skip
        keys = {"anchors", "movers", "kinematics", "motion_frames", "agents", "pose_heads",
                "bev_pool", "leader", "leader_stop", "grid"}  # fmt: skip
        _require_keys(options, keys, where)
        if options["anchors"] not in ANCHORS:
            raise ValueError(
                f"{where}: anchors: expected one of {ANCHORS}, got {options['anchors']!r}"
            )
        if options["movers"] not in MOVERS:
            raise ValueError(
                f"{where}: movers: expected one of {MOVERS}, got {options['movers']!r}"
            )
        if not isinstance(options["kinematics"], bool):
            raise ValueError(
                f"{where}: kinematics: expected true or false, got {options['kinematics']!r}"
            )
        for key, least in (("motion_frames", 0), ("agents", 0), ("pose_heads", 1), ("bev_pool", 1)):
            v = options[key]
            if not isinstance(v, int) or isinstance(v, bool) or v < least:
                raise ValueError(f"{where}: {key}: expected an int >= {least}, got {v!r}")
        for key in ("leader", "leader_stop"):
            if not isinstance(options[key], bool):
                raise ValueError(f"{where}: {key}: expected true or false, got {options[key]!r}")
        grid = _grid_of(options["grid"], f"{where}: grid")
    else:
        _require_keys(options, set(), where)
    _register_builtin()
    if not isinstance(tok["kind"], str) or tok["kind"] not in _REGISTRY:
        raise ValueError(
            f"ckpt_path {path}: tokenizer kind {tok['kind']!r} is not registered "
            f"(known: {registered_tokenizers()}); call register_tokenizer first"
        )
    for where, d in (("tokenizer", tok), ("world_model", wm)):
        if not isinstance(d["config"], dict):
            raise ValueError(
                f"ckpt_path {path}: {where} config: expected a dict, "
                f"got {type(d['config']).__name__}"
            )
        sd = d["state_dict"]
        if not isinstance(sd, dict) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
            raise ValueError(f"ckpt_path {path}: {where} state_dict: expected a dict of tensors")
    try:  # a registered builder may fail in any way on a config read from a file
        tokenizer = _REGISTRY[tok["kind"]].from_config(tok["config"])
    except Exception as err:
        raise ValueError(
            f"ckpt_path {path}: tokenizer config refused: {type(err).__name__}: {err}"
        ) from err
    try:
        config = WorldModelConfig.from_dict(wm["config"])
        if wm_kind == "pose_warp":
            world_model = PoseWarpWorldModel(
                config,
                anchors=options["anchors"],
                movers=options["movers"],
                kinematics=options["kinematics"],
                motion_frames=options["motion_frames"],
                agents=options["agents"],
                pose_heads=options["pose_heads"],
                bev_pool=options["bev_pool"],
                leader=options["leader"],
                leader_stop=options["leader_stop"],
            )
        else:
            world_model = WorldModel(config)
    except (TypeError, ValueError) as err:
        raise ValueError(f"ckpt_path {path}: world_model config refused: {err}") from err
    try:
        tokenizer.load_state_dict(tok["state_dict"], strict=True)
        world_model.load_state_dict(wm["state_dict"], strict=True)
    except RuntimeError as err:
        raise ValueError(f"ckpt_path {path}: state dict does not match its config: {err}") from err
    if grid is not None:
        shape = tokenizer_grid_shape(tokenizer)
        if shape is not None and tuple(shape) != tuple(grid.shape):
            raise ValueError(
                f"ckpt_path {path}: world_model options: grid shape {tuple(grid.shape)} does "
                f"not match the tokenizer's grid_shape {tuple(shape)}"
            )
        planner_options = {"grid": grid, **planner_options}
    return Planner(tokenizer, world_model, device=device, **planner_options)
