import pytest

from renderworld.constants import GRIDS, NUM_OCC3D_CLASSES
from renderworld.tokenizer import VARIANTS, TokenizerConfig, build_tokenizer


def test_paper_default():
    cfg = TokenizerConfig()
    assert cfg.variant == "am_vae"
    assert cfg.grid_shape == GRIDS["occ3d"].shape
    assert cfg.latent_shape == (50, 50) and cfg.downsample == (4, 4) and cfg.num_levels == 3
    assert cfg.latent_channels == 128 and cfg.codebook_size == 512
    assert cfg.codebook_sizes == (256, 256) and cfg.codebook_names == ("air", "non_air")
    assert cfg.level_channels == (64, 128, 256)


@pytest.mark.parametrize("variant", VARIANTS)
def test_equal_code_budget(variant):
    cfg = TokenizerConfig(variant=variant, codebook_size=512)
    assert sum(cfg.codebook_sizes) == 512
    assert len(cfg.codebook_sizes) == cfg.num_codebooks == len(cfg.codebook_names)
    assert cfg.air_mask_head == (variant in ("air_mask", "am_vae"))


def test_for_grid():
    coarse = TokenizerConfig.for_grid("coarse", base_channels=8)
    assert coarse.grid_shape == (50, 50, 4) and coarse.latent_shape == (25, 25)
    assert TokenizerConfig.for_grid("occ3d").latent_shape == (50, 50)
    assert TokenizerConfig.for_grid("coarse", latent_shape=(50, 50)).num_levels == 1
    with pytest.raises(ValueError, match="grid: unknown grid"):
        TokenizerConfig.for_grid("nope")


@pytest.mark.parametrize(
    "kw, field",
    [
        ({"latent_shape": (30, 50)}, "latent_shape"),  # 200 / 30 not an integer
        ({"latent_shape": (40, 40)}, "latent_shape"),  # 200 / 40 = 5, not a power of two
        ({"latent_shape": (50,)}, "latent_shape"),
        ({"grid_shape": (200, 200)}, "grid_shape"),
        ({"codebook_size": 0}, "codebook_size"),
        ({"codebook_size": 1}, "codebook_size"),  # two codebooks need >= 2
        ({"latent_channels": 0}, "latent_channels"),
        ({"embed_dim": -1}, "embed_dim"),
        ({"variant": "vqgan"}, "variant"),
        ({"beta": -1.0}, "beta"),
        ({"ema_decay": 1.0}, "ema_decay"),
        ({"dead_code_steps": -1}, "dead_code_steps"),
        ({"usage_window": 0}, "usage_window"),
        ({"channel_mult": (1, 2)}, "channel_mult"),
        ({"class_weights": (1.0,) * 3}, "class_weights"),
        ({"num_res_blocks": -1}, "num_res_blocks"),
    ],
)
def test_bad_configs_name_the_field(kw, field):
    with pytest.raises(ValueError, match=f"^{field}:"):
        TokenizerConfig(**kw)


def test_lists_from_yaml_become_tuples_and_dict_build():
    cfg = TokenizerConfig(
        grid_shape=[32, 32, 8],
        latent_shape=[8, 8],
        class_weights=[1.0] * NUM_OCC3D_CLASSES,
        base_channels=4,
        latent_channels=4,
        codebook_size=8,
    )
    assert cfg.grid_shape == (32, 32, 8) and isinstance(cfg.class_weights, tuple)
    hash(cfg)
    model = build_tokenizer(cfg.to_dict())
    assert model.cfg == cfg
    with pytest.raises(ValueError, match="cfg: unknown tokenizer fields \\['latent_size'\\]"):
        build_tokenizer({"latent_size": 4})
    with pytest.raises(TypeError, match="cfg: expected a TokenizerConfig"):
        from renderworld.tokenizer import SceneTokenizer

        SceneTokenizer({"variant": "plain"})
