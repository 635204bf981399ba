"""Threshold search, export of Occ3D-layout pseudo labels, and the comparison picture."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID
from renderworld.data import load_occ3d_labels
from renderworld.img2occ.export import export_occupancy
from renderworld.img2occ.readout import (
    ThresholdSearch,
    choose_threshold,
    confusion_matrix,
    geometry_iou_from_confusion,
    miou_from_confusion,
    readout_occupancy,
)
from renderworld.img2occ.viz import draw_views
from tests.img2occ._synthetic import TEST_GRID
from tests.img2occ.conftest import make_model


def test_confusion_and_miou_by_hand():
    gt = np.array([4, 4, 11, 17, 17, 11])
    pred = np.array([4, 17, 11, 4, 17, 11])
    conf = confusion_matrix(pred, gt)
    assert conf[4, 4] == 1 and conf[4, 17] == 1 and conf[17, 4] == 1 and conf[11, 11] == 2
    miou, iou = miou_from_confusion(conf)
    assert iou[4] == pytest.approx(1 / 3) and iou[11] == pytest.approx(1.0)
    assert np.isnan(iou[0])  # absent class: left out of the mean
    assert miou == pytest.approx((1 / 3 + 1) / 2)
    assert geometry_iou_from_confusion(conf) == pytest.approx(3 / 5)
    masked = confusion_matrix(pred, gt, mask=np.array([1, 0, 1, 0, 1, 1], bool))
    assert masked.sum() == 4 and masked[4, 17] == 0
    with pytest.raises(ValueError, match=r"gt: expected labels in \[0, 17\], got \[14, 27\]"):
        confusion_matrix(pred, gt + 10)


def test_threshold_search_finds_the_separating_threshold():
    rng = np.random.default_rng(0)
    gt = rng.choice([4, 11, FREE_ID], size=2000, p=[0.2, 0.3, 0.5])
    cls = np.where(gt == FREE_ID, 4, gt)
    # occupied voxels have opacity in (0.6, 1), free ones in (0, 0.4): any t in [0.4, 0.6) wins
    op = np.where(gt == FREE_ID, rng.uniform(0, 0.4, gt.size), rng.uniform(0.6, 1, gt.size))
    search = ThresholdSearch([0.1, 0.3, 0.5, 0.7, 0.9])
    search.update(torch.tensor(op[:1000]), torch.tensor(cls[:1000]), torch.tensor(gt[:1000]))
    search.update(torch.tensor(op[1000:]), torch.tensor(cls[1000:]), torch.tensor(gt[1000:]))
    assert search.best("miou") == 0.5 and search.best("iou") == 0.5
    assert search.scores("miou")[2] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="criterion"):
        search.scores("f1")
    with pytest.raises(ValueError, match="thresholds"):
        ThresholdSearch([1.5])


def test_choose_threshold_stores_into_model(synthetic_batch):
    model = make_model()
    t, scores = choose_threshold(model, [synthetic_batch, synthetic_batch])
    assert model.occupancy_threshold.item() == pytest.approx(t)
    assert t in scores and model.training  # restored mode
    with pytest.raises(ValueError, match="empty"):
        choose_threshold(model, [])
    no_gt = {k: v for k, v in synthetic_batch.items() if k != "occ"}
    with pytest.raises(ValueError, match="'occ'"):
        choose_threshold(model, [no_gt])


def test_per_class_thresholds_maximise_each_class_iou():
    # Class 4 voxels are faint (opacity ~0.2), class 11 ones opaque (~0.8); free voxels lie at
    # 0.1 (predicted 4) and 0.5 (predicted 11). One threshold must sacrifice one class;
    # per-class thresholds separate both: 4 at 0.15, 11 at 0.6.
    gt = np.array([4] * 10 + [11] * 10 + [FREE_ID] * 20)
    cls = np.array([4] * 10 + [11] * 10 + [4] * 10 + [11] * 10)
    op = np.array([0.2] * 10 + [0.8] * 10 + [0.1] * 10 + [0.5] * 10)
    search = ThresholdSearch([0.05, 0.15, 0.3, 0.6])
    search.update(torch.tensor(op), torch.tensor(cls), torch.tensor(gt))
    per_class = search.best_per_class()
    assert per_class[4] == 0.15 and per_class[11] == 0.6
    single = search.best("miou")
    assert per_class[0] == single  # absent classes fall back to the single best one
    # The readout with them is exact on this toy: mIoU 1 where no single threshold gets there.
    pred = readout_occupancy(
        torch.tensor(op)[None].float(),
        torch.nn.functional.one_hot(torch.tensor(cls), 17)[None].float(),
        torch.tensor(per_class, dtype=torch.float32),
        (40, 1, 1),
    )
    assert pred.view(-1).tolist() == gt.tolist()
    assert max(search.scores("miou")) < 1.0


def test_choose_per_class_thresholds_stores_them_and_readout_uses_them(synthetic_batch):
    model = make_model()
    assert bool((model.class_thresholds < 0).all())  # unset: the single threshold applies
    choose_threshold(model, [synthetic_batch], per_class=True)
    t = model.class_thresholds
    assert bool(((t >= 0) & (t < 1)).all())
    model.eval()
    with torch.no_grad():
        out = model(synthetic_batch, render=False)
    g = out.gaussians
    expected = readout_occupancy(g.opacities, g.logits, t, out.grid_shape)
    assert torch.equal(model.readout(out), expected)
    # A checkpoint state without per-class thresholds (older runs) loads as "unset".
    state = {k: v for k, v in model.state_dict().items() if k != "class_thresholds"}
    fresh = make_model()
    fresh.load_state_dict(state, strict=True)
    assert bool((fresh.class_thresholds < 0).all())
    with pytest.raises(ValueError, match="per_class"):
        choose_threshold(model, [synthetic_batch], criterion="iou", per_class=True)
    with pytest.raises(ValueError, match="thresholds"):
        model.set_class_thresholds([0.5] * 3)


def _items(batch, tokens):
    """Unbatched dataset items (as Img2OccDataset returns them) from a B = 1 batch."""
    items = []
    for i, tok in enumerate(tokens):
        item = {k: v[0] for k, v in batch.items() if isinstance(v, torch.Tensor)}
        item["meta"] = {"sample_token": tok, "scene": "scene-0001"}
        if i == 1:  # a sample without Occ3D GT: masks come from camera visibility
            for k in ("occ", "mask_lidar", "mask_camera"):
                item.pop(k)
        items.append(item)
    return items


def test_export_writes_occ3d_layout_labels(synthetic_batch, tmp_path):
    model = make_model()
    model.set_threshold(0.09)  # near the initial opacities: a mix of occupied and free
    items = _items(synthetic_batch, ["tok0a", "tok1b", "tok2c"])
    # mixed items cannot share a batch (missing keys), so export one at a time
    paths = export_occupancy(model, items, tmp_path, batch_size=1, progress=False)
    assert [p.relative_to(tmp_path).as_posix() for p in paths] == [
        f"gts/scene-0001/{t}/labels.npz" for t in ("tok0a", "tok1b", "tok2c")
    ]
    model.eval()
    with torch.no_grad():
        out = model(synthetic_batch, render=False)
        want = model.readout(out)[0].numpy()
    for i, p in enumerate(paths):
        labels = load_occ3d_labels(p, expected_shape=TEST_GRID.shape)
        np.testing.assert_array_equal(labels.semantics, want)
        assert 0 < (labels.semantics != FREE_ID).sum() < labels.semantics.size
        if i == 1:
            seen = (out.visibility[0] > 0).numpy().astype(np.uint8)
            np.testing.assert_array_equal(labels.mask_camera, seen)
        else:
            np.testing.assert_array_equal(
                labels.mask_camera, synthetic_batch["mask_camera"][0].numpy().astype(np.uint8)
            )


def test_export_rejects_unsafe_names(synthetic_batch, tmp_path):
    model = make_model()
    items = _items(synthetic_batch, ["../../etc"])
    with pytest.raises(ValueError, match="meta.sample_token"):
        export_occupancy(model, items, tmp_path, progress=False)
    with pytest.raises(ValueError, match="batch_size"):
        export_occupancy(model, items, tmp_path, batch_size=0, progress=False)


def test_draw_views_writes_png(synthetic_batch, tmp_path):
    from PIL import Image

    model = make_model()
    model.eval()
    with torch.no_grad():
        out = model(synthetic_batch)
    path = draw_views(synthetic_batch, out, tmp_path / "views.png")
    img = Image.open(path)
    assert img.size[0] > 600 and img.size[1] > 600  # six rows of four panels
    with pytest.raises(ValueError, match="sample"):
        draw_views(synthetic_batch, out, tmp_path / "x.png", sample=3)
