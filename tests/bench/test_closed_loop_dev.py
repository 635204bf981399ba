"""The closed-loop dev sets' summary (benchmarks/closed_loop_dev.py): read, pooled, paired."""

from __future__ import annotations

import subprocess
import sys

import pytest

from benchmarks.closed_loop_dev import ROOT, table
from renderworld.sim.closed_loop.compare import load_run
from tests.sim.test_compare_drives import write_run

WM = "world_model"


def runs(tmp_path, name, scores):
    """{set: rows} of a run whose sets each hold scene s1 and s2 (the same names in both)."""
    out = {}
    for st, (p1, p2) in scores.items():
        rows = [("s1", "cut_in", WM, p1, p1 == 0.0), ("s2", "lead_brake", WM, p2, False)]
        out[st] = load_run(write_run(tmp_path / name / st, rows), WM, st)
    return out


def test_sets_are_summed_up_and_paired_within_each_set(tmp_path):
    base = runs(tmp_path, "base", {"turns": (0.8, 0.6), "pdev": (0.5, 0.9)})
    new = runs(tmp_path, "new", {"turns": (0.9, 0.6), "pdev": (0.0, 0.9)})
    lines = table(new, base).splitlines()
    turns, pdev, pooled = (line.split(" | ") for line in lines[2:])
    assert turns[:4] == ["| turns", "2", "0.750", "0"] and turns[-1] == "+0.050 ± 0.050 |"
    assert pdev[:4] == ["| pdev", "2", "0.450", "1"] and pdev[-1] == "-0.250 ± 0.250 |"
    # All four scenes, each paired with its own set's (the names recur across sets).
    assert pooled[:4] == ["| all", "4", "0.600", "1"] and pooled[-1].startswith("-0.100 ± ")
    assert "vs --against" not in table(new, None)


def run_script(*args):
    """benchmarks/closed_loop_dev.py with ``args``: its exit code, stdout and stderr."""
    script = ROOT / "benchmarks" / "closed_loop_dev.py"
    run = subprocess.run([sys.executable, str(script), *map(str, args)], capture_output=True,
                         text=True)  # fmt: skip
    return run.returncode, run.stdout + run.stderr


def test_bad_arguments_are_named(tmp_path):
    rc, err = run_script("--bundle", tmp_path / "no.pt", "--out", tmp_path / "out")
    assert rc != 0 and "--bundle: no planner bundle" in err
    bundle = tmp_path / "b.pt"
    bundle.write_bytes(b"")
    rc, err = run_script("--bundle", bundle, "--out", tmp_path / "out", "--against", tmp_path / "x")
    assert rc != 0 and "--against:" in err and "has no run of" in err
    rc, err = run_script("--bundle", bundle, "--out", tmp_path / "out", "--nudges", "0", "2.5")
    assert rc != 0 and "--nudges: expected starts within 1 m" in err


def test_several_starts_score_each_scene_by_its_mean(tmp_path):
    """``--nudges``: the runs from each start are read from their own folders, each scene
    scored by its mean over them, and ``--against`` must hold the same starts."""
    runs(tmp_path, "a", {"turns": (0.8, 0.6)})
    runs(tmp_path / "a", "nudge+0.001", {"turns": (0.0, 1.0)})  # s1 collides from this start
    runs(tmp_path, "b", {"turns": (0.8, 0.6)})
    bundle = tmp_path / "b.pt"
    bundle.write_bytes(b"")
    args = ["--bundle", bundle, "--sets", "turns", "--nudges", "0", "0.001"]
    rc, out = run_script(*args, "--out", tmp_path / "a")
    assert rc == 0, out
    turns = next(line for line in out.splitlines() if line.startswith("| turns")).split(" | ")
    # s1: (0.8 + 0.0) / 2, s2: (0.6 + 1.0) / 2; at fault in one start of two: 0.5 per start.
    assert turns[:4] == ["| turns", "2", "0.600", "0.50"]
    assert "starts [0.0, 0.001] m ahead of the log" in out
    rc, err = run_script(*args, "--out", tmp_path / "a", "--against", tmp_path / "b")
    assert rc != 0 and "has no run of ['nudge+0.001/turns']" in err


@pytest.mark.parametrize("name", ["turns", "routes", "pdev", "pdevi"])
def test_every_set_drives_what_the_protocol_names(name):
    from benchmarks.closed_loop_dev import SETS

    rows = [r for r in (ROOT / "docs" / "protocol.md").read_text().splitlines()
            if r.startswith("| planner dev")]  # fmt: skip
    # Some row of the protocol's split table holds every drive argument of the set.
    assert any(all(arg in r for arg in SETS[name]) for r in rows)
