"""The held-out closed-loop split (``configs/sim/preset/closed_loop.yaml``): its size and mix of
behaviours, its own seed and scene names, and a few of its worlds built (one per road kind)."""

from __future__ import annotations

from collections import Counter

import pytest

from renderworld.constants import MINI_TRAIN_SCENES, MINI_VAL_SCENES
from renderworld.sim import build_world
from renderworld.sim.scene import INTERACTIONS, ROAD_KINDS
from tools.make_fixtures import CONFIG_DIR, config_from_preset

PRESET = "closed_loop"
OTHERS = sorted(p.stem for p in (CONFIG_DIR / "preset").glob("*.yaml") if p.stem != PRESET)


@pytest.fixture(scope="module")
def split():
    return config_from_preset(PRESET)


def _names(cfg) -> list[str]:
    return [name for name, _ in cfg.named_scenes]


def test_split_size_and_behaviours(split):
    assert len(split.scenes) >= 64
    assert split.keyframes == 22
    seen = Counter(s.behaviour for s in split.scenes)
    for b in INTERACTIONS:
        assert seen[b] >= 8, b
    plain = [s for s in split.scenes if s.behaviour not in INTERACTIONS]
    assert len(plain) >= 16
    assert {"cruise", "turn_left", "turn_right", "stop_and_go", "parked"} <= set(seen)
    # Log replay ends off road in lane_change_right (docs/closed_loop.md): not in this split.
    assert "lane_change_right" not in seen
    assert {s.kind for s in split.scenes} == set(ROAD_KINDS)
    assert {s.effects.weather for s in split.scenes} == {"clear", "rain", "fog"}
    assert any(s.effects.night for s in split.scenes)
    assert len({s.speed for s in split.scenes}) > 30
    # Every scene is held out (val), also in splits.json.
    assert split.split_lists() == {"val": _names(split)}


def test_own_seed_and_scene_names(split):
    assert OTHERS, "no other presets found"
    names = set(_names(split))
    assert len(names) == len(split.scenes)
    assert names.isdisjoint(MINI_TRAIN_SCENES) and names.isdisjoint(MINI_VAL_SCENES)
    for other in OTHERS:
        cfg = config_from_preset(other)
        assert split.seed != cfg.seed, other
        assert split.version != cfg.version, other
        assert names.isdisjoint(cfg.scene_names), other


def test_one_world_per_road_kind_builds(split):
    first = {}
    for i, (name, spec) in enumerate(split.named_scenes):
        first.setdefault(spec.kind, (i, name, spec))
    assert set(first) == set(ROAD_KINDS)
    # The same worlds build_worlds(split) makes: the scene index is mixed into the seed.
    for i, name, spec in first.values():
        world = build_world(name, spec, split.keyframes, split.seed, i)
        assert world.name == name and world.spec.behaviour == spec.behaviour
        assert len(world.ego.scripted) == (spec.behaviour in INTERACTIONS)
