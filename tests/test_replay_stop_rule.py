"""scripts/replay_stop_rule.py: a restart rule replayed on a trace stops where the rule in stage 3 would."""

from __future__ import annotations

import json

import pytest

from conftest import load_script


def replay_script():
    return load_script("replay_stop_rule")


def trace_with_gains(gains_e6: list[float]) -> list[dict]:
    """A main run reaching 0.9999, then one restart per gain (two checkpoints each, 10 s apart)."""
    trace, score, time_s = [{"time_s": 1.0, "stage": "refine", "iteration": 20, "score": 0.9999}], 0.9999, 1.0
    for number, gain in enumerate(gains_e6, start=1):
        for iteration, share in ((30, 0.5), (60, 1.0)):
            time_s += 5.0
            trace.append({"time_s": time_s, "stage": f"restart {number}", "iteration": iteration,
                          "score": score + share * gain * 1e-6})
        score += gain * 1e-6
    return trace


def test_restart_gains_are_each_restarts_best_over_the_best_before_it():
    script = replay_script()
    stages = script.restart_stages(trace_with_gains([8.0, 1.0, 3.0]))
    assert [after - before for before, after, _ in stages] == pytest.approx([8e-6, 1e-6, 3e-6], abs=1e-12)
    assert [end for _, _, end in stages] == [11.0, 21.0, 31.0]


def test_a_rule_stops_after_the_restarts_it_judges(tmp_path, capsys):
    """Gains 8, 1, 4.5, 0.3, 0.1 (1e−6): 1e−5 over one restart stops after the first; 5e−6 over two after the
    fourth (4.5 + 0.3), not the third (1 + 4.5); a rule never met runs the whole trace. The time is the
    trace's at that restart's end plus what the run spent after its trace (60 − 51 s)."""
    script = replay_script()
    trace = trace_with_gains([8.0, 1.0, 4.5, 0.3, 0.1])
    replay = script.replay_restart_rule
    assert replay(trace, 60.0, 1e-5, 1) == (pytest.approx(0.9999 + 8e-6), pytest.approx(11.0 + 9.0))
    assert replay(trace, 60.0, 5e-6, 2) == (pytest.approx(0.9999 + 13.8e-6), pytest.approx(41.0 + 9.0))
    assert replay(trace, 60.0, 0.0, 2) == (pytest.approx(0.9999 + 13.9e-6), pytest.approx(60.0))
    report = tmp_path / "run.json"
    report.write_text(json.dumps({"score": 0.9999139, "seconds": {"total": 60.0}, "trace": trace}))
    assert script.main([str(report), "--rules", "1e-5/1", "5e-6/2"]) == 0
    row = capsys.readouterr().out.splitlines()[2]
    assert row == "| run | 8.0 1.0 4.5 0.3 0.1 | 0.9999139 / 60 | 0.9999080 / 20 | 0.9999138 / 50 |"


def test_bad_rules_and_reports_get_clear_errors(tmp_path, capsys):
    script = replay_script()
    for bad in ("1e-5", "x/2", "1e-5/0"):
        with pytest.raises(SystemExit):
            script.main([str(tmp_path / "none.json"), "--rules", bad])
        assert "MIN_GAIN" in capsys.readouterr().err
    report = tmp_path / "left_out.json"
    report.write_text(json.dumps({"score": None, "seconds": {"total": 3.0}, "trace": []}))
    with pytest.raises(SystemExit):
        script.main([str(report)])
    assert "left_out.json: no score" in capsys.readouterr().err
