"""What importing torch costs, known before it is paid (octcl/torch_import.py), and budgets that use it."""

import json
import os
import subprocess
import sys
from importlib import metadata

import numpy as np
import pytest

from octcl.torch_import import (CACHE_FILE, CPU_BUILD_IMPORT_S, KEPT_TIMES, OTHER_BUILD_IMPORT_S, record_import_s,
                                 torch_import_s)


@pytest.fixture
def without_torch(monkeypatch, tmp_path):
    """This process as if torch were not imported yet, with an empty cache folder of its own."""
    monkeypatch.delitem(sys.modules, "torch", raising=False)
    monkeypatch.setenv("OCTCL_CACHE_DIR", str(tmp_path))
    return tmp_path


@pytest.mark.parametrize("version, requirements, expected", [
    ("2.13.0+cpu", [], CPU_BUILD_IMPORT_S),
    ("2.11.0+cu130", [], OTHER_BUILD_IMPORT_S),
    ("2.9.0+rocm6.4", [], OTHER_BUILD_IMPORT_S),
    ("2.8.0", ["filelock", "sympy>=1.13"], CPU_BUILD_IMPORT_S),  # PyPI's macOS and Windows wheels
    ("2.8.0", ["filelock", "nvidia-cudnn-cu12==9.10 ; platform_system == 'Linux'"], OTHER_BUILD_IMPORT_S),
])
def test_without_a_measurement_the_estimate_is_the_builds_default(without_torch, monkeypatch, version, requirements,
                                                                  expected):
    monkeypatch.setattr(metadata, "version", lambda name: version)
    monkeypatch.setattr(metadata, "requires", lambda name: requirements)
    assert torch_import_s() == expected


def test_the_estimate_is_the_median_time_kept_for_this_interpreter_and_version(without_torch, monkeypatch):
    monkeypatch.setattr(metadata, "version", lambda name: "2.13.0+cpu")
    key = f"{sys.executable} torch 2.13.0+cpu"
    cache = without_torch / CACHE_FILE
    cache.write_text(json.dumps({key: [1.0, 2.5, 0.5], f"{sys.executable} torch 2.12.0+cpu": [40.0]}))
    assert torch_import_s() == 1.0  # of 1.0, 2.5 and 0.5; another version's 40 s are not this one's
    cache.write_text("not json")  # a damaged cache is as none
    assert torch_import_s() == CPU_BUILD_IMPORT_S
    monkeypatch.setitem(sys.modules, "torch", object())
    assert torch_import_s() == 0.0


def test_the_last_times_are_kept_and_their_median_is_the_estimate(without_torch, monkeypatch):
    monkeypatch.setattr(metadata, "version", lambda name: "2.13.0+cpu")
    times = [1.5, 4.0, 1.1, 1.2, 1.3, 1.4]
    for seconds in times:
        record_import_s(seconds)
    kept = json.loads((without_torch / CACHE_FILE).read_text())
    assert kept == {f"{sys.executable} torch 2.13.0+cpu": times[-KEPT_TIMES:]}
    assert torch_import_s() == 1.3  # the median of 4.0, 1.1, 1.2, 1.3, 1.4


def test_a_process_times_its_first_import_for_the_next(tmp_path):
    code = ("from octcl.torch_import import import_torch, torch_import_s\n"
            "before = torch_import_s(); import_torch(); print(before, torch_import_s())\n")
    environment = {**os.environ, "OCTCL_CACHE_DIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=environment)
    assert done.returncode == 0, done.stderr
    before, after = map(float, done.stdout.split())
    assert before in (CPU_BUILD_IMPORT_S, OTHER_BUILD_IMPORT_S) and after == 0.0  # nothing measured before
    kept = json.loads((tmp_path / CACHE_FILE).read_text())
    assert list(kept) == [f"{sys.executable} torch {metadata.version('torch')}"]
    assert len(kept[f"{sys.executable} torch {metadata.version('torch')}"]) == 1
    assert 0 < kept[f"{sys.executable} torch {metadata.version('torch')}"][0] < 60


def test_a_budget_leaves_out_what_a_slow_torch_import_would_push_past_it(official_data, tmp_path):
    """Where torch took 100 s to import before, a 20 s budget on a real-like target runs neither the aim step
    nor any score (each needs torch) and never imports it; the phantom is written and the process ends in time."""
    from octcl.host.pipeline.target import read_target, target_scan
    from octcl.host.stage1.ceiling import WRITABLE
    from octcl.host.stage1.levels import target_levels

    levels = target_levels(target_scan(read_target(official_data / "Scan_Exp2_Layers_A.png")))
    unwritable = np.flatnonzero(~WRITABLE)
    bright = levels > 60
    levels[bright] = unwritable[np.searchsorted(unwritable, levels[bright]) % unwritable.size]
    target, output = tmp_path / "real_like.npy", tmp_path / "out.txt"
    np.save(target, levels)
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / CACHE_FILE).write_text(json.dumps({f"{sys.executable} torch {metadata.version('torch')}": [100.0]}))
    code = ("import json, sys, time\n"
            "started = time.monotonic()\n"
            "from octcl.host.pipeline.invert import invert\n"
            f"result = invert({str(target)!r}, {str(output)!r}, time_budget_s=20, started=started)\n"
            "print(json.dumps(['torch' in sys.modules, result.score, time.monotonic() - started]))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "OCTCL_CACHE_DIR": str(cache)})
    assert done.returncode == 0, done.stderr
    imported, score, seconds = json.loads(done.stdout)
    assert not imported and score is None and seconds < 20
    assert output.exists()
