"""A tiny model learns the synthetic scene's 3-D occupancy from 2-D labels alone.

The readout (threshold chosen on this training sample, stored in the model) must reach an
mIoU on camera-visible voxels well above both the untrained model and a trivial baseline
that fills every visible voxel with the most frequent class.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID
from renderworld.img2occ import Img2Occ
from renderworld.img2occ.readout import choose_threshold, confusion_matrix, miou_from_confusion
from tests.img2occ.conftest import make_model


def _miou(model, batch) -> float:
    model.eval()
    with torch.no_grad():
        occ = model.readout(model(batch, render=False))
    return miou_from_confusion(confusion_matrix(occ, batch["occ"], batch["mask_camera"]))[0]


def _baseline_miou(batch) -> float:
    gt = batch["occ"]
    vals, counts = np.unique(gt[gt != FREE_ID].numpy(), return_counts=True)
    fill = torch.full_like(gt, int(vals[counts.argmax()]))
    return miou_from_confusion(confusion_matrix(fill, gt, batch["mask_camera"]))[0]


def _train(batch, steps: int) -> tuple[Img2Occ, float, float]:
    torch.manual_seed(0)
    # depth_l1_weight: Pearson alone cannot tell a half-opaque veil of air Gaussians from the
    # surface behind it (it is blind to affine depth changes); see Img2OccConfig.
    model = make_model("torch", depth_l1_weight=2.0)
    start = _miou(model, batch)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    model.train()
    for _ in range(steps):
        loss, _ = model.loss(batch, model(batch))
        opt.zero_grad()
        loss.backward()
        opt.step()
    threshold, scores = choose_threshold(model, [batch])
    assert model.occupancy_threshold.item() == pytest.approx(threshold)
    assert scores[threshold] == pytest.approx(max(s for s in scores.values() if s == s))
    return model, start, _miou(model, batch)


def test_overfits_one_sample_short(synthetic_batch):
    base = _baseline_miou(synthetic_batch)
    _, start, end = _train(synthetic_batch, steps=200)
    # measured (seed 0): untrained 0.00, baseline 0.05; 200 steps 0.77 with AVX-512 kernels,
    # 0.76 with AVX2 (at 120 steps 0.49 and 0.53: the rounding of the CPU's kernels moved it
    # across the bar, so the test trains on to where the machines agree)
    assert start < 0.05
    assert end > 0.5 and end > base + 0.4, (start, end, base)


@pytest.mark.slow
def test_overfits_one_sample_long(synthetic_batch):
    base = _baseline_miou(synthetic_batch)
    _, start, end = _train(synthetic_batch, steps=300)
    # measured: 250 steps 0.81 (seed 0)
    assert end > 0.7 and end > base + 0.6, (start, end, base)
