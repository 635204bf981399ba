"""Which settings a ``world_model`` evaluation scores: "3D-Occ", "Camera", or both.

* "3D-Occ": GT occupancy inputs, GT targets.
* "Camera": Img2Occ pseudo-label inputs (``labels.npz`` in the Occ3D layout, written by
  ``tools/export_occ.py``), GT targets.

Training validates the run's own setting (``stage.occ_root``: null = 3D-Occ, a pseudo-label
folder = Camera). ``tools/eval.py stage=world_model ckpt=A pseudo_labels=DIR [camera_ckpt=B]
[camera_tokenizer_ckpt=T]``
scores both in one pass over the same windows: 3D-Occ with the model of ``ckpt`` and Camera with
the model of ``camera_ckpt`` (the model trained on pseudo labels); without ``camera_ckpt`` the
Camera rows run the ``ckpt`` model on pseudo-label inputs (a model trained on GT, tested on
camera predictions). ``camera_tokenizer_ckpt`` is the tokenizer of the Camera rows (it encodes the
pseudo-label history and decodes the forecasts; the paper trains the Camera setting's tokenizer
on the pseudo labels); null = ``stage.tokenizer_ckpt``, the 3D-Occ tokenizer. Metric keys: the
run's own setting unprefixed (``model/miou_1s``), the added Camera setting under ``camera/``
(``camera/model/miou_1s``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["EvalSetting", "eval_settings", "setting_header"]


@dataclass(frozen=True)
class EvalSetting:
    """One evaluated setting.

    Attributes:
        key: ``"occ3d"`` or ``"camera"``.
        label: table label, ``"3D-Occ"`` or ``"Camera"``.
        prefix: metric-key prefix (``""`` or ``"camera/"``).
        inputs: batch key of the history occupancy (``"occ"``, or ``"occ_target"`` = the GT
            frames when the dataset's own source is pseudo labels).
        source: name of the inputs' source: ``"gt"`` or the pseudo-label folder (token-cache
            key, with each frame's data root and sample token: ``windows.frame_keys``).
        ckpt: checkpoint of the model of this setting; None = the evaluated model itself.
        tokenizer: tokenizer checkpoint of this setting; None = ``stage.tokenizer_ckpt``.
    """

    key: str
    label: str
    prefix: str
    inputs: str
    source: str
    ckpt: str | None = None
    tokenizer: str | None = None


def _path_or_none(cfg: Any, key: str) -> str | None:
    value = cfg.get(key)
    if value in (None, ""):
        return None
    if not isinstance(value, (str, Path)):
        raise ValueError(f"{key}: expected a path or null, got {value!r}")
    return str(value)


def eval_settings(cfg: Any) -> tuple[list[EvalSetting], str | None]:
    """The settings of a run config and the pseudo-label folder its val windows read.

    Returns:
        (settings in table order, ``occ_root`` of the validation windows or None).

    Raises:
        ValueError: ``pseudo_labels`` together with ``stage.occ_root``, ``camera_ckpt`` or
            ``camera_tokenizer_ckpt`` without ``pseudo_labels``, or a path that does not exist.
    """
    occ_root = _path_or_none(cfg.stage, "occ_root")
    evaluating = cfg.get("task") == "eval"
    pseudo = _path_or_none(cfg, "pseudo_labels") if evaluating else None
    camera_ckpt = _path_or_none(cfg, "camera_ckpt") if evaluating else None
    camera_tok = _path_or_none(cfg, "camera_tokenizer_ckpt") if evaluating else None
    for key, path in (("camera_ckpt", camera_ckpt), ("camera_tokenizer_ckpt", camera_tok)):
        if path and not pseudo:
            raise ValueError(
                f"{key}: {path!r} needs pseudo_labels=<Img2Occ pseudo-label folder> "
                "(the Camera setting's inputs)"
            )
    if pseudo and occ_root:
        raise ValueError(
            f"pseudo_labels: set together with stage.occ_root={occ_root!r}; pass one: "
            "pseudo_labels=DIR (both settings) or stage.occ_root=DIR (Camera setting only)"
        )
    for key, path in (("pseudo_labels", pseudo), ("camera_ckpt", camera_ckpt)):
        if path and not Path(path).exists():
            raise ValueError(f"{key}: {path!r} does not exist")
    if camera_tok and not Path(camera_tok).is_file():
        raise ValueError(
            f"camera_tokenizer_ckpt: {camera_tok!r} does not exist or is not a file; pass a "
            "tokenizer checkpoint (checkpoints/best.pt of a tokenizer run)"
        )
    if pseudo:
        return [
            EvalSetting("occ3d", "3D-Occ", "", "occ_target", "gt"),
            EvalSetting("camera", "Camera", "camera/", "occ", pseudo, camera_ckpt, camera_tok),
        ], pseudo
    if occ_root:
        return [EvalSetting("camera", "Camera", "", "occ", occ_root)], occ_root
    return [EvalSetting("occ3d", "3D-Occ", "", "occ", "gt")], None


def setting_header(settings: list[EvalSetting], ckpt: Any, tokenizer_ckpt: Any) -> str:
    """One header line saying what each setting's inputs, targets, model and tokenizer are."""
    parts = []
    for s in settings:
        if s.tokenizer:
            tok = f"tokenizer = {s.tokenizer} (camera_tokenizer_ckpt)"
        elif len(settings) > 1 and s.key == "camera":
            tok = f"tokenizer = {tokenizer_ckpt} (the 3D-Occ tokenizer; no camera_tokenizer_ckpt)"
        else:
            tok = f"tokenizer = {tokenizer_ckpt}"
        if s.key == "occ3d":
            parts.append(f"3D-Occ = GT occupancy inputs, GT targets, {tok}")
            continue
        if s.ckpt:
            model = f"model = {s.ckpt} (trained on pseudo labels)"
        elif len(settings) > 1:
            model = f"model = {ckpt} (the 3D-Occ checkpoint; no camera_ckpt given)"
        else:
            model = f"model = {ckpt}"
        parts.append(
            f"Camera = Img2Occ pseudo-label inputs ({s.source}), GT targets, {model}, {tok}"
        )
    return "Settings: " + "; ".join(parts)


#: ``stage.forecaster`` values: the token model and the pose-warp model.
