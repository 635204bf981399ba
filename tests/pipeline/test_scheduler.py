"""The runner's scheduling: one-core steps side by side, whole-machine steps alone."""

import json
import sys

import pytest

from renderworld.pipeline.runner import PipelineError, Step, run_steps

QUIET = lambda *_: None  # noqa: E731


def _timed(tmp_path, name, cores=None, depends_on=(), seconds=0.4, fail=False, wait_for=None):
    """A step recording its start and end time (``<name>/t.json``); ``wait_for``: the name of a
    step whose start it waits for (up to 30 s), so it only succeeds when both run at once."""
    out = tmp_path / name
    code = [
        "import json, pathlib, sys, time",
        f"o = pathlib.Path({str(out)!r}); o.mkdir(exist_ok=True); t0 = time.time()",
        "(o / 'started').write_text('1'); print('working', flush=True)",
    ]
    if wait_for:
        other = tmp_path / wait_for / "started"
        code += [
            "deadline = time.time() + 30",
            f"while not pathlib.Path({str(other)!r}).exists():",
            "    time.sleep(0.01)",
            "    if time.time() > deadline: sys.exit(5)",
        ]
    code += [
        f"time.sleep({seconds})",
        "(o / 't.json').write_text(json.dumps([t0, time.time()]))",
        f"sys.exit({4 if fail else 0})",
    ]
    command = (sys.executable, "-c", "\n".join(code))
    return Step(name, name, command, out, depends_on=tuple(depends_on), cores=cores)


def _span(tmp_path, name):
    return json.loads((tmp_path / name / "t.json").read_text())


def test_one_core_steps_run_side_by_side_and_their_lines_name_them(tmp_path, capsys):
    steps = [
        _timed(tmp_path, "a", cores=1, wait_for="b"),
        _timed(tmp_path, "b", cores=1, wait_for="a"),
        _timed(tmp_path, "c", depends_on=("a", "b")),
    ]
    results = run_steps(steps, tmp_path / "logs", tmp_path, cores=2)
    assert [r.status for r in results] == ["ran", "ran", "ran"]
    assert [r.name for r in results] == ["a", "b", "c"]
    (a0, a1), (b0, b1), (c0, _) = (_span(tmp_path, n) for n in "abc")
    assert max(a0, b0) < min(a1, b1)  # they overlapped
    assert c0 >= max(a1, b1)  # the dependant waited for both
    out = capsys.readouterr().out
    assert "    [a] working" in out and "    [b] working" in out
    assert "    working" in out  # c ran alone: no prefix
    assert "working" in (tmp_path / "logs" / "a.log").read_text()


def test_whole_machine_steps_run_alone_and_are_never_passed(tmp_path):
    steps = [
        _timed(tmp_path, "a", cores=1, seconds=0.6),
        _timed(tmp_path, "b"),  # the whole machine: waits for a
        _timed(tmp_path, "c", cores=1),  # fits beside a, but must not pass b
    ]
    run_steps(steps, tmp_path / "logs", tmp_path, echo=QUIET, cores=2)
    (_, a1), (b0, b1), (c0, _) = (_span(tmp_path, n) for n in "abc")
    assert b0 >= a1 and c0 >= b1


def test_a_step_waiting_for_a_dependency_may_be_passed(tmp_path):
    steps = [
        _timed(tmp_path, "a", cores=1, seconds=0.6),
        _timed(tmp_path, "b", cores=1, depends_on=("a",)),
        _timed(tmp_path, "c", cores=1, seconds=0.6),
    ]
    run_steps(steps, tmp_path / "logs", tmp_path, echo=QUIET, cores=2)
    (a0, a1), (b0, _), (c0, c1) = (_span(tmp_path, n) for n in "abc")
    assert c0 < a1 and a0 < c1  # c ran beside a while b waited for a
    assert b0 >= a1


def test_one_core_leaves_every_step_alone(tmp_path):
    steps = [_timed(tmp_path, n, cores=1, seconds=0.2) for n in "ab"]
    run_steps(steps, tmp_path / "logs", tmp_path, echo=QUIET, cores=1)
    (_, a1), (b0, _) = (_span(tmp_path, n) for n in "ab")
    assert b0 >= a1
    for bad in (0, "2", 1.5, True):
        with pytest.raises(ValueError, match=r"cores: expected an int >= 1 or null, got "):
            run_steps(steps, tmp_path / "logs", tmp_path, echo=QUIET, cores=bad)


def test_a_failed_step_lets_the_step_beside_it_finish_and_starts_nothing_new(tmp_path):
    steps = [
        _timed(tmp_path, "a", cores=1, seconds=0.0, fail=True),
        _timed(tmp_path, "b", cores=1, seconds=0.6),
        _timed(tmp_path, "c", cores=1),
    ]
    with pytest.raises(PipelineError, match=r"step 'a' failed with exit code 4 .*a\.log"):
        run_steps(steps, tmp_path / "logs", tmp_path, echo=QUIET, cores=2)
    assert (tmp_path / "b" / ".step-done.json").is_file()  # finished: kept
    assert not (tmp_path / "a" / ".step-done.json").exists()
    assert not (tmp_path / "c").exists()  # never started
    steps[0] = _timed(tmp_path, "a", cores=1, seconds=0.0)
    again = run_steps(steps, tmp_path / "logs", tmp_path, echo=QUIET, cores=2)
    assert [r.status for r in again] == ["ran", "skipped", "ran"]
