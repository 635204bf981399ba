"""A bundle holding the package's own tokenizer loads in a fresh process (no stage import)."""

import subprocess
import sys

import torch

from renderworld.planning import save_planner_bundle
from renderworld.tokenizer import TokenizerConfig, build_tokenizer
from renderworld.world import WorldModel, WorldModelConfig


def test_fresh_process_loads_scene_tokenizer_bundle(tmp_path):
    tok = build_tokenizer(
        TokenizerConfig(grid_shape=(16, 16, 4), latent_shape=(8, 8), latent_channels=8,
                        codebook_size=16, base_channels=8, num_res_blocks=1, attention=False)
    )  # fmt: skip
    sizes = tok.encode(torch.zeros(1, 16, 16, 4, dtype=torch.uint8)).codebook_sizes
    wm = WorldModel(
        WorldModelConfig(codebook_sizes=tuple(sizes), token_grid=(8, 8), embed_dim=16,
                         num_heads=2, num_scales=1, layers_per_scale=(1,))
    )  # fmt: skip
    path = save_planner_bundle(tmp_path / "planner.pt", tok, wm)
    code = (
        "import sys; from renderworld.planning import load_planner; "
        f"p = load_planner({str(path)!r}); print(type(p).__name__)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "Planner"
