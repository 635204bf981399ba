"""Sparse 2-D label files and infos parquet files: round trips, densify rule, errors."""

import numpy as np
import pandas as pd
import pytest

from renderworld.data import (
    IGNORE_LABEL,
    DatasetError,
    SparseLabels2D,
    densify_labels2d,
    load_infos,
    load_labels2d,
    save_labels2d,
)
from renderworld.data.infos import infos_schema, write_infos
from renderworld.data.labels2d import read_labels2d_params


def sparse(u, v, d, lab, h, w):
    return SparseLabels2D(
        np.asarray(u, np.uint16),
        np.asarray(v, np.uint16),
        np.asarray(d, np.float32),
        np.asarray(lab, np.uint8),
        h,
        w,
    )


def test_round_trip_and_densify(tmp_path):
    a = sparse([0, 3], [1, 2], [5.0, 7.5], [4, 11], 4, 6)
    b = sparse([], [], [], [], 2, 3)
    path = save_labels2d(tmp_path / "x" / "s.npz", ["A", "B"], [a, b], {"scale": 0.5})
    cams, (a2, b2) = load_labels2d(path)
    assert cams == ["A", "B"] and read_labels2d_params(path) == {"scale": 0.5}
    for x, y in ((a, a2), (b, b2)):
        for key in ("u", "v", "depth", "label"):
            np.testing.assert_array_equal(getattr(x, key), getattr(y, key))
            assert getattr(x, key).dtype == getattr(y, key).dtype
    depth, sem = a2.densify()
    assert depth.shape == (4, 6) and depth.dtype == np.float32 and sem.dtype == np.uint8
    assert depth[1, 0] == 5.0 and depth[2, 3] == 7.5 and (depth > 0).sum() == 2
    assert sem[1, 0] == 4 and sem[2, 3] == 11 and (sem == IGNORE_LABEL).sum() == 22
    assert not list(tmp_path.glob("x/*.tmp*"))  # atomic write leaves no temp file


def test_densify_to_a_smaller_size_keeps_the_nearest():
    # Label pixels (0, 0) and (1, 1) both fall in output pixel (0, 0) at half size.
    lab = sparse([0, 1, 3], [0, 1, 3], [9.0, 4.0, 2.0], [15, 4, 11], 4, 4)
    depth, sem = densify_labels2d(lab, (2, 2))
    np.testing.assert_array_equal(depth, [[4.0, 0.0], [0.0, 2.0]])
    np.testing.assert_array_equal(sem, [[4, IGNORE_LABEL], [IGNORE_LABEL, 11]])
    with pytest.raises(ValueError, match=r"size: expected positive \(H, W\)"):
        densify_labels2d(lab, (0, 2))


def test_save_validates(tmp_path):
    with pytest.raises(ValueError, match=r"labels\[A\]: pixel outside the 2x2 map"):
        save_labels2d(tmp_path / "s.npz", ["A"], [sparse([2], [0], [1.0], [1], 2, 2)])
    bad = SparseLabels2D(
        np.zeros(1, np.int64),
        np.zeros(1, np.uint16),
        np.ones(1, np.float32),
        np.zeros(1, np.uint8),
        2,
        2,
    )
    with pytest.raises(ValueError, match=r"labels\[A\].u: expected \[1\] uint16"):
        save_labels2d(tmp_path / "s.npz", ["A"], [bad])
    with pytest.raises(ValueError, match=r"cameras/labels: expected equal lengths"):
        save_labels2d(tmp_path / "s.npz", ["A", "B"], [])


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(DatasetError, match=r"nope.npz: 2-D labels file not found"):
        load_labels2d(tmp_path / "nope.npz")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match=r"junk.npz: not a readable .npz"):
        load_labels2d(junk)
    partial = tmp_path / "partial.npz"
    np.savez(partial, cameras=np.array(["A"]), height=np.array([2]), width=np.array([2]))
    with pytest.raises(DatasetError, match=r"partial.npz: 2-D labels file lacks 'cam0_u"):
        load_labels2d(partial)


