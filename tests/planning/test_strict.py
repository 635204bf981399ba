"""Every bad file and bad request gets one clear error naming the file or the field."""

import json

import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID
from renderworld.planning import (
    MAX_STEP_DISPLACEMENT_M,
    PlannerSession,
    PlanRequest,
    load_planner,
    register_tokenizer,
    save_planner_bundle,
)
from tests.planning.test_api import make_planner, make_request
from tests.world.fake_tokenizer import PatchTokenizer

register_tokenizer("test_patch", PatchTokenizer)


@pytest.fixture()
def bundle(tmp_path):
    planner = make_planner()
    return save_planner_bundle(tmp_path / "planner.pt", planner.tokenizer, planner.world_model)


def _write(path, data: bytes):
    path.write_bytes(data)
    return path


@pytest.mark.parametrize("keep", [0.5, 0.9, 0.01])
def test_truncated_bundle_names_the_file(bundle, keep):
    data = bundle.read_bytes()
    bad = _write(bundle.with_name("cut.pt"), data[: int(len(data) * keep)])
    with pytest.raises(ValueError, match=r"ckpt_path .*cut\.pt: not a readable planner bundle"):
        load_planner(bad)


def test_empty_and_random_files_name_the_file(tmp_path):
    rng = np.random.default_rng(0)
    for name, data in (("empty.pt", b""), ("noise.pt", rng.bytes(4096))):
        with pytest.raises(ValueError, match=rf"ckpt_path .*{name}: not a readable planner"):
            load_planner(_write(tmp_path / name, data))


def test_json_file_names_the_file(tmp_path):
    path = tmp_path / "planner.json"
    path.write_text(json.dumps({"schema_version": 1, "stage": "planner_bundle"}))
    with pytest.raises(ValueError, match=r"ckpt_path .*planner\.json: not a readable planner"):
        load_planner(path)


def test_pickled_code_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "code.pt"
    torch.save({"stage": "planner_bundle", "fn": np.random.default_rng}, path)
    with pytest.raises(ValueError, match=r"ckpt_path .*code\.pt: not a readable planner bundle"):
        load_planner(path)


@pytest.mark.parametrize(
    "payload, match",
    [
        (torch.zeros(3), r"not a planner bundle \(expected a dict .* got Tensor\)"),
        ([1, 2], r"not a planner bundle \(expected a dict .* got list\)"),
        ({"model": {}, "config": "x"}, r"not a planner bundle .* got \['config', 'model'\]"),
        (  # a training checkpoint of another stage
            {"model": {}, "config": "", "stage": "world_model", "schema_version": 1},
            "expected stage 'planner_bundle', got 'world_model'",
        ),
        (  # right stage, other schema
            {"stage": "planner_bundle", "schema_version": 1, "weights": {}},
            "expected keys",
        ),
    ],
)
def test_foreign_torch_files_name_the_file(tmp_path, payload, match):
    path = tmp_path / "foreign.pt"
    torch.save(payload, path)
    with pytest.raises(ValueError, match=r"ckpt_path .*foreign\.pt: .*" + match):
        load_planner(path)


def _tampered(bundle, edit):
    data = torch.load(bundle, weights_only=True)
    edit(data)
    torch.save(data, bundle)
    return bundle


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda d: d["tokenizer"].update(config=[1]), "tokenizer config: expected a dict"),
        (lambda d: d["world_model"].update(state_dict=[]), "world_model state_dict: expected"),
        (
            lambda d: d["world_model"]["state_dict"].update({"ego_head.bias": "x"}),
            "world_model state_dict: expected a dict of tensors",
        ),
        (lambda d: d["tokenizer"]["config"].update(patch=3), "tokenizer config refused"),
        (lambda d: d["world_model"]["config"].update(embed_dim=-1), "world_model config refused"),
        (lambda d: d["tokenizer"].update(kind=7), "tokenizer kind 7 is not registered"),
    ],
)
def test_malformed_bundle_contents_name_the_file(bundle, edit, match):
    with pytest.raises(ValueError, match=r"ckpt_path .*planner\.pt: " + match):
        load_planner(_tampered(bundle, edit))


def _occ(t=5):
    return np.full((t, 8, 8, 4), FREE_ID, dtype=np.uint8)


