"""Bad scene descriptions fail with a clear ValueError before anything is written."""

from __future__ import annotations

import pytest

from renderworld.sim import ObjectSpec, SceneSpec, SimConfig, simulate


def _config(**scene) -> SimConfig:
    return SimConfig(
        keyframes=2,
        scenes=[SceneSpec(num_moving=0, num_pedestrians=0, **scene)],
        scene_names=["scene-0061"],
    )


def _assert_nothing_written(tmp_path):
    assert list(tmp_path.iterdir()) == [], "a failed run must not leave files behind"


@pytest.mark.parametrize(
    "config, match",
    [
        (lambda: _config(objects=[ObjectSpec("vehicle.spaceship", 10.0, 12.0)]), "unknown class"),
        (lambda: _config(objects=[ObjectSpec("animal", 10.0, 12.0)]), "is not simulated"),
        (
            lambda: _config(
                objects=[
                    ObjectSpec("static.manmade", 30.0, 30.0, size=(10.0, 10.0, 8.0)),
                    ObjectSpec("vehicle.car", 33.0, 31.0),
                ]
            ),
            r"objects\[1\]: overlaps static object scene.objects\[0\]",
        ),
        (lambda: _config(route=[[0.0, -1.75], [2.0, 2.0], [2.0, 40.0]]), "leaves the driveable"),
        (
            lambda: _config(lanes=1, objects=[ObjectSpec("vehicle.car", 6.0, -1.75)]),
            "blocks the ego route",
        ),
        (lambda: _config(kind="straight", behaviour="turn_left"), "turn only on intersection"),
        (lambda: _config(kind="roundabout"), r"scenes\[0\].kind: expected one of"),
    ],
)
def test_bad_scene_raises_before_writing(tmp_path, config, match):
    with pytest.raises(ValueError, match=match):
        simulate(config(), tmp_path / "out", progress=False)
    _assert_nothing_written(tmp_path)


def test_zero_keyframes_and_zero_image_size_raise(tmp_path):
    with pytest.raises(ValueError, match=r"keyframes: expected an integer >= 1, got 0"):
        simulate(SimConfig.from_dict({"keyframes": 0}), tmp_path / "out")
    with pytest.raises(ValueError, match=r"image_size: expected a positive image size 'WxH'"):
        SimConfig.from_dict({"image_size": "0x225"})
    with pytest.raises(ValueError, match=r"sensors.image_width: expected a positive integer"):
        SimConfig.from_dict({"sensors": {"image_width": 0}})
    bad = _config()
    bad.keyframes = 0
    with pytest.raises(ValueError, match="keyframes"):
        simulate(bad, tmp_path / "out", progress=False)
    _assert_nothing_written(tmp_path)


def test_unknown_config_keys_and_types_raise():
    with pytest.raises(ValueError, match=r"config: unknown keys \['colour'\]"):
        SimConfig.from_dict({"colour": "red"})
    with pytest.raises(ValueError, match=r"scenes\[0\].effects: unknown keys \['snow'\]"):
        SimConfig.from_dict({"scenes": [{"effects": {"snow": True}}]})
    with pytest.raises(ValueError, match=r"effects.weather: expected one of"):
        SimConfig.from_dict({"scenes": [{"effects": {"weather": "hail"}}]})
    with pytest.raises(TypeError, match="config: expected a dict"):
        SimConfig.from_dict(["not", "a", "dict"])
    with pytest.raises(TypeError, match="config: expected a SimConfig"):
        simulate({"keyframes": 2}, "/nonexistent/never-written")


def test_existing_output_is_not_overwritten(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(FileExistsError, match="already exists"):
        simulate(_config(), out, progress=False)
    assert (out / "keep.txt").read_text() == "x"


def test_interrupted_run_leaves_no_dataset(tmp_path, monkeypatch):
    """A crash mid-run removes its partial directory and never creates ``out``."""
    import sys

    sim = sys.modules["renderworld.sim.simulate"]  # the module (the package exports a function)

    calls = {"n": 0}
    real = sim.render_camera

    def crash(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt("simulated interrupt")
        return real(*args, **kwargs)

    monkeypatch.setattr(sim, "render_camera", crash)
    cfg = _config()
    cfg.sensors.image_width, cfg.sensors.image_height = 64, 36
    with pytest.raises(KeyboardInterrupt):
        simulate(cfg, tmp_path / "out", progress=False)
    _assert_nothing_written(tmp_path)
