"""A small resumable pipeline runner: steps are commands with fingerprinted inputs.

Each step writes into its own output folder and, when it succeeds, a stamp
``<out_dir>/.step-done.json`` holding the fingerprint of what it was run from: its command,
the fingerprints of the steps it depends on, and the content of the files and code folders it
names. Re-running the pipeline skips every step whose stamp matches; a step that was
interrupted has no stamp and runs again (training steps resume from their own checkpoints).

Steps that keep one core busy (``Step.cores=1``: the simulator, the converters) run side by
side when the machine has cores to spare; every other step has the machine to itself. A step
starts once its dependencies have finished and its cores are free, in list order: it may pass
an earlier step that waits for a dependency, never one that waits for cores.

Used by ``tools/run_pipeline.py`` (``make demo``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["Step", "StepResult", "PipelineError", "fingerprint_paths", "machine_cores", "run_steps"]

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
        cores: cores the step keeps busy when another step may run beside it; None: all of
            them (the step runs alone). Not part of the fingerprint.
    """

    name: str
    description: str
    command: tuple[str, ...]
    out_dir: Path
    depends_on: tuple[str, ...] = ()
    inputs: tuple[Path, ...] = ()
    resume_args: tuple[str, ...] = ()
    resume_marker: Path | None = None
    cores: int | None = None


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


def machine_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS reports one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def run_steps(
    steps: Sequence[Step],
    log_dir: Path,
    cwd: Path,
    force: Sequence[str] = (),
    env: dict[str, str] | None = None,
    echo=print,
    cores: int | None = None,
) -> list[StepResult]:
    """Run steps, skipping those whose stamp matches their fingerprint.

    Steps start in list order once their dependencies have finished; ``Step.cores=1`` steps
    share the machine's ``cores`` (their output lines are then prefixed with the step name),
    every other step runs alone.

    Args:
        steps: the steps, in dependency order.
        log_dir: where each step's combined stdout/stderr goes (``<name>.log``).
        cwd: working directory of the commands.
        force: names of steps to re-run even when up to date (``"all"`` for every step).
        env: environment for the commands (default: this process's).
        echo: where progress lines go.
        cores: cores to share among steps (default :func:`machine_cores`; 1: one step at a
            time).

    Returns:
        One :class:`StepResult` per step, in the order of ``steps``.

    Raises:
        PipelineError: when a command exits non-zero (no stamp is written for it, so the next
            run retries it; earlier steps stay done). Steps running beside it finish first.
        ValueError: duplicate step names, an unknown dependency or ``cores`` not an int >= 1.
    """
    names = [s.name for s in steps]
    if len(set(names)) != len(names):
        raise ValueError(f"steps: names must be unique, got {names}")
    if cores is None:
        cores = machine_cores()
    elif isinstance(cores, bool) or not isinstance(cores, int) or cores < 1:
        raise ValueError(f"cores: expected an int >= 1 or null, got {cores!r}")
    log_dir = Path(log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    upstream: dict[str, str] = {}
    results: dict[str, StepResult] = {}
    todo: list[tuple[Step, str, bool]] = []  # (step, header, ran before from other inputs)
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
            results[step.name] = StepResult(
                step.name, "skipped", float(stamp.get("seconds", 0.0)), fp
            )
        else:
            todo.append((step, header, stamp is not None))
    _Scheduler(todo, upstream, results, log_dir, cwd, env, echo, cores).run()
    return [results[n] for n in names]


class _Scheduler:
    """Starts the steps to run as their dependencies finish and cores free up (``run_steps``)."""

    def __init__(self, todo, fingerprints, results, log_dir, cwd, env, echo, cores):
        self.todo, self.fps, self.results = list(todo), fingerprints, results
        self.log_dir, self.cwd, self.env, self.echo, self.cores = log_dir, cwd, env, echo, cores
        self.done = threading.Condition()
        self.running: dict[str, int] = {}  # step name -> cores held
        self.finished: list[tuple[Step, float | BaseException]] = []
        self.lock = threading.Lock()  # one output line at a time

    def _cores(self, step: Step) -> int:
        return self.cores if step.cores is None else min(max(1, step.cores), self.cores)

    def run(self) -> None:
        failure: BaseException | None = None
        with self.done:
            while self.todo or self.running:
                if failure is None:
                    self._start_what_fits()
                if not self.running:
                    break
                while not self.finished:
                    self.done.wait()
                step, outcome = self.finished.pop(0)
                del self.running[step.name]
                if isinstance(outcome, BaseException):
                    failure = failure or outcome
                    continue
                fp = self.fps[step.name]
                _write_stamp(step, {"fingerprint": fp, "seconds": outcome, "command": step.command})
                self._say(f"    {step.name} done in {outcome:.0f} s")
                log = self.log_dir / f"{step.name}.log"
                self.results[step.name] = StepResult(step.name, "ran", outcome, fp, log)
        if failure is not None:
            raise failure

    def _start_what_fits(self) -> None:
        free = self.cores - sum(self.running.values())
        unfinished = {s.name for s, _, _ in self.todo} | set(self.running)
        for entry in list(self.todo):
            step, header, stale = entry
            if unfinished.intersection(step.depends_on):
                continue  # waits for a dependency: later steps may start first
            need = self._cores(step)
            if need > free or (need == self.cores and self.running):
                return  # waits for cores: nothing after it starts first
            self.todo.remove(entry)
            self.running[step.name] = need
            free -= need
            self._start(step, header, stale, shared=need < self.cores)

    def _start(self, step: Step, header: str, stale: bool, shared: bool) -> None:
        if stale and step.out_dir.exists():
            # It ran before from other inputs: its outputs are stale, start it over (before
            # deciding whether to resume, so a stale checkpoint is never continued).
            header += f"\n    inputs changed since the last run: clearing {step.out_dir}"
            shutil.rmtree(step.out_dir)
        command = list(step.command)
        if step.resume_marker is not None and Path(step.resume_marker).exists():
            command += list(step.resume_args)
            header += f" — resuming from {step.resume_marker}"
        self._say(f"{header}\n    $ {' '.join(command)}")
        prefix = f"    [{step.name}] " if shared else "    "
        log = self.log_dir / f"{step.name}.log"

        def work():
            try:
                outcome = _run_logged(step.name, command, log, self.cwd, self.env, prefix, self)
            except BaseException as err:  # reported by run() once the others finish
                outcome = err
            with self.done:
                self.finished.append((step, outcome))
                self.done.notify()

        threading.Thread(target=work, name=f"step-{step.name}", daemon=True).start()

    def _say(self, text: str) -> None:
        with self.lock:
            self.echo(text)

    def write(self, line: str) -> None:
        """One line of a step's output on this process's stdout."""
        with self.lock:
            sys.stdout.write(line)
            sys.stdout.flush()


def _run_logged(name, command, log: Path, cwd: Path, env, prefix: str, out) -> float:
    """Run one step's command, its output both on stdout (``out.write``, each line after
    ``prefix``) and in ``log``; seconds taken.

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
            out.write(prefix + line)
        rc = proc.wait()
    seconds = time.perf_counter() - t0
    if rc != 0:
        raise PipelineError(
            f"step {name!r} failed with exit code {rc} after {seconds:.0f} s; "
            f"log: {log}. Re-run to retry it (finished steps are kept)."
        )
    return seconds
