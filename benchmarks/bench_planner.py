"""Planner latency: today's planner and the streaming / trajectory-only / fast planner side by side.

Usage::

    PYTHONPATH=. python benchmarks/bench_planner.py [--device cpu] [--threads 2 1]
        [--reps-mini 20] [--reps-occ3d 3] [--skip-occ3d] [--skip-mini] [--profile-decoder]
        [--modes today "new full" "new traj" "full bf16" "fast plan"]
        [--mini-tokenizer outputs/demo/tokenizer/checkpoints/best.pt]
        [--mini-world-model outputs/demo/world_model/checkpoints/best.pt]
    PYTHONPATH=. python benchmarks/bench_planner.py --baseline REF [--threads 1 2] ...

With ``--baseline REF`` it compares commit REF's planner with this checkout's, each in a worker
process (``planner_worker.py``: untrained models, rounds interleaved): REF's ``today`` / session
``full`` / ``traj`` beside this checkout's ``full`` / ``traj`` / ``full bf16`` and the pose-warp
world model's ``pw full`` / ``pw traj`` (and the same with the opt-in loop settings
``retain_freed_memory()`` + ``Planner(world_model_threads=1)``, rows ``new+opt``), with
``x old`` = REF's wall time / this one's.
Without it, the in-process modes below (one source tree).

Modes, all on the same tokenizer and world model weights, one new frame per plan:

* ``today``: ``Planner(fast=False).plan(request)``: the reference path (encodes all five
  history frames with ``SceneTokenizer.encode``, rolls out, decodes six frames with
  ``SceneTokenizer.decode``), i.e. what a caller of the PlanRequest API ran before streaming,
  trajectory-only planning and the fast codec. The world-model rollout code is shared with the
  new modes (its KV cache changes apply to both).
* ``new full``: ``PlannerSession`` on ``Planner(fast=True)``: ``push`` the new frame (one encode),
  ``plan(..., forecast=True)`` (rollout + fast decode of six frames).
* ``new traj``: the same with ``forecast=False`` (no occupancy decode).
* ``full bf16``: ``new full`` with ``precision="bfloat16"`` (decoder under bf16 autocast;
  the trajectory is float32's). On CPU this uses AVX-512 BF16 where the CPU has it.
* ``fast plan`` (``--modes ... "fast plan"``): ``Planner(fast=True).plan(request)``, no streaming.
* ``pw full`` / ``pw traj`` (``--modes ... "pw full" "pw traj"``): the pose-warp world model (the
  main job's kind: ``stage.forecaster=pose_warp``, anchors ``ctr_cv``) on the same tokenizer,
  session, forecast on / off. With ``--device cuda`` this is the GPU check of both world
  models in one run.
* ``pw checked``: ``pw full`` with ``check=True``: the candidates around the plan tracked and
  scored against the forecast (``renderworld.planning.checked``).
* ``pw checked traj``: ``pw traj`` with ``check=True``: the checked plan without the occupancy
  forecast (the check reads the movers' forecast, not the decoded frames): what the closed
  loop drives.

Cases:

* ``mini 50x50x4``: the demo's trained checkpoints when present (``make demo``; its world
  model is the pose-warp kind, requests carry ``ego_yaws``), else
  **untrained** models of the same sizes (experiment=tokenizer_mini / world_model_mini: AM-VAE
  latent 25x25, 64 channels, 256 codes, base 32, 1 res block, no attention; world model D=64,
  2 scales x 1 block). Latency depends on the shapes, not on the weights.
* ``Occ3D 200x200x16``: AM-VAE at the paper's sizes (``TokenizerConfig()``: latent 50x50,
  128 channels, 512 codes) + world model D=128, 4 heads, 3 scales x 2 blocks, untrained.

Rounds interleave the modes (one call of each per round) so that load from other processes on
a shared machine hits every mode alike; figures are medians over rounds after one warm-up
round, per torch intra-op thread count. ``encode`` / ``world`` / ``decode`` are the planner's
own stage timings (``PlanResult.timings``), ``wall`` the whole call (session: push + plan).
OpenMP threads wait passively (``OMP_WAIT_POLICY=PASSIVE``) unless the environment says
otherwise: spinning threads are several times slower on a busy shared CPU.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# On a CPU shared with other processes, OpenMP threads that spin-wait at every barrier steal
# the cores their peers need (measured: the mini rollout at 2 threads 685 ms spinning vs 110 ms
# passive under load ~7). Set before torch loads OpenMP; export OMP_WAIT_POLICY=ACTIVE to compare.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from renderworld.bench.planner_latency import (  # noqa: E402
    make_request,
    mini_models,
    occ3d_models,
    pose_warp_model,
    session_runner,
)
from renderworld.planning import Planner, PlannerSession, PlanRequest  # noqa: E402
from renderworld.world.tracks import clear_track_cache  # noqa: E402

DEMO = Path("outputs/demo")
STAGES = ("encode", "world_model", "decode")


def _run_today(planner: Planner, req: PlanRequest, _session) -> dict:
    clear_track_cache()  # as session_runner: each plan tracks its history once
    t0 = time.perf_counter()
    res = planner.plan(req)
    return {**res.timings, "wall": 1e3 * (time.perf_counter() - t0)}


def _run_fast_plan(planner: Planner, req: PlanRequest, _session) -> dict:
    return _run_today(planner, req, None)


def agreement(models, grid, device: str) -> str:
    """How far the new planner's outputs are from today's on the benchmark request."""
    tok, wm = models
    req = make_request(grid, wm.config.history_frames, np.random.default_rng(0))
    ref = Planner(tok, wm, device=device, fast=False).plan(req)
    out = []
    for precision in ("float32", "bfloat16"):
        new = Planner(tok, wm, device=device, precision=precision).plan(req)
        dt = float(np.abs(new.trajectory - ref.trajectory).max())
        agree = float((new.occupancy_forecast == ref.occupancy_forecast).mean())
        out.append(f"{precision}: max |traj - today| {dt:.2e} m, forecast voxels equal {agree:.6f}")
    return "; ".join(out)


MODES = (
    "today", "new full", "new traj", "full bf16", "fast plan", "pw full", "pw traj", "pw checked",
    "pw checked traj",
)  # fmt: skip


def bench_case(models, grid, device: str, reps: int, wanted) -> dict[str, dict]:
    """Median timings (ms) per mode, rounds interleaved."""
    tok, wm = models
    ref = Planner(tok, wm, device=device, fast=False)
    fast = Planner(tok, wm, device=device, fast=True)
    bf16 = Planner(tok, wm, device=device, fast=True, precision="bfloat16")
    modes = {
        "today": (ref, _run_today),
        "new full": (fast, session_runner(True)),
        "new traj": (fast, session_runner(False)),
        "full bf16": (bf16, session_runner(True)),
    }
    modes["fast plan"] = (fast, _run_fast_plan)
    planners = [fast, bf16]
    if {"pw full", "pw traj", "pw checked", "pw checked traj"} & set(wanted):
        pw = Planner(tok, pose_warp_model(wm), device=device)
        modes.update(
            {
                "pw full": (pw, session_runner(True)),
                "pw traj": (pw, session_runner(False)),
                "pw checked": (pw, session_runner(True, check=True)),  # candidates scored
                "pw checked traj": (pw, session_runner(False, check=True)),  # no occupancy
            }
        )
        planners.append(pw)
    modes = {k: v for k, v in modes.items() if k in wanted}
    req = make_request(grid, ref.config.history_frames, np.random.default_rng(0))
    sessions = {id(p): PlannerSession(p) for p in planners}
    for session in sessions.values():
        for frame in req.occupancy[:-1]:
            session.push(frame)
    runs: dict[str, list[dict]] = {m: [] for m in modes}
    for r in range(reps + 1):
        for name, (planner, run) in modes.items():
            timing = run(planner, req, sessions.get(id(planner)))
            if r:  # round 0 warms up
                runs[name].append(timing)
    return {
        name: {k: statistics.median(t[k] for t in ts) for k in (*STAGES, "wall")}
        for name, ts in runs.items()
    }


def profile_decoder(models, threads: int, rows: int = 12) -> None:
    """torch.profiler tables of one six-frame decode, reference vs fast codec (CPU)."""
    from torch.profiler import ProfilerActivity, profile

    from renderworld.tokenizer.inference import FastSceneCodec
    from renderworld.tokenizer.tokens import Tokens

    torch.set_num_threads(threads)
    tok = models[0].eval()
    g = torch.Generator().manual_seed(0)
    idx = torch.stack(
        [
            torch.randint(0, k, (6, *tok.cfg.latent_shape), generator=g)
            for k in tok.cfg.codebook_sizes
        ],
        1,
    )
    tokens = Tokens(idx, tok.cfg.codebook_sizes, tok.cfg.codebook_names)
    for name, decode in (("reference", tok.decode), ("fast", FastSceneCodec(tok).decode)):
        with torch.inference_mode():
            decode(tokens)
            t0 = time.perf_counter()
            with profile(activities=[ProfilerActivity.CPU]) as prof:
                decode(tokens)
        print(f"# {name} decode of 6 frames, {threads} thread(s): {time.perf_counter() - t0:.2f} s")
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows))


def _describe_machine(device: str) -> str:
    if device.startswith("cuda"):
        return torch.cuda.get_device_name(device)
    model = platform.processor() or "cpu"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    isa = torch.backends.cpu.get_cpu_capability()  # AVX2 / AVX512: oneDNN's kernels differ
    l3 = Path("/sys/devices/system/cpu/cpu0/cache/index3/size")
    cache = f", L3 {l3.read_text().strip()}" if l3.is_file() else ""
    return f"{model}, {os.cpu_count()} logical CPUs, {isa}{cache}"


def _commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True,
            cwd=Path(__file__).resolve().parents[1],
        )  # fmt: skip
        dirty = subprocess.run(["git", "status", "--porcelain"], capture_output=True, text=True)
        return out.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


OLD_MODES = ("today", "full", "traj")
#: Added to REF's modes when REF's planner has the pose-warp world model.
OLD_POSE_MODES = ("pw full", "pw traj")
NEW_MODES = ("full", "traj", "full bf16", "pw full", "pw traj")
#: This checkout with retain_freed_memory() and Planner(world_model_threads=1) (new+opt rows).
OPT_MODES = ("full", "traj", "pw full", "pw traj")


def _extract(ref: str, dest: Path) -> Path:
    """The ``renderworld`` package of commit ``ref`` under ``dest`` (``git archive``)."""
    repo = Path(__file__).resolve().parents[1]
    archive = subprocess.run(
        ["git", "archive", ref, "renderworld"], cwd=repo, capture_output=True, check=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest


def _worker(tree: Path, case: str, threads: int, modes, opt: bool = False) -> subprocess.Popen:
    script = Path(__file__).resolve().parent / "planner_worker.py"
    extra = ["--retain-memory", "--world-model-threads", "1"] if opt else []
    proc = subprocess.Popen(
        [sys.executable, str(script), "--tree", str(tree), "--case", case,
         "--threads", str(threads), "--modes", *modes, *extra],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    line = proc.stdout.readline().strip()
    if line != "ready":
        raise RuntimeError(f"planner worker ({tree}, {case}) did not start: {line!r}")
    return proc


def _round(proc: subprocess.Popen) -> dict:
    import json

    proc.stdin.write("go\n")
    proc.stdin.flush()
    return json.loads(proc.stdout.readline())


def compare(ref: str, cases, threads_list, reps: dict, bf16: bool = True) -> None:
    """Commit ``ref``'s planner and this checkout's, each in a worker process, rounds
    interleaved (one plan per mode and side per round; medians after one warm-up round).
    ``bf16=False`` leaves out the ``full bf16`` mode (slow on CPUs without bf16 arithmetic)."""
    new_modes = tuple(m for m in NEW_MODES if bf16 or m != "full bf16")
    repo = Path(__file__).resolve().parents[1]
    header = (
        f"{'grid':<18}{'thr':>4}  {'planner':<9}{'mode':<10}{'encode':>9}{'world':>9}"
        f"{'decode':>9}{'wall':>10}{'plans/s':>9}{'x old':>7}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        old_tree = _extract(ref, Path(tmp))
        old_modes = OLD_MODES
        if (old_tree / "renderworld/planning/pose_warp.py").is_file():
            old_modes += OLD_POSE_MODES
        for case in cases:
            name = {"mini": "mini 50x50x4", "occ3d": "Occ3D 200x200x16"}[case]
            print(f"# {name}: untrained models ({'mini' if case == 'mini' else 'paper'} sizes); "
                  f"{reps[case]} rounds; old = {ref}, new = this checkout")  # fmt: skip
            print(header)
            for threads in threads_list:
                sides = {
                    "old": (_worker(old_tree, case, threads, old_modes), old_modes),
                    "new": (_worker(repo, case, threads, new_modes), new_modes),
                    "new+opt": (_worker(repo, case, threads, OPT_MODES, opt=True), OPT_MODES),
                }
                runs = {(side, m): [] for side, (_, modes) in sides.items() for m in modes}
                try:
                    for r in range(reps[case] + 1):
                        for side, (proc, _) in sides.items():
                            for mode, t in _round(proc).items():
                                if r:  # round 0 warms up
                                    runs[(side, mode)].append(t)
                finally:
                    for proc, _ in sides.values():
                        proc.stdin.close()
                        proc.wait()
                med = {
                    k: {s: statistics.median(t[s] for t in ts) for s in (*STAGES, "wall")}
                    for k, ts in runs.items()
                }
                for (side, mode), m in med.items():
                    base = med.get(("old", mode))
                    ratio = f"{base['wall'] / m['wall']:>7.2f}" if base else f"{'-':>7}"
                    print(
                        f"{name:<18}{threads:>4}  {side:<9}{mode:<10}{m['encode']:>9.1f}"
                        f"{m['world_model']:>9.1f}{m['decode']:>9.1f}{m['wall']:>10.1f}"
                        f"{1e3 / m['wall']:>9.2f}{ratio}",
                        flush=True,
                    )
                print(f"# load average after {name}, {threads} thread(s): "
                      f"{os.getloadavg()[0]:.1f}", flush=True)  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, nargs="+", default=[2, 1], help="torch threads")
    ap.add_argument("--reps-mini", type=int, default=20)
    ap.add_argument("--reps-occ3d", type=int, default=3)
    ap.add_argument("--mini-tokenizer", type=Path, default=DEMO / "tokenizer/checkpoints/best.pt")
    ap.add_argument(
        "--mini-world-model", type=Path, default=DEMO / "world_model/checkpoints/best.pt"
    )
    ap.add_argument("--skip-occ3d", action="store_true")
    ap.add_argument("--skip-mini", action="store_true")
    ap.add_argument(
        "--modes", nargs="+", choices=MODES, default=list(MODES[:4]), help="'today' is needed"
    )
    ap.add_argument(
        "--profile-decoder", action="store_true", help="only profile the Occ3D decoder (CPU)"
    )
    ap.add_argument(
        "--no-bf16", action="store_true", help="--baseline: leave out the bf16 decoder mode"
    )
    ap.add_argument(
        "--baseline",
        metavar="REF",
        help="compare this checkout's planner (token and pose-warp world models) with commit "
        "REF's in worker processes, rounds interleaved (planner_worker.py)",
    )
    args = ap.parse_args()
    if args.baseline:
        now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
        print(
            f"# Planner latency (ms, medians), batch 1, one new frame per plan\n# {now}, commit "
            f"{_commit()}, device cpu: {_describe_machine('cpu')}, torch {torch.__version__}, "
            f"load average at start {os.getloadavg()[0]:.1f}, "
            f"OMP_WAIT_POLICY={os.environ['OMP_WAIT_POLICY']}"
        )
        cases = [
            c for c, skip in (("mini", args.skip_mini), ("occ3d", args.skip_occ3d)) if not skip
        ]
        reps = {"mini": args.reps_mini, "occ3d": args.reps_occ3d}
        compare(args.baseline, cases, args.threads, reps, bf16=not args.no_bf16)
        print(f"# load average at end {os.getloadavg()[0]:.1f}")
        return
    if args.profile_decoder:
        print(f"# load average {os.getloadavg()[0]:.1f}, commit {_commit()}")
        profile_decoder(occ3d_models(), args.threads[0])
        return
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    print(
        f"# Planner latency (ms, medians of interleaved rounds after 1 warm-up round), batch 1, "
        f"5 history frames, 6-step KV-cached rollout\n# {now}, commit {_commit()}, "
        f"device {args.device}: {_describe_machine(args.device)}, torch {torch.__version__}, "
        f"load average at start {os.getloadavg()[0]:.1f}, "
        f"OMP_WAIT_POLICY={os.environ['OMP_WAIT_POLICY']}"
    )
    cases = []
    if not args.skip_mini:
        models, source = mini_models(args.mini_tokenizer, args.mini_world_model)
        cases.append(("mini 50x50x4", (50, 50, 4), models, source, args.reps_mini))
    if not args.skip_occ3d:
        cases.append(("Occ3D 200x200x16", (200, 200, 16), occ3d_models(), "untrained, paper "
                      "sizes", args.reps_occ3d))  # fmt: skip
    header = (
        f"{'grid':<18}{'thr':>4}  {'mode':<16}{'encode':>9}{'world':>9}{'decode':>9}"
        f"{'wall':>10}{'plans/s':>9}{'x today':>9}"
    )
    for name, grid, models, source, reps in cases:
        print(f"# {name}: {source}; {reps} rounds")
        print(f"# outputs vs today: {agreement(models, grid, args.device)}")
        print(header)
        for threads in args.threads:
            torch.set_num_threads(threads)
            res = bench_case(models, grid, args.device, reps, set(args.modes) | {"today"})
            base = res["today"]["wall"]
            for mode, m in res.items():
                print(
                    f"{name:<18}{threads:>4}  {mode:<16}{m['encode']:>9.1f}"
                    f"{m['world_model']:>9.1f}{m['decode']:>9.1f}{m['wall']:>10.1f}"
                    f"{1e3 / m['wall']:>9.2f}{base / m['wall']:>9.1f}",
                    flush=True,
                )
    print(f"# load average at end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
