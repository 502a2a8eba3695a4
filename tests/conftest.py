"""Shared pytest fixtures."""

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def official_data() -> Path:
    """The official SynthOCT scans, maps and metrics in the repository's ``data/official/``.

    See ``data/README.md`` for their provenance and licence.
    """
    path = Path(__file__).resolve().parents[1] / "data" / "official"
    assert path.is_dir(), f"reference data folder missing: {path}"
    return path


@pytest.fixture(scope="session")
def lpips_weights() -> Path:
    """The cached LPIPS weights; fails (not skips) with the fetch hint when missing."""
    from octcl._lpips import WeightsMissingError, check_weights

    try:
        return check_weights()
    except WeightsMissingError as exc:
        pytest.fail(str(exc), pytrace=False)


@pytest.fixture(scope="session")
def official_uniform_metrics(official_data) -> dict:
    """Official MS-SSIM and LPIPS of Uniform_A against Uniform_B: {map: {metric: value}}."""
    import csv

    with open(official_data / "metrics_exp1_uniform.csv", newline="") as handle:
        return {
            row["Map_Type"]: {"MS-SSIM": float(row["MS-SSIM"]), "LPIPS": float(row["LPIPS"])}
            for row in csv.DictReader(handle)
        }


@pytest.fixture(scope="session")
def official_uniform_maps(official_data) -> tuple[dict, dict]:
    """The official Struct/OAC/SC/RSC map PNGs of Uniform_A and Uniform_B as the metric reads them."""
    from octcl.scorer import _read_map_for_metrics

    def maps(scan):
        suffixes = {"Struct": "", "OAC": "_OAC", "SC": "_SC", "RSC": "_RSC"}
        return {
            name: _read_map_for_metrics(official_data / f"Scan_{scan}{suffix}.png")
            for name, suffix in suffixes.items()
        }

    return maps("Exp1_Uniform_A"), maps("Exp1_Uniform_B")


@pytest.fixture(scope="session")
def official_reference():
    """``rendering(kind, seed)``: float64 reference rendering of a baseline phantom, made once per session."""
    from octcl.phantom import Phantom
    from octcl.render import render

    cache = {}

    def rendering(kind, seed):
        if (kind, seed) not in cache:
            cache[kind, seed] = render(Phantom.baseline(kind, seed), backend="numpy")
        return cache[kind, seed]

    return rendering


@pytest.fixture
def slow_clock(monkeypatch):
    """``slow_clock(module)``: the module's ``time`` jumps 1000 s at every reading.

    A run that takes no decision from the clock gives the same result under
    it as under the real one; a run that does stops or changes course.
    """
    import itertools
    import time
    import types

    def install(module):
        readings = itertools.count()
        start = time.monotonic()

        def reading():
            return start + 1000.0 * next(readings)

        monkeypatch.setattr(module, "time", types.SimpleNamespace(monotonic=reading, perf_counter=reading))

    return install
