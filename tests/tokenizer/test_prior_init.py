"""Output heads started at the data's class frequencies (stage.prior_init)."""

import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES
from renderworld.tokenizer import TokenizerConfig, build_tokenizer

GRID = (16, 16, 4)


def _model(variant: str):
    torch.manual_seed(0)
    cfg = TokenizerConfig(variant=variant, grid_shape=GRID, latent_shape=(8, 8), latent_channels=8,
                          codebook_size=16, embed_dim=4, base_channels=8, num_res_blocks=1,
                          attention=False)  # fmt: skip
    return build_tokenizer(cfg)


@pytest.mark.parametrize("variant", ["am_vae", "plain"])
def test_heads_start_at_the_class_frequencies_and_unseen_classes_far_below(variant):
    model = _model(variant)
    counts = torch.zeros(GRID[2], NUM_OCC3D_CLASSES)
    counts[:, FREE_ID] = 9000.0
    counts[0, 11] = 3000.0  # road at the lowest level only
    counts[1:, 4] = 1000.0  # cars above it
    model.init_output_prior(counts)
    heads = [model.class_head] if variant == "plain" else [model.air_head, model.non_air_head]
    for h in heads:  # features do not matter: the scores are the biases
        h.conv.weight.data.zero_()
    occ = torch.zeros((1, *GRID), dtype=torch.uint8) + FREE_ID
    log_p = model(occ, compute_loss=False).logits[0, 0, 0]  # [Z, 18] log-probabilities / logits
    p = torch.softmax(log_p.detach().double(), -1).numpy()
    want = (counts.double() + 1) / (counts.double() + 1).sum(1, keepdim=True)
    np.testing.assert_allclose(p, want.numpy(), rtol=1e-4)
    assert p[0, 11] > 0.2 and p[0, 0] < 1e-3  # "others", never seen, starts far below
    with pytest.raises(ValueError, match="class_counts"):
        model.init_output_prior(torch.zeros(3, NUM_OCC3D_CLASSES))
