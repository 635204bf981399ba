"""A small resumable pipeline runner: steps are commands with fingerprinted inputs.

Each step writes into its own output folder and, when it succeeds, a stamp
``<out_dir>/.step-done.json`` holding the fingerprint of what it was run from: its command,
the fingerprints of the steps it depends on, and the content of the files and code folders it
names. Re-running the pipeline skips every step whose stamp matches; a step that was
interrupted has no stamp and runs again (training steps resume from their own checkpoints).

Used by ``tools/run_pipeline.py`` (``make demo``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["Step", "StepResult", "PipelineError", "run_steps", "fingerprint_paths"]

STAMP = ".step-done.json"


class PipelineError(RuntimeError):
    """A step failed; the message names the step, its exit code and its log file."""


@dataclass(frozen=True)
class Step:
    """One pipeline step.

    Attributes:
        name: short unique id (also the log file name).
        description: one line shown in the progress header.
        command: argv, run from ``cwd``.
        out_dir: folder the step writes; its stamp lives there.
        depends_on: names of earlier steps whose outputs this step reads.
        inputs: files or folders whose content is part of the fingerprint (configs, code).
        resume_args: arguments appended when ``resume_marker`` exists (an interrupted run to
            continue); not part of the fingerprint.
        resume_marker: a file whose presence means the step can resume (e.g. ``last.pt``).
    """

    name: str
    description: str
    command: tuple[str, ...]
    out_dir: Path
    depends_on: tuple[str, ...] = ()
    inputs: tuple[Path, ...] = ()
    resume_args: tuple[str, ...] = ()
    resume_marker: Path | None = None


@dataclass
class StepResult:
    """What happened to a step: ``status`` is ``"ran"`` or ``"skipped"``.

    ``seconds`` is this run's time for a step that ran, the recorded time of the run that made
    its outputs for a skipped one.
    """

    name: str
    status: str
    seconds: float
    fingerprint: str
    log: Path | None = None
    extra: dict = field(default_factory=dict)


def fingerprint_paths(paths: Sequence[Path], suffixes=(".py", ".yaml", ".json", ".toml")) -> str:
    """SHA-256 over the content of files (folders: their files with ``suffixes``, sorted)."""
    h = hashlib.sha256()
    for p in paths:
        p = Path(p)
        files = sorted(f for f in p.rglob("*") if f.suffix in suffixes) if p.is_dir() else [p]
        for f in files:
            if "__pycache__" in f.parts or not f.is_file():
                continue
            h.update(str(f.relative_to(p.parent) if p.is_dir() else f.name).encode())
            h.update(f.read_bytes())
    return h.hexdigest()


def _step_fingerprint(step: Step, upstream: dict[str, str]) -> str:
    h = hashlib.sha256()
    h.update(json.dumps(list(step.command)).encode())
    for dep in step.depends_on:
        if dep not in upstream:
            raise ValueError(f"step {step.name!r}: depends_on names unknown step {dep!r}")
        h.update(upstream[dep].encode())
    h.update(fingerprint_paths(step.inputs).encode())
    return h.hexdigest()[:16]


def _read_stamp(step: Step) -> dict | None:
    path = step.out_dir / STAMP
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _write_stamp(step: Step, payload: dict) -> None:
    step.out_dir.mkdir(parents=True, exist_ok=True)
    tmp = step.out_dir / (STAMP + ".tmp")
    tmp.write_text(json.dumps(payload, indent=2))
    os.replace(tmp, step.out_dir / STAMP)


def run_steps(
    steps: Sequence[Step],
    log_dir: Path,
    cwd: Path,
    force: Sequence[str] = (),
    env: dict[str, str] | None = None,
    echo=print,
) -> list[StepResult]:
    """Run steps in order, skipping those whose stamp matches their fingerprint.

    Args:
        steps: the steps, in dependency order.
        log_dir: where each step's combined stdout/stderr goes (``<name>.log``).
        cwd: working directory of the commands.
        force: names of steps to re-run even when up to date (``"all"`` for every step).
        env: environment for the commands (default: this process's).
        echo: where progress lines go.

    Returns:
        One :class:`StepResult` per step.

    Raises:
        PipelineError: when a command exits non-zero (no stamp is written for it, so the next
            run retries it; earlier steps stay done).
    """
    names = [s.name for s in steps]
    if len(set(names)) != len(names):
        raise ValueError(f"steps: names must be unique, got {names}")
    log_dir = Path(log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    upstream: dict[str, str] = {}
    results: list[StepResult] = []
    for i, step in enumerate(steps, 1):
        fp = _step_fingerprint(step, upstream)
        upstream[step.name] = fp
        stamp = _read_stamp(step)
        header = f"[{i}/{len(steps)}] {step.name}: {step.description}"
        if (
            stamp
            and stamp.get("fingerprint") == fp
            and step.name not in force
            and "all" not in force
        ):
            echo(f"{header} — up to date, skipped (ran in {stamp.get('seconds', 0):.0f} s before)")
            results.append(StepResult(step.name, "skipped", float(stamp.get("seconds", 0.0)), fp))
            continue
        if stamp and step.out_dir.exists():
            # It ran before from other inputs: its outputs are stale, start it over (before
            # deciding whether to resume, so a stale checkpoint is never continued).
            echo(f"{header}\n    inputs changed since the last run: clearing {step.out_dir}")
            shutil.rmtree(step.out_dir)
        command = list(step.command)
        if step.resume_marker is not None and Path(step.resume_marker).exists():
            command += list(step.resume_args)
            echo(f"{header} — resuming from {step.resume_marker}")
        else:
            echo(header)
        echo(f"    $ {' '.join(command)}")
        log = log_dir / f"{step.name}.log"
        seconds = _run_logged(step.name, command, log, cwd, env)
        _write_stamp(step, {"fingerprint": fp, "seconds": seconds, "command": step.command})
        echo(f"    done in {seconds:.0f} s")
        results.append(StepResult(step.name, "ran", seconds, fp, log))
    return results


def _run_logged(name: str, command: list[str], log: Path, cwd: Path, env) -> float:
    """Run one step's command, its output both indented on stdout and in ``log``; seconds taken.

    Raises:
        PipelineError: the command exited non-zero.
    """
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.Popen(
            command,
            cwd=cwd,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            bufsize=1,
        )
        assert proc.stdout is not None
        for line in proc.stdout:
            fh.write(line)
            sys.stdout.write("    " + line)
            sys.stdout.flush()
        rc = proc.wait()
    seconds = time.perf_counter() - t0
    if rc != 0:
        raise PipelineError(
            f"step {name!r} failed with exit code {rc} after {seconds:.0f} s; "
            f"log: {log}. Re-run to retry it (finished steps are kept)."
        )
    return seconds