def row(**overrides):
    """A valid infos row with neutral values."""
    out = {}
    for field in infos_schema():
        t = field.type
        if hasattr(t, "list_size") and t.list_size > 0 and str(t.value_type) == "bool":
            out[field.name] = [False] * t.list_size
        elif hasattr(t, "list_size") and t.list_size > 0 and field.name != "future_boxes":
            out[field.name] = [0.0] * t.list_size
        elif field.name == "future_boxes":
            out[field.name] = [[] for _ in range(7)]
        elif str(t) == "string":
            out[field.name] = ""
        else:
            out[field.name] = 0
    out.update(overrides)
    return out


def test_infos_round_trip_sorted(tmp_path):
    rows = [
        row(scene_name="b", scene_index=1, frame_index=0, sample_token="t2"),
        row(
            scene_name="a",
            scene_index=0,
            frame_index=1,
            sample_token="t1",
            future_boxes=[[[1, 2, 3, 4, 0.5, 4, 0]]] + [[] for _ in range(6)],
        ),
        row(scene_name="a", scene_index=0, frame_index=0, sample_token="t0"),
    ]
    path = write_infos(rows, tmp_path / "infos_train.parquet", metadata={"version": "v"})
    df = load_infos(tmp_path, "train")
    assert df["sample_token"].tolist() == ["t0", "t1", "t2"]
    assert df.attrs["infos_dir"] == str(tmp_path) and df.attrs["metadata"]["version"] == "v"
    assert list(df.iloc[1]["future_boxes"][0][0]) == [1, 2, 3, 4, 0.5, 4, 0]
    assert path.name == "infos_train.parquet"


def test_infos_errors(tmp_path):
    with pytest.raises(ValueError, match=r"rows: expected the infos columns; missing \['split'\]"):
        r = row()
        del r["split"]
        write_infos([r], tmp_path / "x.parquet")
    with pytest.raises(DatasetError, match=r"x.parquet: infos file not found"):
        load_infos(tmp_path / "x.parquet")
    pd.DataFrame({"a": [1]}).to_parquet(tmp_path / "old.parquet")
    with pytest.raises(DatasetError, match=r"old.parquet: infos schema version None, expected 2"):
        load_infos(tmp_path / "old.parquet")
    with pytest.raises(ValueError, match=r"split: required when path is a folder"):
        load_infos(tmp_path)


def test_infos_split_all_reads_every_split_of_the_folder(tmp_path):
    meta = {"version": "v"}
    val = [
        row(scene_name="b", scene_index=1, frame_index=1, sample_token="b1", split="val"),
        row(scene_name="b", scene_index=1, frame_index=0, sample_token="b0", split="val"),
    ]
    write_infos(val, tmp_path / "infos_val.parquet", metadata=meta)
    train = [
        row(scene_name="c", scene_index=2, frame_index=0, sample_token="c0", split="train"),
        row(scene_name="a", scene_index=0, frame_index=0, sample_token="a0", split="train"),
    ]
    write_infos(train, tmp_path / "infos_train.parquet", metadata=meta)
    df = load_infos(tmp_path, "all")
    # Sorted like one split: by scene, then frame, whichever file a scene came from.
    assert df["sample_token"].tolist() == ["a0", "b0", "b1", "c0"]
    assert df["split"].tolist() == ["train", "val", "val", "train"]
    assert df.attrs["splits"] == ["train", "val"] and df.attrs["metadata"]["version"] == "v"
    assert df.attrs["infos_dir"] == str(tmp_path)
    assert df.index.tolist() == [0, 1, 2, 3]
    # Errors name the folder: none there, a token in two files, files of two conversions.
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError, match=rf"{empty}: split 'all' found no infos_<split>"):
        load_infos(empty, "all")
    write_infos([row(scene_name="a", scene_index=0, frame_index=0, sample_token="a0")],
                tmp_path / "infos_extra.parquet", metadata=meta)  # fmt: skip
    with pytest.raises(DatasetError, match=r"sample token 'a0' is in two infos files"):
        load_infos(tmp_path, "all")
    write_infos([row(scene_name="d", scene_index=3, frame_index=0, sample_token="d0")],
                tmp_path / "infos_extra.parquet", metadata={"version": "w"})  # fmt: skip
    with pytest.raises(DatasetError, match=r"infos_train.parquet and infos_extra.parquet come from "
                                           r"different conversions"):  # fmt: skip
        load_infos(tmp_path, "all")
