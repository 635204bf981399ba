"""The schedule record a training run leaves in its run dir."""

from __future__ import annotations

import pytest

from renderworld.training.schedule import SCHEDULE_FILE, read_schedule, write_schedule


def test_round_trip_and_absent_record(tmp_path):
    assert read_schedule(tmp_path) is None  # not a training run
    write_schedule(tmp_path, 1795, 2700, True, 11.25, 675.123456)
    assert read_schedule(tmp_path) == {
        "step": 1795,
        "max_steps": 2700,
        "stopped_early": True,
        "max_minutes": 11.25,
        "elapsed_s": 675.123,
    }


@pytest.mark.parametrize("text", ["not json", '{"step": 3}', '{"step": "x", "max_steps": 1}'])
def test_a_malformed_record_names_the_file(tmp_path, text):
    (tmp_path / SCHEDULE_FILE).write_text(text)
    with pytest.raises(ValueError, match="schedule.json: not a schedule record"):
        read_schedule(tmp_path)
