"""The invert pipeline: target checks, time budget, checkpoints that survive a kill, reports."""

import json
import os
import random
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from octcl._io import ImageFormatError, write_grey_png
from octcl.host.pipeline.invert import invert
from octcl.host.stage3.refine import Phase, RefineSchedule
from octcl.host.stage1.start import TWIN_ITERATIONS
from octcl.config import DEFAULT_CONFIG
from octcl.phantom import CONTRACT_Y_LIMIT_UM, TARGET_ROWS, Phantom
from octcl.scorer import COMPONENTS

SHORT = RefineSchedule(phases=(Phase(4, 0.01, 0.02),), restarts=(), score_every=2)


@pytest.fixture(scope="module")
def layers_path(official_data):
    return official_data / "Scan_Exp2_Layers_A.png"


def _assert_contract(path):
    phantom = Phantom.load(path, y_limit_um=CONTRACT_Y_LIMIT_UM)
    assert 0 < len(phantom) <= TARGET_ROWS
    return phantom


@pytest.mark.parametrize("kind", ["black", "white", "grey", "small", "text"])
def test_bad_targets_are_refused_naming_the_file(tmp_path, kind):
    target = tmp_path / f"{kind}.png"
    if kind == "text":
        target.write_text("not an image\n")
        message = "not a PNG"
    elif kind == "small":
        write_grey_png(target, np.zeros((128, 512), np.uint8) + np.arange(512, dtype=np.uint8)[None] // 2)
        message = "expected 256x512"
    else:
        level = {"black": 0, "white": 255, "grey": 128}[kind]
        write_grey_png(target, np.full((256, 512), level, np.uint8))
        message = {"black": "black", "white": "white", "grey": "grey level 128"}[kind]
    output = tmp_path / "out.txt"
    with pytest.raises(ImageFormatError, match=message) as info:
        invert(target, output, time_budget_s=30)
    assert str(target) in str(info.value)
    assert not output.exists()


def test_bad_budget_is_refused(layers_path, tmp_path):
    with pytest.raises(ValueError, match="time_budget_s"):
        invert(layers_path, tmp_path / "out.txt", time_budget_s=0)


def test_an_unknown_backend_is_refused(layers_path, tmp_path):
    with pytest.raises(ValueError, match="backend must be one of opencl, numpy"):
        invert(layers_path, tmp_path / "out.txt", backend="cuda")
    assert not (tmp_path / "out.txt").exists()


@pytest.mark.parametrize("backend", ["opencl", "numpy"])
def test_either_backend_renders_every_level_of_a_scanner_rendered_scan(layers_path, tmp_path, backend):
    """Stage 1 on the device (the default) and the NumPy reference: the same fixed schedule puts every pixel
    of Layers A at its level, the report says which backend ran and the reproduce options name it."""
    report = tmp_path / "report.json"
    result = invert(layers_path, tmp_path / "out.txt", iterations=0, field_iterations=60, backend=backend,
                    report_path=report)
    assert result.exact_share == 1.0 and result.score == 1.0
    assert json.loads(report.read_text())["settings"]["field_backend"] == backend
    assert f"--backend {backend} " in result.reproduce


@pytest.mark.clock
def test_budget_is_respected_and_report_written(layers_path, tmp_path):
    """The physical regime's stages cut by the clock: stage 1 by its share, stage 3 by the deadline."""
    budget = 15.0
    output, report_path = tmp_path / "layers.txt", tmp_path / "layers.json"
    calls = []
    start = time.monotonic()
    result = invert(layers_path, output, time_budget_s=budget, seed=3, report_path=report_path,
                    progress=calls.append, regime="physical")
    elapsed = time.monotonic() - start
    assert elapsed < budget + 5.0
    _assert_contract(output)
    assert result.stopped_by_deadline and result.iterations > 0 and not result.reproducible
    assert result.score >= result.initial_score
    assert result.checkpoints >= 1

    # Progress: every stage, the estimate never beyond the budget left, and a
    # last state at 100 % with the final score.
    assert [state.stage for state in calls][0] == "field"
    assert {state.stage for state in calls} >= {"field", "decode", "setup", "refine", "done"}
    for state in calls:
        assert 0.0 <= state.seconds_left <= budget - state.elapsed_s
        assert 0.0 <= state.fraction <= 1.0
    final = calls[-1]
    assert final.stage == "done" and final.fraction == 1.0 and final.seconds_left == 0.0
    assert final.iteration == result.iterations

    report = json.loads(report_path.read_text())
    assert report["seed"] == 3 and report["settings"]["time_budget_s"] == budget and report["regime"] == "physical"
    # Stage 1's share, 1.2 s, is too short for its 1500 steps: the clock cut it and set its learning rate.
    assert result.field_iterations < 1500 and report["settings"]["field_clock_steps"] > 0
    assert set(COMPONENTS) <= set(report["components"])
    assert report["peak_memory_mib"] > 0
    stages = [entry["stage"] for entry in report["trace"]]
    assert stages[0] == "field" and "initial" in stages and "refine" in stages
    times = [entry["time_s"] for entry in report["trace"]]
    assert times == sorted(times) and times[-1] <= budget
    scored = [entry for entry in report["trace"] if entry["score"] is not None]
    assert max(entry["score"] for entry in scored) == pytest.approx(result.score)
    assert final.score == scored[-1]["score"]  # the last exact score, not the stage-2 one
    assert final.score_elapsed_s == pytest.approx(scored[-1]["time_s"], abs=0.5)


@pytest.mark.clock
def test_a_ten_second_budget_gives_a_complete_linear_phantom(layers_path, tmp_path):
    """The default (linear) regime within 10 s: a phantom in the contract, scored, on time."""
    output = tmp_path / "layers.txt"
    start = time.monotonic()
    result = invert(layers_path, output, time_budget_s=10.0)
    elapsed = time.monotonic() - start
    assert elapsed < 10.0 + 2.0
    phantom = _assert_contract(output)
    assert result.regime == "linear" and result.scatterers == len(phantom) <= 2 * 256 * 512
    assert result.score >= result.initial_score > 0.999


def test_kill_leaves_a_complete_checkpoint(layers_path, tmp_path):
    """SIGKILL at a random moment after the first checkpoint: the output is a whole, valid phantom."""
    output = tmp_path / "killed.txt"
    # Checkpoints as often as the score improves (every iteration is scored),
    # so the kill is likely to land during a write. The physical regime: the
    # linear one renders this scan exactly after stage 1 and stops there.
    code = (
        "import octcl.host.pipeline.invert as invert\n"
        "from octcl.host.stage3.refine import Phase, RefineSchedule\n"
        "invert.CHECKPOINT_INTERVAL_S = 0.0\n"
        f"invert.invert({str(layers_path)!r}, {str(output)!r}, time_budget_s=120, regime='physical',\n"
        "              field_iterations=20,\n"
        "              schedule=RefineSchedule(phases=(Phase(10000, 0.002, 0.05),), restarts=(), score_every=1))\n"
    )
    process = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 100
        while not output.exists():
            assert process.poll() is None, process.stderr.read().decode()
            assert time.monotonic() < deadline, "no checkpoint within 100 s"
            time.sleep(0.05)
        first_seen = output.stat().st_mtime_ns
        time.sleep(random.Random(os.getpid()).uniform(0.0, 8.0))
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == -signal.SIGKILL
    _assert_contract(output)
    assert output.stat().st_mtime_ns >= first_seen


@pytest.mark.clock
def test_a_deadline_run_that_took_no_decision_from_the_clock_repeats(tmp_path, layers_path):
    """Deadline mode, threads timed or given: the same file, and ``reproduce``'s fixed schedule writes it too."""
    schedule = RefineSchedule(phases=(Phase(6, 0.002, 0.02),), restarts=(), score_every=3)
    timed = invert(layers_path, tmp_path / "timed.txt", time_budget_s=3000, field_iterations=40, schedule=schedule)
    # Layers A is the scanner's own: stage 1 renders it exactly and stage 3 stops at once.
    assert timed.reproducible and timed.threads is None and timed.stop_reason == "ceiling"
    two = invert(layers_path, tmp_path / "two.txt", time_budget_s=3000, field_iterations=40, schedule=schedule,
                 threads=2)
    assert two.reproducible and two.reproduce == timed.reproduce.replace("--threads 1", "--threads 2")
    fixed = invert(layers_path, tmp_path / "fixed.txt", time_budget_s=3000, iterations=timed.iterations,
                   field_iterations=timed.field_iterations, threads=1, schedule=schedule)
    assert fixed.reproducible
    contents = (tmp_path / "timed.txt").read_bytes()
    assert (tmp_path / "two.txt").read_bytes() == contents and (tmp_path / "fixed.txt").read_bytes() == contents


def test_stage_1_budget_counts_what_the_budget_has_lost_before_it():
    from octcl.host.pipeline.invert import FIELD_BUDGET_CAP_S, FIELD_BUDGET_FRACTION, MIN_FIELD_BUDGET_S, field_budget_s

    # Linear: all but the reserve (decode, first write, close) and what the process's start took.
    assert field_budget_s("linear", 5.0, 0.7, reserve_s=1.5) == pytest.approx(5.0 - 0.7 - 1.5)
    assert field_budget_s("linear", 600.0, 0.7, reserve_s=1.5) == FIELD_BUDGET_CAP_S
    assert field_budget_s("linear", 1.0, 0.9, reserve_s=1.5) == MIN_FIELD_BUDGET_S  # late, but a phantom
    # Physical: its share of the budget, from the start.
    assert field_budget_s("physical", 100.0, 0.5) == pytest.approx(FIELD_BUDGET_FRACTION * 100.0 - 0.5)
    assert field_budget_s("physical", 6000.0, 0.5) == pytest.approx(FIELD_BUDGET_CAP_S - 0.5)


def test_the_reserve_is_what_this_machine_measured_per_grid_else_the_defaults(monkeypatch, tmp_path):
    """The longest of the decode-and-first-write spans and of the closes kept for the regime and grid, and the
    exit's; the defaults where none was measured, and for another grid."""
    from octcl.config import ScannerConfig
    from octcl.host.pipeline.invert import (CLOSE_S, EXIT_RESERVE_S, LINEAR_WRITE_RESERVE_S, SPANS,
                                            TISSUE_WRITE_RESERVE_S, write_reserve_s)

    monkeypatch.setenv("OCTCL_CACHE_DIR", str(tmp_path))
    assert write_reserve_s("linear") == pytest.approx(LINEAR_WRITE_RESERVE_S + CLOSE_S + EXIT_RESERVE_S)
    for seconds in (1.4, 1.6, 1.5):
        SPANS.record("linear first write 256x512", seconds)
    SPANS.record("close 256x512", 0.3)
    assert write_reserve_s("linear") == pytest.approx(1.6 + 0.3 + EXIT_RESERVE_S)
    assert write_reserve_s("tissue") == pytest.approx(TISSUE_WRITE_RESERVE_S + 0.3 + EXIT_RESERVE_S)
    small = ScannerConfig(depth_pixels=64, a_scans=128)
    assert write_reserve_s("linear", small) == pytest.approx(LINEAR_WRITE_RESERVE_S + CLOSE_S + EXIT_RESERVE_S)


@pytest.mark.clock
def test_budget_runs_from_the_start_it_is_given(layers_path, tmp_path, monkeypatch):
    """A budget that began 2 s before the call leaves stage 1 2 s less; the write's time counts from that start.
    The run keeps its decode-and-first-write span and, where stage 3 took no step, its close for the next run.
    Stage 3 keeps back what follows it by the run's measures (a grey target: its write, no ceiling score to
    compute), with a margin, and the exit's share, where that is less than the budget's share."""
    from octcl.host.pipeline.invert import AFTER_STAGE_3_FACTOR, EXIT_RESERVE_S, SPANS, final_reserve_s

    monkeypatch.setenv("OCTCL_CACHE_DIR", str(tmp_path / "cache"))

    started = time.monotonic() - 2.0
    result = invert(layers_path, tmp_path / "out.txt", time_budget_s=6.0, report_path=tmp_path / "r.json",
                    started=started)
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["settings"]["field_budget_s"] <= 6.0 - 2.0 - EXIT_RESERVE_S
    assert 2.0 < result.seconds["written"] <= result.seconds["total"]
    first_write = SPANS.times("linear first write 256x512")
    assert len(first_write) == 1 and result.seconds["decode"] < first_write[0] < result.seconds["written"]
    assert len(SPANS.times("close 256x512")) == (1 if result.iterations == 0 else 0)
    deadline = report["settings"]["refine_deadline_s"]
    write = report["seconds"]["checkpoint_writes"] / report["checkpoints"]
    assert 6.0 - final_reserve_s(6.0) < deadline <= 6.0 - EXIT_RESERVE_S - AFTER_STAGE_3_FACTOR * 0.5 * write


@pytest.mark.clock
def test_a_budget_with_no_time_left_to_score_writes_its_phantom_and_leaves_the_score_out(real_like_target, tmp_path):
    """A real-like target (levels the scanner never writes) with 1 s of its budget left: the phantom is written,
    the score (torch, the network, a score: more than that second) is left out, the ceiling's scores too, and the
    report says so. (When the process ends is measured by scripts/bench_invert.py, docs/benchmarks.md.)"""
    budget, started = 3.0, time.monotonic() - 2.0
    result = invert(real_like_target, tmp_path / "out.txt", time_budget_s=budget, report_path=tmp_path / "r.json",
                    started=started)
    assert result.score is None and result.components is None and result.initial_score is None
    assert result.ceiling["diffused_score"] is None
    assert result.stop_reason in ("ceiling", "deadline") and result.iterations == 0  # at its aim or not
    _assert_contract(tmp_path / "out.txt")
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["score"] is None and report["trace"][-1]["score"] is None


def test_the_tissue_regime_writes_a_phantom_at_tissue_scale_and_says_what_it_is(layers_path, tmp_path):
    """--regime tissue: the linear field decoded at tissue scale, then stage 3 with shadowing (a fixed short
    schedule here). The phantom shadows by whole decibels (the linear regime's by 1e−12 dB, its energies
    ≲ 1e−10 %), the result and report carry its figures as tissue and the decode's choices."""
    result = invert(layers_path, tmp_path / "tissue.txt", time_budget_s=600, regime="tissue", iterations=2,
                    field_iterations=40, report_path=tmp_path / "r.json")
    phantom = _assert_contract(tmp_path / "tissue.txt")
    assert np.all(phantom.energy_pct <= 100)
    assert result.tissue is not None and result.tissue["shadow_db"] > 3
    assert result.tissue["energy_pct"]["p95"] > 1e-3
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["tissue"] == json.loads(json.dumps(result.tissue))
    decode = report["settings"]["tissue_decode"]
    assert {"scale", "short_lines", "capped_rows", "bottom_light_db"} <= set(decode)
    # The decode's field is stage 1's least-norm twin, back on the aimed levels within its iterations.
    assert decode["twin_iterations"] <= TWIN_ITERATIONS and decode["twin_identical"] > 0.9
    assert report["seconds"]["twin"] > 0
    # Stage 1 without the aim's rounds: its aim is the error-diffused one.
    assert all("aim" not in candidate["schedule"] for candidate in report["settings"]["field_candidates"])
    assert result.reproduce.startswith("--regime tissue")
    # The maps handed out (a batch draws its pictures from them) are the written file's own.
    from octcl.render import render
    from octcl.tissue import attenuation_map, transmission_map

    np.testing.assert_array_equal(result.levels, render(phantom).levels)
    np.testing.assert_allclose(result.attenuation_per_mm, attenuation_map(transmission_map(phantom)), rtol=1e-6)
    assert "levels" not in result.as_dict() and "attenuation_per_mm" not in result.as_dict()


def test_the_twin_takes_its_share_of_the_time_left():
    """The tissue regime's least-norm twin gets what stage 1 left of its budget, at most TWIN_SHARE of the
    seconds before the exit (the rest is the decode's and stage 3's), at least MIN_FIELD_BUDGET_S; on a fixed
    schedule its iterations alone bound it."""
    from octcl.host.pipeline.invert import MIN_FIELD_BUDGET_S, TWIN_SHARE, twin_budget_s

    assert twin_budget_s(None, None) is None
    assert 0 < TWIN_SHARE < 1
    assert twin_budget_s(15.0, 20.0) == pytest.approx(TWIN_SHARE * 20.0)  # a short budget: the share
    assert twin_budget_s(36.0, 590.0) == 36.0  # the default budget: what stage 1 left
    assert twin_budget_s(-1.0, 20.0) == twin_budget_s(5.0, 0.0) == MIN_FIELD_BUDGET_S


@pytest.mark.clock
def test_the_linear_regime_writes_its_phantom_before_importing_torch(layers_path, tmp_path):
    """Stages 1–2 of one candidate need neither torch nor the scorer, and a scan the scanner rendered,
    inverted exactly, is scored without them: the whole run never imports torch (2 s on two cores)."""
    output = tmp_path / "out.txt"
    code = (
        "import sys, json\n"
        "from octcl.host.pipeline.invert import invert\n"
        "seen = []\n"
        f"def progress(state, output={str(output)!r}):\n"
        "    import os\n"
        "    if state.stage == 'setup' and not seen:\n"
        "        seen.append((os.path.exists(output), 'torch' in sys.modules))\n"
        f"result = invert({str(layers_path)!r}, {str(output)!r}, time_budget_s=60, progress=progress)\n"
        "print(json.dumps([seen[0], 'torch' in sys.modules, result.score, result.stop_reason]))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == [[True, False], False, 1.0, "ceiling"]


def test_levels_equal_to_a_grey_target_score_exactly_one_as_the_scorer_computes_it(layers_path):
    """The shortcut of invert's lazy scorer: ExactScore itself gives 1.0 on every component for them."""
    from octcl.host.stage1.levels import target_levels
    from octcl.host.pipeline.invert import _LazyExactScore
    from octcl.host.stage3.loss import ExactScore
    from octcl.host.pipeline.target import read_target, target_scan

    target = read_target(layers_path)
    levels = target_levels(target_scan(target))
    lazy = _LazyExactScore(target, DEFAULT_CONFIG)
    assert lazy.grey and lazy(levels) == ExactScore(target)(levels) == {**dict.fromkeys(COMPONENTS, 1.0), "mean": 1.0}
    assert lazy._score is None  # the shortcut built nothing
    other = levels.copy()
    other[0, 0] ^= 1
    assert lazy(other)["mean"] < 1.0 and lazy._score is not None


def test_the_lazy_scorer_scores_each_image_once(layers_path):
    """A run asks for the same levels' score more than once (the aim step, stage 3's input, the ceiling): the
    scorer computes each image once, hands out copies, and keeps what the computation took for stage 3's clock."""
    from octcl.host.pipeline.invert import _LazyExactScore
    from octcl.host.pipeline.target import read_target, target_scan
    from octcl.host.stage1.levels import target_levels

    target = read_target(layers_path)
    levels = target_levels(target_scan(target))
    lazy = _LazyExactScore(target, DEFAULT_CONFIG)
    calls = []

    def counted(image):
        calls.append(image.copy())
        return {"mean": float(image.mean()) / 255.0}

    lazy._score = counted  # stands in for ExactScore: what matters is how often it is asked
    moved = levels.copy()
    moved[0, :8] ^= 1
    first = lazy(moved)
    first["mean"] = -1.0  # a caller's change stays the caller's
    assert lazy(moved) == {"mean": float(moved.mean()) / 255.0} and len(calls) == 1
    again = moved.copy()
    again[1, 0] ^= 1
    lazy(again)
    assert len(calls) == 2 and lazy.seconds >= 0.0
