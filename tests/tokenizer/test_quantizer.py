import math

import pytest
import torch

from renderworld.tokenizer import VectorQuantizer, code_usage_stats


def test_usage_and_perplexity_on_hand_made_assignment():
    # K = 8; codes 0 and 1 used 3 times each, code 2 twice: 3 of 8 used.
    idx = torch.tensor([[0, 0, 0, 1], [1, 1, 2, 2]])
    s = code_usage_stats(idx, 8)
    assert float(s["usage"]) == pytest.approx(3 / 8)
    p = torch.tensor([3 / 8, 3 / 8, 2 / 8])
    assert float(s["perplexity"]) == pytest.approx(math.exp(float(-(p * p.log()).sum())), 1e-6)
    one = code_usage_stats(torch.zeros(10, dtype=torch.int64), 8)
    assert float(one["perplexity"]) == pytest.approx(1.0) and float(one["usage"]) == 1 / 8
    uniform = code_usage_stats(torch.arange(8).repeat(3), 8)
    assert float(uniform["perplexity"]) == pytest.approx(8.0, 1e-5)


def _grid(points: torch.Tensor) -> torch.Tensor:
    """[N, C] -> [1, C, 1, N] latent map."""
    return points.t()[None, :, None, :].contiguous()


@pytest.mark.parametrize("ema", [True, False])
def test_assignment_is_nearest_code_and_straight_through(ema):
    vq = VectorQuantizer(4, 2, beta=0.5, ema=ema)
    vq.initialized.fill_(True)
    code = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [5.0, 5.0]])
    vq.codebook.data.copy_(code)
    vq.eval()
    pts = torch.tensor([[0.1, -0.1], [0.9, 0.2], [0.2, 0.8], [4.0, 6.0], [0.6, 0.1]])
    z = _grid(pts).requires_grad_(True)
    out = vq(z)
    assert out.indices.tolist() == [[[0, 1, 2, 3, 1]]]
    assert torch.equal(out.quantized.detach(), _grid(code[[0, 1, 2, 3, 1]]))
    assert torch.equal(vq.lookup(out.indices), out.quantized.detach())
    (out.quantized * 2.0).sum().backward()
    assert torch.equal(z.grad, torch.full_like(z, 2.0))  # straight through: identity gradient
    z.grad = None
    vq(z).loss.backward()  # beta * mean((z - q)^2) (+ codebook term without EMA)
    q = _grid(code[[0, 1, 2, 3, 1]])
    assert torch.allclose(z.grad, 0.5 * 2.0 * (z - q).detach() / z.numel())
    if not ema:
        assert vq.codebook.grad is not None and torch.isfinite(vq.codebook.grad).all()


def clusters(n_clusters: int, per: int, seed: int, dim: int = 4) -> torch.Tensor:
    """Tight clusters around fixed centres; ``seed`` draws the noise."""
    centres = torch.randn(n_clusters, dim, generator=torch.Generator().manual_seed(123)) * 3.0
    g = torch.Generator().manual_seed(seed)
    pts = centres.repeat_interleave(per, 0) + 0.05 * torch.randn(n_clusters * per, dim, generator=g)
    return _grid(pts)


@pytest.mark.parametrize("ema", [True, False])
def test_dead_codes_are_restarted_and_usage_rises(ema):
    k = 16
    torch.manual_seed(0)
    vq = VectorQuantizer(k, 4, ema=ema, dead_code_steps=3, usage_window=5)
    vq.initialized.fill_(True)  # keep our hand-made codebook
    far = torch.full((k, 4), 100.0)
    far[0], far[1] = 0.0, 1.0  # only two codes anywhere near the data
    vq.codebook.data.copy_(far)
    if ema:
        vq.ema_sum.copy_(far)
    vq.train()
    first = vq(clusters(12, 20, seed=0))
    assert float(first.stats["usage"]) == pytest.approx(2 / k)
    restarted = 0.0
    for step in range(20):
        out = vq(clusters(12, 20, seed=step))
        restarted += float(out.stats["restarted"])
    assert restarted >= k - 2  # the 14 far codes (at least) were restarted
    assert float(out.stats["window_usage"]) >= 0.6
    assert float(out.stats["usage"]) >= 0.6
    assert float(out.stats["perplexity"]) > 6.0
    assert float((vq.codebook.detach() - 100.0).abs().min()) > 50.0  # no code left out at 100

    # Without the remedy the same codebook stays collapsed.
    vq0 = VectorQuantizer(k, 4, ema=ema, dead_code_steps=0, usage_window=5)
    vq0.initialized.fill_(True)
    vq0.codebook.data.copy_(far)
    if ema:
        vq0.ema_sum.copy_(far)
    vq0.train()
    for step in range(20):
        out0 = vq0(clusters(12, 20, seed=step))
    assert float(out0.stats["window_usage"]) <= 2 / k


def test_restart_does_not_count_as_use():
    vq = VectorQuantizer(4, 2, dead_code_steps=2, usage_window=100)
    vq.initialized.fill_(True)
    vq.codebook.data.copy_(torch.tensor([[0.0, 0.0], [50.0, 0], [60.0, 0], [70.0, 0]]))
    vq.ema_sum.copy_(vq.codebook)
    vq.train()
    z = _grid(torch.zeros(6, 2))  # every cell identical: only one code can ever be used
    for _ in range(6):
        out = vq(z)
        assert torch.isfinite(out.loss) and torch.isfinite(out.quantized).all()
    assert float(out.stats["window_usage"]) == pytest.approx(1 / 4)
    assert torch.allclose(vq.codebook, torch.zeros(4, 2))  # restarted onto the data


def test_ema_moves_codes_to_cluster_means_and_first_batch_initialises():
    torch.manual_seed(0)
    vq = VectorQuantizer(3, 2, ema=True, decay=0.5, dead_code_steps=0)
    pts = torch.tensor([[0.0, 0.0], [0.2, 0.0], [10.0, 10.0], [10.0, 10.4], [-5.0, 3.0]])
    vq.train()
    vq(_grid(pts))  # data-dependent init: the codebook is a permutation of the points' rows
    assert bool(vq.initialized)
    for _ in range(30):
        vq(_grid(pts))
    means = {tuple(round(v, 3) for v in row) for row in vq.codebook.tolist()}
    assert means == {(0.1, 0.0), (10.0, 10.2), (-5.0, 3.0)}


def test_eval_mode_changes_nothing():
    vq = VectorQuantizer(8, 4, dead_code_steps=1)
    vq.train()
    vq(clusters(3, 5, seed=0))
    before = {k: v.clone() for k, v in vq.state_dict().items()}
    vq.eval()
    for s in range(3):
        vq(clusters(3, 5, seed=s + 10))
    assert all(torch.equal(before[k], v) for k, v in vq.state_dict().items())


def test_bad_latent_shape():
    with pytest.raises(ValueError, match=r"z: expected \[B, 4, h, w\]"):
        VectorQuantizer(8, 4)(torch.zeros(1, 3, 2, 2))
