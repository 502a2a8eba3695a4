"""scripts/bench_batch.py: what bounds a batch's throughput, from its scans' rows."""

from __future__ import annotations

import pytest

from conftest import load_script


def rows(scans: list[tuple[str, float, float]]) -> dict:
    """Summary rows of scans (worker, seconds, CPU seconds)."""
    return {f"scan_{index}.npy": {"worker": worker, "seconds": seconds, "cpu_s": cpu}
            for index, (worker, seconds, cpu) in enumerate(scans)}


def test_cpu_figures_bound_the_throughput_by_the_scans_cpu_time():
    script = load_script("bench_batch")
    # Two workers on two cores: a's scans take 5 + 6 s, b's 4 s; the batch 12 s from start to end.
    figures = script.cpu_figures(rows([("a", 5.0, 4.5), ("a", 6.0, 5.5), ("b", 4.0, 5.0)]), wall_s=12.0, cores=2)
    assert figures["cpu_s_per_scan"] == pytest.approx(5.0)
    assert figures["cpu_bound_scans_per_hour"] == pytest.approx(2 * 3600 / 5.0)
    assert figures["outside_scans_s"] == pytest.approx(((12 - 11) + (12 - 4)) / 2)
    assert figures["cpu_use_pct"] == pytest.approx(100 * 15 / 24)
    # A batch whose cores were busy throughout reaches its bound.
    busy = script.cpu_figures(rows([("a", 5.0, 5.0), ("b", 5.0, 5.0)]), wall_s=5.0, cores=2)
    assert 3600 * 2 / 5.0 == pytest.approx(busy["cpu_bound_scans_per_hour"])
    assert busy["outside_scans_s"] == 0 and busy["cpu_use_pct"] == pytest.approx(100)
