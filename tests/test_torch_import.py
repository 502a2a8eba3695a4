"""What importing torch costs, known before it is paid (octcl/torch_import.py), and budgets that use it."""

import json
import os
import shutil
import subprocess
import sys
import time
from importlib import metadata

import pytest

from conftest import cache_with_built_programs
from octcl import torch_import
from octcl._lpips import WEIGHTS_FILENAME, weights_path
from octcl.host.pipeline.invert import PREFETCH_TORCH_MIN_S
from octcl.torch_import import (BACKGROUND, BACKGROUND_FACTOR, BACKGROUND_LEFT_MIN_S, CACHE_FILE, CPU_BUILD_IMPORT_S,
                                 KEPT_TIMES, OTHER_BUILD_IMPORT_S, record_import_s, torch_import_s)


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


@pytest.mark.clock
def test_a_budget_leaves_out_what_a_slow_torch_import_would_push_past_it(real_like_target, tmp_path):
    """Where torch took 100 s to import before, a 20 s budget on a real-like target runs neither the aim step
    nor any score (each needs torch) and never imports it; the phantom is written and the process ends in time."""
    target, output = real_like_target, tmp_path / "out.txt"
    cache = cache_with_built_programs(tmp_path / "cache")
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


def test_a_background_import_is_waited_for_and_its_time_kept_apart(tmp_path):
    """import_torch waits for the thread's import; while it runs the estimate is what is left of the
    background's expected time (nothing measured: BACKGROUND_FACTOR times the build's default)."""
    code = ("import sys, threading\n"
            "from octcl.torch_import import import_torch, import_torch_in_background, torch_import_s\n"
            "import_torch_in_background(); during = torch_import_s(); torch = import_torch()\n"
            "print(during, torch_import_s(), hasattr(torch, 'tensor'),\n"
            "      any(t.name == 'octcl-import-torch' and t.is_alive() for t in threading.enumerate()))\n")
    environment = {**os.environ, "OCTCL_CACHE_DIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=environment)
    assert done.returncode == 0, done.stderr
    during, after, complete, alive = done.stdout.split()
    defaults = [BACKGROUND_FACTOR * value for value in (CPU_BUILD_IMPORT_S, OTHER_BUILD_IMPORT_S)]
    assert any(BACKGROUND_LEFT_MIN_S <= float(during) <= value for value in defaults)
    assert float(after) == 0.0 and complete == "True" and alive == "False"
    version = metadata.version("torch")
    kept = json.loads((tmp_path / CACHE_FILE).read_text())
    assert list(kept) == [f"{sys.executable} torch {version} {BACKGROUND}"]  # not taken for a foreground import
    assert 0 < kept[f"{sys.executable} torch {version} {BACKGROUND}"][0] < 60


@pytest.mark.clock
def test_a_running_background_import_is_estimated_by_what_is_left_of_its_time(without_torch, monkeypatch):
    monkeypatch.setattr(metadata, "version", lambda name: "2.13.0+cpu")
    (without_torch / CACHE_FILE).write_text(json.dumps({f"{sys.executable} torch 2.13.0+cpu background": [3.0],
                                                        f"{sys.executable} torch 2.13.0+cpu": [1.0]}))

    class Running:
        @staticmethod
        def is_alive():
            return True

    monkeypatch.setattr(torch_import, "_background", {"thread": Running(), "started": time.perf_counter() - 1.0})
    assert 1.9 < torch_import_s() <= 2.0  # 3 s expected, 1 s gone
    monkeypatch.setitem(torch_import._background, "started", time.perf_counter() - 10.0)
    assert torch_import_s() == BACKGROUND_LEFT_MIN_S  # late, but still running
    monkeypatch.setattr(torch_import, "_background", {})
    assert torch_import_s() == 1.0  # the foreground's own figure


@pytest.mark.clock
def test_an_invert_run_begins_the_import_where_it_will_need_torch_and_the_budget_allows(real_like_target, tmp_path):
    """A real-like target (levels the scanner never writes) needs torch for its aim and score: the run
    imports it on a thread from its start, and scores; not when less than PREFETCH_TORCH_MIN_S would be left
    before the exit (beside a stage 1 run against the clock the import slows it)."""
    code = ("import json, sys\n"
            "from octcl.host.pipeline.invert import invert\n"
            "from octcl import torch_import\n"
            # A short stage 1 without the aim, and a stage 3 that stops at its first score: what is tested is the
            # import's start and the score, not the stages' length
            f"result = invert({str(real_like_target)!r}, sys.argv[1], time_budget_s=float(sys.argv[2]),"
            " field_schedule='display:20,project:20,hinge:20', target_score=0.5)\n"
            "print(json.dumps([bool(torch_import._background), result.score is not None]))\n")
    version = metadata.version("torch")
    cache = cache_with_built_programs(tmp_path / "cache")  # one for both runs
    shutil.copy(weights_path(), cache / WEIGHTS_FILENAME)  # the score needs the LPIPS weights
    (cache / CACHE_FILE).write_text(json.dumps({f"{sys.executable} torch {version}": [1.0]}))
    for label, budget, expected in (("long", 3 * PREFETCH_TORCH_MIN_S, [True, True]),
                                    ("short", PREFETCH_TORCH_MIN_S, [False])):
        done = subprocess.run([sys.executable, "-c", code, str(cache / "out.txt"), str(budget)], capture_output=True,
                              text=True, timeout=180, env={**os.environ, "OCTCL_CACHE_DIR": str(cache)})
        assert done.returncode == 0, done.stderr
        assert json.loads(done.stdout)[:len(expected)] == expected, label
