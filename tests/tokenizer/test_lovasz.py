"""Lovász-softmax against brute-force evaluations of its definition (Berman et al. 2018)."""

import itertools

import pytest
import torch

from renderworld.tokenizer.lovasz import (
    jaccard_increments,
    lovasz_extension,
    lovasz_softmax,
    lovasz_softmax_reference,
)

IMPLS = [lovasz_softmax, lovasz_softmax_reference]


def jaccard_set_loss(mispredicted: set[int], truth: set[int]) -> float:
    """Delta_J(M) = |M| / |truth U M| (0 for the empty set)."""
    if not mispredicted:
        return 0.0
    return len(mispredicted) / len(truth | mispredicted)


def greedy_value(m, truth, order) -> float:
    """sum_i m_(order i) * (Delta(S_i) - Delta(S_{i-1})) for one permutation."""
    total, prev, chosen = 0.0, 0.0, set()
    for i in order:
        chosen.add(i)
        cur = jaccard_set_loss(chosen, truth)
        total += m[i] * (cur - prev)
        prev = cur
    return total


def lovasz_by_max_over_permutations(m, truth) -> float:
    """For a submodular Delta the Lovász extension is the max of the greedy values over all
    orders (the vertices of its base polytope); no sorting involved."""
    return max(greedy_value(m, truth, p) for p in itertools.permutations(range(len(m))))


def lovasz_by_threshold_integral(m, truth) -> float:
    """int_0^1 Delta({i : m_i >= t}) dt, exact on the piecewise-constant level sets."""
    levels = sorted({0.0, *m, 1.0})
    total = 0.0
    for lo, hi in zip(levels[:-1], levels[1:]):
        level_set = {i for i, v in enumerate(m) if v >= hi}
        total += (hi - lo) * jaccard_set_loss(level_set, truth)
    return total


@pytest.mark.parametrize("n", [1, 2, 3, 5, 6])
def test_extension_matches_brute_force_definitions(n):
    g = torch.Generator().manual_seed(n)
    for trial in range(6):
        gt = (torch.rand(n, generator=g, dtype=torch.float64) < 0.5).double()
        if trial == 0:
            gt.zero_()  # class absent: Delta still defined
        p = torch.rand(n, generator=g, dtype=torch.float64)
        m = (gt - p).abs()
        truth = {i for i in range(n) if gt[i] == 1}
        ours = float(lovasz_extension(m, gt))
        assert ours == pytest.approx(lovasz_by_max_over_permutations(m.tolist(), truth), abs=1e-12)
        assert ours == pytest.approx(lovasz_by_threshold_integral(m.tolist(), truth), abs=1e-12)


def test_increments_sum_to_jaccard_loss_of_whole_set():
    gt = torch.tensor([1.0, 0.0, 1.0, 1.0, 0.0])
    inc = jaccard_increments(gt)
    # All elements mispredicted: |M| = 5, truth U M = 5 -> Delta = 1.
    assert float(inc.sum()) == pytest.approx(1.0)
    assert bool((inc >= 0).all())  # Delta is increasing along a chain


@pytest.mark.parametrize("impl", IMPLS)
def test_equals_exact_jaccard_loss_on_hard_predictions(impl):
    g = torch.Generator().manual_seed(1)
    k, n = 5, 40
    target = torch.randint(0, k - 1, (n,), generator=g)  # class k-1 absent from the target
    pred = torch.randint(0, k, (n,), generator=g)
    probs = torch.nn.functional.one_hot(pred, k).double()
    ious = []
    for c in range(k):
        t, p = target == c, pred == c
        if t.any():
            ious.append(float((t & p).sum()) / float((t | p).sum()))
    expected = 1.0 - sum(ious) / len(ious)
    assert float(impl(probs, target, present_only=True)) == pytest.approx(expected, abs=1e-12)
    # All classes: the absent class' loss is 1 if it was predicted anywhere, else 0.
    absent_loss = 1.0 if bool((pred == k - 1).any()) else 0.0
    expected_all = (sum(1.0 - i for i in ious) + absent_loss) / k
    assert float(impl(probs, target, present_only=False)) == pytest.approx(expected_all)


def test_batched_equals_per_class_reference_float64():
    g = torch.Generator().manual_seed(2)
    logits = torch.randn(300, 18, generator=g, dtype=torch.float64)
    target = torch.randint(0, 18, (300,), generator=g)
    target[target == 5] = 6  # an absent class
    valid = torch.rand(300, generator=g) < 0.8
    for present_only in (True, False):
        a = lovasz_softmax(logits.softmax(-1), target, present_only, valid)
        b = lovasz_softmax_reference(logits.softmax(-1), target, present_only, valid)
        assert float(a) == pytest.approx(float(b), abs=1e-12)
    f32 = lovasz_softmax(logits.float().softmax(-1), target)
    assert float(f32) == pytest.approx(float(lovasz_softmax(logits.softmax(-1), target)), abs=1e-5)


@pytest.mark.parametrize("impl", IMPLS)
def test_degenerate_cases_finite_with_finite_gradients(impl):
    # One class only (an all-free volume), perfect and uniform predictions, empty valid mask.
    target = torch.full((50,), 17)
    for logits in (torch.zeros(50, 18), torch.nn.functional.one_hot(target, 18) * 30.0):
        x = logits.clone().requires_grad_(True)
        loss = impl(x.softmax(-1), target, present_only=False)
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(x.grad).all()
    perfect = impl(torch.nn.functional.one_hot(target, 18).float(), target)
    assert float(perfect) == 0.0
    x = torch.zeros(50, 18, requires_grad=True)
    empty = impl(x.softmax(-1), target, valid=torch.zeros(50, dtype=torch.bool))
    empty.backward()
    assert float(empty.detach()) == 0.0 and torch.isfinite(x.grad).all()


def test_bad_shapes():
    with pytest.raises(ValueError, match="probs: expected \\[N, K\\]"):
        lovasz_softmax(torch.rand(3), torch.zeros(3, dtype=torch.int64))
    with pytest.raises(ValueError, match="target: expected \\[3\\]"):
        lovasz_softmax(torch.rand(3, 2), torch.zeros(4, dtype=torch.int64))
