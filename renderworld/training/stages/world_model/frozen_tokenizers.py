"""Frozen tokenizers of the ``world_model`` stage and the codes of its windows (a mixin).

The tokenizer lives on the stage, never in the trained module; codes are cached in memory by
(tokenizer checkpoint, source, frame key), the frame key being the frame's data root and sample
token (:func:`~renderworld.training.stages.world_model.windows.frame_keys`), so each keyframe is
encoded once per run and two datasets whose sample tokens collide never share codes. Needs the
stage's ``cfg``, ``settings``, ``grid``, ``_tokenizers`` and ``_codes`` (declared on the class).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch

from renderworld.precision import autocast_off
from renderworld.tokenizer import SceneTokenizer
from renderworld.training.checkpoint import CheckpointError
from renderworld.training.stages.tokenizer import load_tokenizer
from renderworld.training.stages.world_model.windows import frame_keys

if TYPE_CHECKING:
    from renderworld.constants import GridSpec
    from renderworld.training.stages.world_model.settings import StageSettings

__all__ = ["FrozenTokenizers"]

_ENCODE_CHUNK = 16  # frames per tokenizer call (bounds memory on the Occ3D grid)


class FrozenTokenizers:
    """``tokenizer`` / ``tokenizer_of`` / ``window_tokens`` of the world-model stage."""

    # What the class this is mixed into provides (set in its ``__init__``):
    cfg: Any  # the run config; ``stage.occ_root`` names the default token source
    settings: StageSettings  # validated ``stage.*`` keys: ``tokenizer_ckpt``, ``cache_tokens``
    grid: GridSpec  # the run's grid; every tokenizer must have been trained on it
    _tokenizers: dict[str, SceneTokenizer]  # frozen tokenizers by checkpoint path (filled here)
    _codes: dict[tuple[str, ...], torch.Tensor]  # cached codes by (tokenizer, source, frame, ...)

    @property
    def tokenizer(self) -> SceneTokenizer:
        """The frozen tokenizer (loaded once from ``stage.tokenizer_ckpt``, eval mode)."""
        return self.tokenizer_of(None)

    def tokenizer_of(self, path: str | None) -> SceneTokenizer:
        """The frozen tokenizer of checkpoint ``path`` (None = ``stage.tokenizer_ckpt``).

        ``path`` is a setting's own tokenizer (``camera_tokenizer_ckpt``); loaded once, eval mode.
        """
        key_name = "stage.tokenizer_ckpt" if path is None else "camera_tokenizer_ckpt"
        path = self.settings.tokenizer_ckpt if path is None else str(path)
        if path not in self._tokenizers:
            try:
                tok = load_tokenizer(path, "cpu")
            except CheckpointError as err:
                raise CheckpointError(f"{key_name}: {err}") from err
            if tuple(tok.cfg.grid_shape) != tuple(self.grid.shape):
                raise ValueError(
                    f"{key_name}: the tokenizer {path!r} was trained on a "
                    f"{tuple(tok.cfg.grid_shape)} grid, this run uses grid {self.grid.name!r} "
                    f"{tuple(self.grid.shape)}; pass grid=<the tokenizer's grid>"
                )
            self._tokenizers[path] = tok
        return self._tokenizers[path]

    def _tokenizer_on(self, device: torch.device, path: str | None = None) -> SceneTokenizer:
        tok = self.tokenizer_of(path)
        if next(tok.parameters()).device != device:
            key = self.settings.tokenizer_ckpt if path is None else str(path)
            self._tokenizers[key] = tok = tok.to(device)
        return tok

    @torch.no_grad()
    def window_tokens(
        self,
        batch: dict,
        frames: int,
        device: torch.device,
        inputs: str = "occ",
        source: str | None = None,
        tokenizer: str | None = None,
    ) -> torch.Tensor:
        """Codes [B, frames, G, h, w] int64 on ``device`` of a batch's first ``frames`` frames.

        Args:
            inputs: batch key of the occupancy to encode (``"occ"`` or ``"occ_target"``).
            source: name of that occupancy's source (cache key with the frame key: data root
                and sample token); default: the run's ``stage.occ_root`` or ``"gt"``.
            tokenizer: checkpoint of the tokenizer that encodes them (a setting's own);
                default: ``stage.tokenizer_ckpt``.

        Frames already encoded (same tokenizer, source, data root and sample token) come from
        the in-memory cache.
        """
        occ = batch[inputs]
        b = occ.shape[0]
        if source is None:
            source = str(self.cfg.stage.get("occ_root") or "gt")
        tok_key = self.settings.tokenizer_ckpt if tokenizer is None else str(tokenizer)
        keys = [
            [(tok_key, source, k) for k in row[:frames]]
            for row in frame_keys(batch, b, occ.shape[1])
        ]
        tok = self._tokenizer_on(device, tokenizer)
        cache = self._codes if self.settings.cache_tokens else {}
        todo: dict[tuple[str, str, str], tuple[int, int]] = {}
        for i, row in enumerate(keys):
            for j, key in enumerate(row):
                if key not in cache and key not in todo:
                    todo[key] = (i, j)
        names, where = list(todo), list(todo.values())
        for c in range(0, len(names), _ENCODE_CHUNK):
            chunk = where[c : c + _ENCODE_CHUNK]
            x = torch.stack([occ[i, j] for i, j in chunk]).to(device)
            with autocast_off():  # the frozen tokenizer's codes in float32 on every device
                idx = tok.encode(x).indices
            store = torch.int16 if max(tok.cfg.codebook_sizes) <= 2**15 else torch.int32
            for key, codes in zip(names[c : c + _ENCODE_CHUNK], idx.to("cpu", store)):
                cache[key] = codes
        codes = torch.stack([torch.stack([cache[k] for k in row]) for row in keys])
        return codes.to(device).long()
