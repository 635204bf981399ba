"""The devkit oracle skips on a machine without registry access and fails on any other error."""

import subprocess
import venv

import pytest

from tests import devkit_oracle

OFFLINE_LOG = (
    "WARNING: Retrying (Retry(total=0)) after connection broken by 'NewConnectionError(...: "
    "Failed to establish a new connection: [Errno 101] Network is unreachable')\n"
    "ERROR: Could not find a version that satisfies the requirement nuscenes-devkit==1.2.0 "
    "(from versions: none)\n"
    "ERROR: No matching distribution found for nuscenes-devkit==1.2.0\n"
)
BROKEN_LOG = "ERROR: nuscenes-devkit 1.2.0 has requirement opencv-python, but the build failed\n"


@pytest.fixture
def pip_fails(tmp_path, monkeypatch):
    """A fresh venv dir whose pip install fails with the log the test sets."""
    monkeypatch.setenv("RENDERWORLD_DEVKIT_VENV", str(tmp_path / "venv"))
    monkeypatch.delenv("RENDERWORLD_DEVKIT_REQUIRED", raising=False)
    monkeypatch.setattr(venv.EnvBuilder, "create", lambda self, root: None)
    log = {"stderr": ""}

    def run(cmd, **kwargs):
        assert cmd[1:4] == ["-m", "pip", "install"], cmd  # only pip may run
        return subprocess.CompletedProcess(cmd, 1, stdout="", stderr=log["stderr"])

    monkeypatch.setattr(devkit_oracle.subprocess, "run", run)
    return log


def test_offline_registry_skips_with_the_reason(pip_fails):
    pip_fails["stderr"] = OFFLINE_LOG
    with pytest.raises(pytest.skip.Exception, match="cannot reach the package registry"):
        devkit_oracle.run_devkit("print(1)")


def test_offline_registry_fails_when_the_devkit_is_required(pip_fails, monkeypatch):
    pip_fails["stderr"] = OFFLINE_LOG
    monkeypatch.setenv("RENDERWORLD_DEVKIT_REQUIRED", "1")
    with pytest.raises(devkit_oracle.DevkitUnavailable, match="Network is unreachable"):
        devkit_oracle.run_devkit("print(1)")


def test_other_pip_failures_fail_with_the_log(pip_fails):
    pip_fails["stderr"] = BROKEN_LOG
    with pytest.raises(RuntimeError, match="the build failed") as err:
        devkit_oracle.run_devkit("print(1)")
    assert not isinstance(err.value, devkit_oracle.DevkitUnavailable)
