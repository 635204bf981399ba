"""Run a sweep's points (``tools/bench.py``): each in its own one-thread subprocess, reusing
those already measured, one at a time or ``jobs`` at a time.

A point's subprocess is ``python -m renderworld.bench.point <spec.json>`` (train, evaluate, time
inference, report its own peak RSS); it leaves ``<out>/points/<id>/result.json``, which a later
run reuses when its fingerprint (:func:`renderworld.bench.sweep.point_fingerprint`) matches.
Planner points time latency only: they always run one at a time, after the training points.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Any

from renderworld.bench.knobs import STAGE_METRICS
from renderworld.bench.sweep import BenchPoint, point_fingerprint, point_spec

__all__ = ["run_point", "run_sweep"]

#: Stages whose points run one at a time whatever ``jobs`` is (they measure latency only).
ALONE = ("planner",)


def run_point(
    point: BenchPoint, point_dir: Path, infer_frames: int, repo: Path, timeout_s: float | None
) -> dict[str, Any]:
    """Run one point in a fresh subprocess (1 torch thread) and return its ``result.json``.

    The previous contents of ``point_dir`` are removed first (an interrupted point restarts).

    Raises:
        RuntimeError: the subprocess failed or wrote no result; the message ends with its log.
    """
    if point_dir.exists():
        shutil.rmtree(point_dir)
    point_dir.mkdir(parents=True)
    spec = point_spec(point, point_dir, infer_frames, repo)
    (point_dir / "spec.json").write_text(json.dumps(spec, indent=2) + "\n")
    env = dict(os.environ)
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(repo), env.get("PYTHONPATH")]))
    cmd = [sys.executable, "-m", "renderworld.bench.point", str(point_dir / "spec.json")]
    log = point_dir / "log.txt"
    with log.open("w") as fh:
        try:
            proc = subprocess.run(
                cmd, cwd=repo, stdout=fh, stderr=subprocess.STDOUT, env=env, timeout=timeout_s
            )
            rc = proc.returncode
        except subprocess.TimeoutExpired:
            rc = "timeout"
    result = point_dir / "result.json"
    if rc != 0 or not result.is_file():
        tail = "\n".join(log.read_text(errors="replace").splitlines()[-25:])
        raise RuntimeError(f"bench point {point.point_id} failed (exit {rc}); log {log}:\n{tail}")
    return json.loads(result.read_text())


def run_sweep(
    points: Sequence[BenchPoint],
    out: Path,
    infer_frames: int = 5,
    overwrite: bool = False,
    repo: Path | None = None,
    runner: Callable[..., dict[str, Any]] = run_point,
    timeout_s: float | None = None,
    echo: Callable[[str], None] = print,
    jobs: int = 1,
) -> list[dict[str, Any]]:
    """Run (or reuse) every point and return their results in the order of ``points``.

    Args:
        points: from :func:`expand_points`.
        out: output folder; point ``i`` runs in ``<out>/points/<point_id>/``.
        infer_frames: validation samples timed per point (median reported).
        overwrite: re-run points whose stored result has the same fingerprint.
        repo: repository root (``configs/`` and the package); default: this checkout.
        runner: the function running one point (``run_point``; tests pass a fake).
        timeout_s: per-point wall-clock cap (None: none).
        echo: progress output.
        jobs: points run at once, each in its own one-thread subprocess (1: one at a time).
            Every result records it (``jobs``): a point timed beside others is slower than one
            timed alone, so compare times only between points measured with the same ``jobs``.
            Planner points (latency only) run one at a time after the others.

    Returns:
        One dict per point: the point's ``result.json`` plus ``fingerprint``, ``reused``.

    Raises:
        ValueError: ``infer_frames`` or ``jobs`` below 1.
        RuntimeError: a point failed (from ``runner``); with ``jobs > 1`` the points already
            running finish and keep their results, no new point starts.
    """
    if not isinstance(infer_frames, int) or isinstance(infer_frames, bool) or infer_frames < 1:
        raise ValueError(f"infer_frames: expected an int >= 1, got {infer_frames!r}")
    if not isinstance(jobs, int) or isinstance(jobs, bool) or jobs < 1:
        raise ValueError(f"jobs: expected an int >= 1, got {jobs!r}")
    repo = Path(repo) if repo is not None else Path(__file__).resolve().parents[2]
    out = Path(out)
    lock = threading.Lock()

    def say(line: str) -> None:  # one whole line at a time when points run side by side
        with lock:
            echo(line)

    results: list[dict[str, Any] | None] = [None] * len(points)
    todo = []
    t_sweep = time.perf_counter()
    for i, point in enumerate(points):
        fp = point_fingerprint(point, infer_frames)
        stored = out / "points" / point.point_id / "result.json"
        if not overwrite and stored.is_file():
            res = json.loads(stored.read_text())
            if res.get("fingerprint") == fp:
                say(f"[{i + 1}/{len(points)}] {point.point_id}: reused ({_summary(res)})")
                results[i] = {**res, "reused": True}
                continue
        todo.append((i, point, fp))

    def measure(i: int, point: BenchPoint, fp: str, at_once: int = jobs) -> dict[str, Any]:
        head = f"[{i + 1}/{len(points)}] {point.point_id}"
        say(f"{head}: running ...")
        pdir = out / "points" / point.point_id
        t0 = time.perf_counter()
        res = runner(point, pdir, infer_frames, repo, timeout_s)
        res = {**res, "fingerprint": fp, "point_wall_s": time.perf_counter() - t0,
               "seed": point.seed, "phase": point.phase, "claimed": point.claimed,
               "jobs": at_once}  # fmt: skip
        (pdir / "result.json").write_text(json.dumps(res, indent=2) + "\n")
        say(f"{head}: {res['point_wall_s']:.0f} s ({_summary(res)})")
        return {**res, "reused": False}

    alone = [t for t in todo if jobs == 1 or t[1].stage in ALONE]
    if len(alone) < len(todo):
        _run_parallel([t for t in todo if t not in alone], measure, jobs, results)
    for i, point, fp in alone:
        results[i] = measure(i, point, fp, 1)
    say(f"sweep: {len(points)} points in {time.perf_counter() - t_sweep:.0f} s")
    return [r for r in results if r is not None]


def _run_parallel(todo, measure, jobs, results) -> None:
    """``measure(*item)`` for every item of ``todo``, ``jobs`` at a time, into ``results``; the
    first failure stops new points from starting and is raised once the running ones end."""
    failure: BaseException | None = None
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        queue = list(todo)
        running = {}
        while queue or running:
            while queue and len(running) < jobs and failure is None:
                item = queue.pop(0)
                running[pool.submit(measure, *item)] = item[0]
            if not running:
                break
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for fut in done:
                i = running.pop(fut)
                try:
                    results[i] = fut.result()
                except Exception as err:  # noqa: BLE001 - re-raised below
                    failure = failure or err
    if failure is not None:
        raise failure


def _summary(res: Mapping[str, Any]) -> str:
    name, _, label = STAGE_METRICS[res["stage"]]["metric"]
    m = res.get("metrics", {}).get(name)
    scale = 100 if "%" in label else 1
    mtxt = f"{name}={scale * m:.2f}" if isinstance(m, (int, float)) else f"{name}=?"
    return (
        f"{mtxt}, train {res.get('train_s', float('nan')):.0f} s, "
        f"infer {res.get('infer_ms', float('nan')):.1f} ms, "
        f"peak {res.get('peak_rss_mib', float('nan')):.0f} MiB"
    )
