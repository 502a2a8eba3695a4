"""scripts/bench_field_schedules.py: stage 1's schedules timed on targets, and their table."""

from __future__ import annotations

import json

import pytest

from conftest import load_script


def test_the_table_gives_each_schedule_its_sum_median_longest_and_misses():
    script = load_script("bench_field_schedules")
    rows = [{"target": target, "schedule": schedule, "seconds": seconds, "identical": identical}
            for target, schedule, seconds, identical in [
                ("a", "display:150,project:100,hinge:200", 1.0, 1.0), ("a", "display:100,hinge:200", 0.5, 1.0),
                ("b", "display:150,project:100,hinge:200", 3.0, 1.0), ("b", "display:100,hinge:200", 2.0, 0.999),
                ("c", "display:150,project:100,hinge:200", 2.0, 1.0), ("c", "display:100,hinge:200", 4.0, 1.0)]]
    lines = script.table(rows).splitlines()
    assert lines[2] == "| `display:150,project:100,hinge:200` | 3 | 6.0 | 2.00 | 3.00 | 0 |"
    assert lines[3] == "| `display:100,hinge:200` | 3 | 6.5 | 2.00 | 4.00 | 1 |"


def test_a_schedule_with_the_aim_step_is_refused(tmp_path, capsys):
    script = load_script("bench_field_schedules")
    with pytest.raises(SystemExit):
        script.main([str(tmp_path / "t.npy"), "--schedules", "display:10,aim:2", "--out", str(tmp_path)])
    assert "without the aim step" in capsys.readouterr().err


def test_short_schedules_run_on_a_real_like_target(real_like_target, tmp_path):
    script = load_script("bench_field_schedules")
    schedules = ["display:3,project:2,hinge:2", "project:2"]
    assert script.main([str(real_like_target), "--schedules", *schedules, "--out", str(tmp_path)]) == 0
    rows = [json.loads(line) for line in (tmp_path / "schedules.jsonl").read_text().splitlines()]
    assert [row["schedule"] for row in rows] == schedules
    assert [[step[0] for step in row["steps"]] for row in rows] == [["display", "project", "hinge"], ["project"]]
    assert all(0 < row["identical"] < 1 and row["seconds"] > 0 for row in rows)  # too short to reach the aim