@pytest.mark.parametrize(
    "disp, match",
    [
        (np.full((4, 2), 1e9), r"ego_displacements: expected steps of at most 50 m per 0.5 s"),
        (np.array([[5, 0], [5, 0], [0, 50.01], [5, 0]], float), r"got 50\.01 m at row 2"),
        (np.array([[36, 36], [0, 0], [0, 0], [0, 0]]) * 1.0, "at most 50 m .* at row 0"),
        (np.array([[5, 0], [np.inf, 0], [5, 0], [5, 0]]), "ego_displacements: expected finite"),
        (np.array([[5, 0], [5, np.nan], [5, 0], [5, 0]]), "ego_displacements: expected finite"),
    ],
)
def test_requests_beyond_the_physical_bound_are_refused(disp, match):
    with pytest.raises(ValueError, match=match):
        PlanRequest(_occ(), disp, "straight")


def test_the_bound_itself_is_accepted_and_one_ulp_more_refused():
    m = MAX_STEP_DISPLACEMENT_M
    disp = np.array([[m, 0], [0, -m], [0.6 * m, 0.8 * m], [-m, 0]])
    PlanRequest(_occ(), disp, "straight")  # exactly the bound per step: allowed
    disp[2] = [0, np.nextafter(m, np.inf)]
    with pytest.raises(ValueError, match=f"at most {m:g} m per 0.5 s .* at row 2"):
        PlanRequest(_occ(), disp, "straight")


def test_session_refusals():
    planner = make_planner()
    session = PlannerSession(planner)
    req = make_request()
    with pytest.raises(TypeError, match="planner: expected Planner"):
        PlannerSession(object())
    with pytest.raises(ValueError, match="occupancy: expected dtype uint8"):
        session.push(req.occupancy[0].astype(np.int32))
    with pytest.raises(ValueError, match=r"occupancy: expected shape \[T, X, Y, Z\]"):
        session.push(req.occupancy[0, 0])
    with pytest.raises(ValueError, match=r"occupancy: expected class ids in \[0, 17\]"):
        session.push(req.occupancy[0] + 20)
    session.push(req.occupancy[0])
    with pytest.raises(ValueError, match=r"occupancy: expected grid \(8, 8, 4\)"):
        session.push(np.full((4, 4, 4), FREE_ID, np.uint8))
    with pytest.raises(
        ValueError, match="session: expected 5 pushed frames before planning, got 1"
    ):
        session.plan(req.ego_displacements, "left")
    for frame in req.occupancy[1:]:
        session.push(frame)
    with pytest.raises(ValueError, match="ego_displacements: expected steps of at most 50 m"):
        session.plan(np.full((4, 2), 1e9), "left")
    with pytest.raises(ValueError, match=r"ego_displacements: expected shape \[T-1, 2\]"):
        session.plan(np.zeros((3, 2)), "left")
    with pytest.raises(ValueError, match="ego_displacements: expected finite"):
        session.plan(np.full((4, 2), np.nan), "left")
    with pytest.raises(ValueError, match="command: expected one of"):
        session.plan(req.ego_displacements, "reverse")
    with pytest.raises(TypeError, match="forecast: expected a bool"):
        session.plan(req.ego_displacements, "left", forecast="no")


def test_planner_option_refusals():
    planner = make_planner()
    with pytest.raises(ValueError, match="precision: expected one of"):
        type(planner)(planner.tokenizer, planner.world_model, precision="float16")
    with pytest.raises(ValueError, match="compile: expected one of"):
        type(planner)(planner.tokenizer, planner.world_model, compile="fast")
    with pytest.raises(ValueError, match="pin_memory: only applies to CUDA devices"):
        type(planner)(planner.tokenizer, planner.world_model, pin_memory=True)
    with pytest.raises(TypeError, match="fast: expected a bool"):
        type(planner)(planner.tokenizer, planner.world_model, fast=1)
    with pytest.raises(TypeError, match="forecast: expected a bool"):
        planner.plan(make_request(), forecast=None)


def test_load_planner_passes_options(bundle):
    planner = load_planner(bundle, fast=False, precision="bfloat16")
    assert planner.fast is False and planner.precision == "bfloat16"
    with pytest.raises(ValueError, match="precision: expected one of"):
        load_planner(bundle, precision="int8")
