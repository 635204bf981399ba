"""The official nuScenes devkit as a test oracle, in its own cached virtual environment.

The devkit pins numpy < 2 and depends on pyquaternion, so it cannot live next to the package's
runtime dependencies. :func:`devkit_python` builds ``.cache/devkit-venv`` once (pip, from the
package registry) and returns its interpreter; :func:`run_devkit` runs a snippet there and
returns what it printed as JSON.

Set ``RENDERWORLD_DEVKIT_VENV`` to reuse a venv elsewhere. When pip cannot reach the package
registry (an offline machine such as a lent GPU box) and no built venv is cached, the tests that
use :func:`run_devkit` skip and say so; with ``RENDERWORLD_DEVKIT_REQUIRED=1`` (CI) they fail with
the pip log instead. Any other pip failure fails the test.
"""

from __future__ import annotations

import fcntl
import json
import os
import subprocess
import sys
import textwrap
import venv
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
DEVKIT_SPEC = ("nuscenes-devkit==1.2.0", "numpy<2")
_STAMP = ".devkit-ready"
# What pip prints when the registry cannot be reached (DNS, no route, time-outs, empty index).
_OFFLINE_MARKS = (
    "NewConnectionError",
    "Network is unreachable",
    "Temporary failure in name resolution",
    "Name or service not known",
    "ConnectTimeoutError",
    "ReadTimeoutError",
    "(from versions: none)",
)


class DevkitUnavailable(RuntimeError):
    """The devkit venv cannot be built because the package registry is out of reach."""


def devkit_venv_dir() -> Path:
    """Devkit venv dir: ``RENDERWORLD_DEVKIT_VENV`` or ``<repo>/.cache/devkit-venv``."""
    env = os.environ.get("RENDERWORLD_DEVKIT_VENV")
    return Path(env) if env else REPO_ROOT / ".cache" / "devkit-venv"


def devkit_python() -> Path:
    """Return the devkit venv's python, building the venv once (file-locked, cached).

    Raises:
        DevkitUnavailable: when pip cannot reach the registry (its output says so).
        RuntimeError: with pip's output when the venv cannot be built for another reason.
    """
    root = devkit_venv_dir()
    py = root / "bin" / "python"
    if (root / _STAMP).exists():
        return py
    root.parent.mkdir(parents=True, exist_ok=True)
    with open(root.parent / ".devkit-venv.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if (root / _STAMP).exists():
            return py
        if not py.exists():
            venv.EnvBuilder(with_pip=True, clear=True).create(root)
        cmd = [str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check", *DEVKIT_SPEC]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            log = f"{proc.stdout}\n{proc.stderr}"
            offline = any(mark in log for mark in _OFFLINE_MARKS)
            error = DevkitUnavailable if offline else RuntimeError
            raise error(f"building the nuScenes devkit venv at {root} failed:\n{log}")
        (root / _STAMP).write_text(" ".join(DEVKIT_SPEC))
    return py


def run_devkit(snippet: str, *args: str, timeout: float = 600) -> object:
    """Run a Python snippet in the devkit venv and parse the JSON it prints last.

    Args:
        snippet: Python source; it must ``print(json.dumps(...))`` as its last output line.
            ``sys.argv[1:]`` holds ``args``.
        *args: string arguments passed to the snippet.
        timeout: seconds.

    Returns:
        The decoded JSON value.

    Raises:
        RuntimeError: with the snippet's stderr when it fails.
        pytest.skip.Exception: when the registry is out of reach and
            ``RENDERWORLD_DEVKIT_REQUIRED`` is not set.
    """
    try:
        py = devkit_python()
    except DevkitUnavailable as err:
        if os.environ.get("RENDERWORLD_DEVKIT_REQUIRED", "") not in ("", "0"):
            raise
        import pytest

        reason = str(err).strip().splitlines()[-1][:200]
        pytest.skip(
            "the nuScenes devkit venv cannot be built: pip cannot reach the package registry "
            f"({reason}); RENDERWORLD_DEVKIT_REQUIRED=1 makes this a failure"
        )
    proc = subprocess.run(
        [str(py), "-c", textwrap.dedent(snippet), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")},
    )
    if proc.returncode != 0:
        raise RuntimeError(f"devkit snippet failed (rc={proc.returncode}):\n{proc.stderr[-4000:]}")
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    if not lines:
        raise RuntimeError(f"devkit snippet printed nothing; stderr:\n{proc.stderr[-4000:]}")
    return json.loads(lines[-1])


if __name__ == "__main__":  # pragma: no cover - manual helper
    print(devkit_python())
    sys.exit(0)
