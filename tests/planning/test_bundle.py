import numpy as np
import pytest
import torch

from renderworld.planning import (
    BUNDLE_SCHEMA_VERSION,
    Planner,
    load_planner,
    register_tokenizer,
    save_planner_bundle,
)
from tests.planning.test_api import make_planner, make_request
from tests.world.fake_tokenizer import PatchTokenizer

register_tokenizer("test_patch", PatchTokenizer)


def perturbed_planner():
    planner = make_planner(seed=3)
    with torch.no_grad():  # a non-default tokenizer state: the bundle must carry it
        planner.tokenizer.class_of_code.copy_(torch.roll(planner.tokenizer.class_of_code, 1))
    return planner


def test_round_trip_reproduces_plans(tmp_path):
    planner = perturbed_planner()
    path = save_planner_bundle(tmp_path / "planner.pt", planner.tokenizer, planner.world_model)
    assert [p.name for p in tmp_path.iterdir()] == ["planner.pt"]  # no temp file left behind
    loaded = load_planner(path)
    assert isinstance(loaded, Planner) and loaded.config == planner.config
    for req in (make_request(seed=5), make_request(seed=6, command="left")):
        a, b = planner.plan(req), loaded.plan(req)
        np.testing.assert_array_equal(a.trajectory, b.trajectory)
        np.testing.assert_array_equal(a.occupancy_forecast, b.occupancy_forecast)
    fresh = make_planner(seed=3)  # same config, other tokenizer state -> other forecast
    req = make_request(seed=5)
    assert not np.array_equal(
        fresh.plan(req).occupancy_forecast, loaded.plan(req).occupancy_forecast
    )


def test_bundle_is_plain_weights_only_data(tmp_path):
    planner = make_planner()
    path = save_planner_bundle(tmp_path / "b.pt", planner.tokenizer, planner.world_model)
    data = torch.load(path, weights_only=True)
    assert data["schema_version"] == BUNDLE_SCHEMA_VERSION and data["stage"] == "planner_bundle"
    assert data["tokenizer"]["kind"] == "test_patch"
    assert data["world_model"]["config"] == planner.config.to_dict()


def _tamper(tmp_path, edit):
    planner = make_planner()
    path = save_planner_bundle(tmp_path / "b.pt", planner.tokenizer, planner.world_model)
    data = torch.load(path, weights_only=True)
    edit(data)
    torch.save(data, path)
    return path


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda d: d.update(stage="world_model"), "expected stage 'planner_bundle'"),
        (lambda d: d.update(schema_version=99), "expected schema_version 1 or 2"),
        (lambda d: d.update(extra=1), "expected keys"),
        (lambda d: d["tokenizer"].update(kind="nope"), "tokenizer kind 'nope' is not registered"),
        (
            lambda d: d["world_model"]["state_dict"].pop("ego_head.bias"),
            "state dict does not match",
        ),
        (lambda d: d["world_model"]["config"].update(embed_dim=32), "state dict does not match"),
        (lambda d: d["world_model"]["config"].update(bogus=1), "unknown WorldModelConfig keys"),
    ],
)
def test_strict_load_failures(tmp_path, edit, match):
    with pytest.raises(ValueError, match=match):
        load_planner(_tamper(tmp_path, edit))


def test_save_and_load_argument_errors(tmp_path):
    planner = make_planner()
    with pytest.raises(ValueError, match="ckpt_path: no such file"):
        load_planner(tmp_path / "missing.pt")
    with pytest.raises(ValueError, match="tokenizer: type Linear is not registered"):
        save_planner_bundle(tmp_path / "x.pt", torch.nn.Linear(1, 1), planner.world_model)
    with pytest.raises(ValueError, match="path: folder .* does not exist"):
        save_planner_bundle(tmp_path / "no" / "x.pt", planner.tokenizer, planner.world_model)
    with pytest.raises(TypeError, match="cls: expected an nn.Module subclass"):
        register_tokenizer("bad", int)
