"""Configuration of the scene tokenizers (AM-VAE, plain VQ-VAE and the two ablations).

One frozen dataclass, :class:`TokenizerConfig`, validated on construction so a bad value
fails where it is written, with a ``ValueError`` naming the field. Grid numbers come from
``renderworld.constants`` (``TokenizerConfig.for_grid("coarse", ...)``) or from config.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

from renderworld.constants import NUM_OCC3D_CLASSES, get_grid

__all__ = ["VARIANTS", "TokenizerConfig"]

#: Tokenizer variants (Table 6.6 of the paper):
#: ``plain`` one codebook, 18-way softmax head; ``air_mask`` one codebook, air-mask
#: (factorised) head; ``separate`` two codebooks (air / non-air latents), 18-way softmax head;
#: ``am_vae`` two codebooks, each decoded by its own branch, combined through the air mask.
VARIANTS: tuple[str, ...] = ("plain", "air_mask", "separate", "am_vae")


def _is_pow2(n: int) -> bool:
    return n >= 1 and (n & (n - 1)) == 0


@dataclass(frozen=True)
class TokenizerConfig:
    """Hyper-parameters of a scene tokenizer.

    Defaults are the paper's setting at the Occ3D grid: 200x200x16 voxels, a 50x50 latent with
    128 channels and a budget of 512 codes.

    Attributes:
        variant: One of :data:`VARIANTS`.
        grid_shape: (X, Y, Z) voxels of the input occupancy.
        latent_shape: (h, w) of the token grid; X/h and Y/w must be powers of two (the encoder
            halves the resolution with stride-2 convolutions).
        latent_channels: C, the dimension of each latent and of each codebook entry.
        codebook_size: K, the total code budget. Single-codebook variants (``plain``,
            ``air_mask``) use one codebook of K codes; two-codebook variants (``separate``,
            ``am_vae``) use two of K // 2 codes each (equal budget of code vectors).
        embed_dim: E, the learned class-embedding size per voxel (height is folded into
            channels: the encoder input has Z * E channels).
        base_channels: Channels at full resolution; doubled per down-sampling level.
        channel_mult: Optional per-level multipliers of ``base_channels`` (one per resolution
            level, full resolution first); empty means (1, 2, 4, ...).
        num_res_blocks: Residual blocks per resolution level (encoder and decoder).
        attention: Whether to add a self-attention block at the latent resolution.
        beta: Commitment weight (Eq. 6.16).
        ema: Update codebooks by exponential moving averages (else by the codebook loss).
        ema_decay: EMA decay of cluster sizes and sums.
        dead_code_steps: A code unused for this many consecutive training steps is restarted
            from a random encoder output of the current batch; 0 disables restarts.
        usage_window: Window (training steps) over which ``usage`` (fraction of codes used) is
            reported.
        ce_weight: Weight of the cross-entropy term (air BCE + non-air CE for air-mask heads).
        lovasz_weight: Weight of the Lovász-softmax term (lambda_1 of Eq. 6.19).
        lovasz_present_only: Average the Lovász term over classes present in the target only.
        class_weights: Optional per-class CE weights, one per Occ3D class (free included).
    """

    variant: str = "am_vae"
    grid_shape: tuple[int, int, int] = (200, 200, 16)
    latent_shape: tuple[int, int] = (50, 50)
    latent_channels: int = 128
    codebook_size: int = 512
    embed_dim: int = 8
    base_channels: int = 64
    channel_mult: tuple[int, ...] = ()
    num_res_blocks: int = 2
    attention: bool = True
    beta: float = 0.25
    ema: bool = True
    ema_decay: float = 0.99
    dead_code_steps: int = 100
    usage_window: int = 100
    ce_weight: float = 10.0
    lovasz_weight: float = 1.0
    lovasz_present_only: bool = True
    class_weights: tuple[float, ...] | None = field(default=None)

    def __post_init__(self) -> None:
        # Hydra/YAML hand lists; store tuples so the config stays hashable and frozen.
        for name in ("grid_shape", "latent_shape", "channel_mult", "class_weights"):
            v = getattr(self, name)
            if isinstance(v, list):
                object.__setattr__(self, name, tuple(v))
        self._validate()

    # ------------------------------------------------------------------ validation
    def _validate(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"variant: expected one of {VARIANTS}, got {self.variant!r}")
        gs, ls = self.grid_shape, self.latent_shape
        if len(gs) != 3 or any(not isinstance(n, int) or n < 1 for n in gs):
            raise ValueError(f"grid_shape: expected 3 positive ints (X, Y, Z), got {gs}")
        if len(ls) != 2 or any(not isinstance(n, int) or n < 1 for n in ls):
            raise ValueError(f"latent_shape: expected 2 positive ints (h, w), got {ls}")
        for axis, (g, h) in enumerate(zip(gs[:2], ls)):
            if g % h != 0 or not _is_pow2(g // h):
                raise ValueError(
                    f"latent_shape: grid size {g} along axis {axis} must be the latent size "
                    f"times a power of two, got latent_shape={ls} for grid_shape={gs}"
                )
        for name in ("latent_channels", "codebook_size", "embed_dim", "base_channels"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{name}: expected a positive int, got {v!r}")
        if self.num_codebooks == 2 and self.codebook_size < 2:
            raise ValueError(
                f"codebook_size: variant {self.variant!r} splits the budget over two "
                f"codebooks and needs at least 2 codes, got {self.codebook_size}"
            )
        if not isinstance(self.num_res_blocks, int) or self.num_res_blocks < 0:
            raise ValueError(f"num_res_blocks: expected an int >= 0, got {self.num_res_blocks!r}")
        if self.channel_mult:
            if len(self.channel_mult) != self.num_levels:
                raise ValueError(
                    f"channel_mult: expected {self.num_levels} multipliers (one per resolution "
                    f"level), got {self.channel_mult}"
                )
            if any(not isinstance(m, int) or m < 1 for m in self.channel_mult):
                raise ValueError(f"channel_mult: expected positive ints, got {self.channel_mult}")
        for name in ("beta", "ce_weight", "lovasz_weight"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v >= 0.0):
                raise ValueError(f"{name}: expected a finite number >= 0, got {v!r}")
        if not 0.0 < self.ema_decay < 1.0:
            raise ValueError(f"ema_decay: expected a value in (0, 1), got {self.ema_decay}")
        if not isinstance(self.dead_code_steps, int) or self.dead_code_steps < 0:
            raise ValueError(f"dead_code_steps: expected an int >= 0, got {self.dead_code_steps}")
        if not isinstance(self.usage_window, int) or self.usage_window < 1:
            raise ValueError(f"usage_window: expected a positive int, got {self.usage_window}")
        if self.class_weights is not None:
            cw = self.class_weights
            if len(cw) != NUM_OCC3D_CLASSES or any(not float(w) >= 0.0 for w in cw):
                raise ValueError(
                    f"class_weights: expected {NUM_OCC3D_CLASSES} non-negative weights, got {cw}"
                )

    # ------------------------------------------------------------------ derived values
    @property
    def downsample(self) -> tuple[int, int]:
        """Down-sampling factor per BEV axis, (X / h, Y / w)."""
        return (
            self.grid_shape[0] // self.latent_shape[0],
            self.grid_shape[1] // self.latent_shape[1],
        )

    @property
    def num_levels(self) -> int:
        """Resolution levels of the encoder (1 + number of stride-2 stages)."""
        return 1 + max(f.bit_length() - 1 for f in self.downsample)

    @property
    def level_channels(self) -> tuple[int, ...]:
        """Channels per resolution level, full resolution first."""
        mult = self.channel_mult or tuple(2**i for i in range(self.num_levels))
        return tuple(self.base_channels * m for m in mult)

    @property
    def num_codebooks(self) -> int:
        """G: 2 for ``separate`` / ``am_vae``, else 1."""
        return 2 if self.variant in ("separate", "am_vae") else 1

    @property
    def codebook_sizes(self) -> tuple[int, ...]:
        """Size of each codebook (the budget split evenly over G codebooks)."""
        g = self.num_codebooks
        return (self.codebook_size // g,) * g

    @property
    def codebook_names(self) -> tuple[str, ...]:
        """``("air", "non_air")`` for two codebooks, ``("scene",)`` for one."""
        return ("air", "non_air") if self.num_codebooks == 2 else ("scene",)

    @property
    def air_mask_head(self) -> bool:
        """Whether the output head is the factorised air-mask head (Eq. 6.13)."""
        return self.variant in ("air_mask", "am_vae")

    # ------------------------------------------------------------------ constructors
    @classmethod
    def for_grid(cls, grid: str, latent_shape: tuple[int, int] | None = None, **kw):
        """Config for a named grid of ``renderworld.constants.GRIDS``.

        Args:
            grid: Grid name (``"occ3d"``, ``"half"``, ``"quarter"``, ``"coarse"``).
            latent_shape: (h, w); default is the largest down-sampling of 4 (the paper's), 2
                or 1 that divides the grid (Occ3D 200 -> 50, coarse 50 -> 25).
            **kw: Any other field.
        """
        shape = get_grid(grid).shape
        if latent_shape is None:
            f = next(f for f in (4, 2, 1) if shape[0] % f == 0 and shape[1] % f == 0)
            latent_shape = (shape[0] // f, shape[1] // f)
        return cls(grid_shape=tuple(shape), latent_shape=tuple(latent_shape), **kw)

    def replace(self, **kw) -> TokenizerConfig:
        """A validated copy with some fields changed."""
        return replace(self, **kw)

    def to_dict(self) -> dict:
        """Plain-python dict of the fields (for checkpoints)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}
