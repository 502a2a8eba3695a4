"""scripts/bench_versions.py: where a run's time went, from its report and its wall time."""

from __future__ import annotations

import os
import subprocess

import pytest

from conftest import load_script

from octcl.host.threads import available_cores


def report(aim_s: float) -> dict:
    """A linear run's report: stage 1 (two candidates' steps) and the decode end 4.0 s after the start,
    the phantom is in place at 4.3 s."""
    steps = [{"name": "display", "seconds": 1.0}, {"name": "project", "seconds": 0.4},
             {"name": "hinge", "seconds": 0.2}, {"name": "aim", "seconds": aim_s}]
    return {"seconds": {"field": 1.6 + aim_s + 0.5, "decode": 0.3, "written": 4.3},
            "trace": [{"time_s": 4.0, "stage": "field"}, {"time_s": 4.2, "stage": "initial"}],
            "settings": {"field_candidates": [{"steps": steps}, {"steps": [{"name": "display", "seconds": 0.5}]}]}}


def test_a_runs_parts_are_read_from_its_report_and_wall_time():
    script = load_script("bench_versions")
    parts = script.run_parts(report(aim_s=0.7), wall_s=4.6)
    assert list(parts) == list(script.PARTS)
    assert parts["display"] == pytest.approx(1.5)  # both candidates' display fits
    assert parts["before stage 1"] == pytest.approx(4.0 - 2.8 - 0.3)
    assert parts["to the write"] == pytest.approx(0.3) and parts["after the write"] == pytest.approx(0.3)
    assert sum(parts.values()) == pytest.approx(4.6)  # here stage 1 is its steps alone


def test_the_table_gives_each_trees_median_parts():
    script = load_script("bench_versions")
    components = {name: 0.9999 for name in ("msssim_Struct", "msssim_OAC", "msssim_SC", "msssim_RSC",
                                            "one_minus_lpips_Struct", "one_minus_lpips_OAC", "one_minus_lpips_SC",
                                            "one_minus_lpips_RSC")}
    rows = [{"target": target, "tree": "0:a", "repeat": 0, "wall_s": wall, "cpu_s": 2 * wall, "written_s": 4.3,
             **script.run_parts(report(aim_s), wall), **components, "mean": 0.9999}
            for target, aim_s, wall in (("x", 0.5, 4.4), ("y", 0.9, 4.8), ("z", 0.7, 4.6))]
    lines = script.table_lines(rows, ["0:a"])
    assert lines[2] == "| x | 4.40 (4.40) / 4.30 / 0.9999000 |"
    assert "0:a: median wall 4.60 s over 3 targets, longest 4.80 s" in lines[-1]
    assert "aim 0.70" in lines[-1] and "after the write 0.30" in lines[-1]
    cores = available_cores()
    assert f"median CPU 9.20 s a run, {9.2 / cores:.2f} s over {cores} cores" in lines[-1]


def fake_tree(folder, body: str):
    """A source tree whose ``octcl.cli.command`` runs ``body`` (the bootstrap imports the tree's own octcl)."""
    (folder / "octcl").mkdir(parents=True)
    (folder / "octcl" / "__init__.py").write_text("")
    (folder / "octcl" / "cli.py").write_text(f"def command():\n{body}\n")
    return folder


def test_a_runs_cpu_time_is_its_childs(tmp_path):
    """run_tree gives the child's wall and CPU seconds; a child that spins 0.3 s shows at least that much CPU."""
    script = load_script("bench_versions")
    spin = "    import time\n    end = time.process_time() + 0.3\n    while time.process_time() < end:\n        pass\n    return 0"
    tree = fake_tree(tmp_path / "spin", spin)
    wall_s, cpu_s = script.run_tree(tree, tmp_path / "t.png", tmp_path / "o.txt", tmp_path / "r.json", [])
    if hasattr(os, "wait4"):
        assert 0.3 <= cpu_s <= wall_s + 0.5
    else:
        assert cpu_s != cpu_s  # NaN where the platform gives no child's CPU time
    failing = fake_tree(tmp_path / "fail", "    return 3")
    with pytest.raises(subprocess.CalledProcessError):
        script.run_tree(failing, tmp_path / "t.png", tmp_path / "o.txt", tmp_path / "r.json", [])
