import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_planning_import_is_light():
    code = (
        "import sys, renderworld.planning, renderworld.world, renderworld.metrics\n"
        "heavy = [m for m in ('hydra', 'omegaconf', 'open3d') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
        "print('ok')\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_public_names_are_exported():
    import renderworld.metrics as metrics
    import renderworld.planning as planning
    import renderworld.world as world

    for mod in (planning, world, metrics):
        assert mod.__all__ and all(hasattr(mod, n) for n in mod.__all__)
