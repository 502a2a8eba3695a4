"""The ``octcl`` command: happy paths on real data, one-line errors (exit 2), one-line internal errors (exit 1)."""

import errno
import json
import os
import shlex
import shutil
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

from octcl._io import PNG_SIGNATURE, _png_chunk, read_png_rgb
from octcl.cli import main
from octcl.phantom import Phantom
from octcl.scorer import COMPONENTS


#: The keys of each subcommand's ``--json`` document, as the README documents them.
COMPONENT_KEYS = {*COMPONENTS, "mean"}
JSON_KEYS = {
    "phantom": {"phantom", "kind", "seed", "scatterers", "seconds"},
    "render": {"phantom", "scan", "scatterers", "backend", "seconds"},
    "maps": {"scan", "maps", "seconds"},
    "score": {"ref", "pred", *COMPONENT_KEYS, "seconds"},
    "score --refs": {"refs", "preds", "scans", "medians", "score", "csv", "seconds"},
    "invert": {"target", "output", "score", "components", "initial_score", "scatterers", "iterations",
               "seconds", "checkpoints", "peak_memory_mib", "stopped_by_deadline", "stop_reason", "falls", "seed", "regime", "field_iterations",
               "fixed_schedule", "threads", "reproduce", "reproducible", "ceiling", "exact_share", "avoidable_share",
               "tissue", "report"},
    "phantom-stats": {"phantom", "target", "scatterers", "energy_pct", "shadow_db", "attenuation_per_mm_median",
                      "scan_attenuation_per_mm_median",
                      "band_um", "band_densities_pct", "bands_with_signal", "seconds"},
    "invert --targets": {"scans", "counts", "medians", "score", "median_seconds", "unscored", "octcl_version",
                         "time_budget_s",
                         "seed", "options", "cluster", "wall_s"},
    "weights": {"weights", "ok"},
    "devices": {"id", "device", "builds", "build_error", "default", "reason"},
}


def run(capsys, *argv):
    status = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def run_both(capsys, command, *argv):
    """Run a command without and with --json: (human stdout, parsed JSON); checks both succeed."""
    status, human, _ = run(capsys, *argv)
    assert status == 0
    with pytest.raises(json.JSONDecodeError):
        json.loads(human)
    assert human.strip() and human.count("\n") <= 20
    status, out, _ = run(capsys, *argv, "--json")
    assert status == 0
    payload = json.loads(out)
    for item in payload if isinstance(payload, list) else [payload]:
        assert set(item) == JSON_KEYS[command], command
    return human, payload


def test_phantom_render_maps_score_reproduce_an_official_scan(tmp_path, capsys, official_data):
    phantom = tmp_path / "layers.txt"
    human, payload = run_both(capsys, "phantom", "phantom", "baseline", "--kind", "layers", "--seed", 42,
                              "-o", phantom)
    assert f"{payload['scatterers']:,} scatterers" in human and str(phantom) in human
    scan = tmp_path / "layers.png"
    human, payload = run_both(capsys, "render", "render", phantom, "-o", scan)
    assert str(scan) in human and payload["scan"] == str(scan)
    human, payload = run_both(capsys, "maps", "maps", scan)
    assert sorted(payload["maps"]) == ["OAC", "RSC", "SC"]
    assert all(path in human for path in payload["maps"].values())
    official = official_data / "Scan_Exp2_Layers_A.png"
    human, result = run_both(capsys, "score", "score", official, scan)
    assert result["msssim_Struct"] > 0.9999
    assert f"{result['mean']:.5f}" in human and "MS-SSIM" in human
    ours, theirs = read_png_rgb(scan)[..., 0], read_png_rgb(official)[..., 0]
    assert np.mean(ours == theirs) > 0.999


def test_quiet_prints_nothing_but_json_when_asked(tmp_path, capsys):
    phantom = tmp_path / "skin.txt"
    assert run(capsys, "phantom", "skin", "-o", phantom, "--quiet") == (0, "", "")
    status, out, err = run(capsys, "render", phantom, "-o", tmp_path / "skin.png", "--quiet", "--json")
    assert status == 0 and err == "" and json.loads(out)["scatterers"] > 0
    status, out, err = run(capsys, "render", phantom, "-o", tmp_path / "skin.png")
    assert status == 0 and "skin.txt" in err  # progress on stderr, plain lines (not a terminal)
    assert "\r" not in err


def test_weights_and_devices_print_summaries_or_json(capsys, lpips_weights):
    human, payload = run_both(capsys, "weights", "weights", "check")
    assert payload["ok"] and str(lpips_weights) in human
    human, payload = run_both(capsys, "devices", "devices")
    assert all(device["id"] in human for device in payload)


def test_score_directories_writes_csv(tmp_path, capsys, official_data):
    refs, preds = tmp_path / "refs", tmp_path / "preds"
    refs.mkdir(), preds.mkdir()
    for name in ("Scan_Exp1_Uniform_A.png",):
        (refs / name).write_bytes((official_data / name).read_bytes())
        (preds / name).write_bytes((official_data / "Scan_Exp1_Uniform_B.png").read_bytes())
    human, result = run_both(capsys, "score --refs", "score", "--refs", refs, "--preds", preds,
                             "--csv", tmp_path / "s.csv")
    assert "global" in human and f"{result['score']:.5f}" in human
    lines = (tmp_path / "s.csv").read_text().splitlines()
    assert [line.split(",")[0] for line in lines] == ["scan", "Scan_Exp1_Uniform_A.png", "median"]
    # One scan: the global score is the mean of its 8 components (official: 0.672493).
    assert abs(float(lines[2].split(",")[-1]) - 0.6724934) < 1e-5


def test_render_numpy_backend_and_truncate(tmp_path, capsys):
    phantom = tmp_path / "small.txt"
    Phantom([0.0, 10.0, 20.0], [0.0, 0.0, 1.0], [100.0, 200.0, 300.0], [1.0, 2.0, 3.0]).save(phantom)
    ini = tmp_path / "Configuration.ini"
    ini.write_text("[Parameters]\nNumber of scatterers in B-scan = 2\n")
    status, _, err = run(capsys, "render", phantom, "-o", tmp_path / "x.png", "--config", ini)
    assert status == 2 and "--truncate" in err and "small.txt" in err
    status, _, _ = run(capsys, "render", phantom, "-o", tmp_path / "x.png", "--config", ini,
                       "--truncate", "--backend", "numpy")
    assert status == 0 and read_png_rgb(tmp_path / "x.png").shape == (256, 512, 3)


@pytest.mark.parametrize("argv, message", [
    (["render", "{tmp}/missing.txt", "-o", "{tmp}/x.png"], "missing.txt: no such file"),
    (["maps", "{tmp}/bad.png"], "bad.png: not a PNG file"),
    (["score", "{tmp}/bad.png", "{tmp}/bad.png"], "bad.png: not a PNG file"),
    (["score", "--refs", "{tmp}"], "--preds"),
    (["render", "{tmp}/bad_phantom.txt", "-o", "{tmp}/x.png"], "bad_phantom.txt:2: E = 'abc' is not a number"),
    (["devices", "--device", "no-such-device"], "no OpenCL device matches 'no-such-device'"),
    (["invert", "{tmp}/bad.png", "-o", "{tmp}/x.txt", "--workers", "2"], "--workers: only with --targets"),
    (["invert", "--targets", "{tmp}/missing", "--out", "{tmp}/out"], "missing: no such folder"),
    (["invert", "--targets", "{tmp}", "--out", "{tmp}/out", "--scheduler", "tcp://127.0.0.1:1", "--workers", "2"],
     "workers and threads per worker are the cluster's own"),
    (["invert", "--targets", "{tmp}", "--out", "{tmp}/out", "--tls-cert", "c.pem"], "TLS needs all three"),
    (["invert", "{tmp}/bad.png", "-o", "{tmp}/x.txt", "--iterations", "111"],
     "iterations must be a whole number in [0, 110]"),
    (["invert", "{tmp}/bad.png", "-o", "{tmp}/x.txt", "--regime", "physical", "--iterations", "401"],
     "iterations must be a whole number in [0, 400]"),
    (["invert", "{tmp}/bad.png", "-o", "{tmp}/x.txt", "--regime", "mirror"], "invalid choice: 'mirror'"),
    (["invert", "{tmp}/bad.png", "-o", "{tmp}/x.txt", "--threads", "0"], "threads must be a whole number ≥ 1"),
    (["invert", "{tmp}/bad.png", "-o", "{tmp}/x.txt", "--target-score", "1.5"], "target_score must be a score in (0, 1]"),
    # Images that claim more pixels than octcl reads are refused by their header, before decoding.
    (["maps", "{tmp}/huge.png"], "huge.png: image is 100000x100000 (rows x columns); octcl reads images of 1 to"),
    (["score", "{tmp}/huge.png", "{tmp}/huge.png"], "huge.png: image is 100000x100000 (rows x columns), expected"),
    (["invert", "{tmp}/huge.png", "-o", "{tmp}/x.txt"], "huge.png: image is 100000x100000"),
    # Output paths that cannot be written, refused before any work.
    (["render", "{tmp}/bad_phantom.txt", "-o", "{tmp}"], "error: {tmp}: is a directory; give a file name"),
    (["render", "{tmp}/bad_phantom.txt", "-o", "{tmp}/bad.png/x.png"], "cannot make its folder: {tmp}/bad.png is a file"),
    (["phantom", "-o", "{tmp}"], "{tmp}: is a directory"),
    (["maps", "{tmp}/bad.png", "-o", "{tmp}/bad_phantom.txt"], "{tmp}/bad_phantom.txt is a file"),
    (["score", "--refs", "{tmp}", "--preds", "{tmp}", "--csv", "{tmp}"], "{tmp}: is a directory"),
    (["invert", "{tmp}/bad.png", "-o", "{tmp}"], "{tmp}: is a directory"),
    (["invert", "{tmp}/bad.png", "-o", "{tmp}/x.txt", "--report", "{tmp}/bad.png/r.json"], "bad.png is a file"),
    # Bad command lines: argparse's refusals, on one line too.
    (["render", "{tmp}/bad_phantom.txt"], "octcl render: error: the following arguments are required: -o/--output"),
    (["render", "{tmp}/bad_phantom.txt", "-o", "{tmp}/x.png", "--spread-width", "wide"], "invalid int value: 'wide'"),
    (["no-such-command"], "octcl: error: argument COMMAND: invalid choice: 'no-such-command'"),
])
def test_bad_input_exits_2_with_one_line_reason(tmp_path, capsys, argv, message):
    (tmp_path / "bad.png").write_text("not an image")
    (tmp_path / "bad_phantom.txt").write_text("1 2 3 4\n1 2 3 abc\n")
    (tmp_path / "huge.png").write_bytes(png_header_only(100_000, 100_000))
    try:
        status, out, err = run(capsys, *[a.format(tmp=tmp_path) for a in argv])
    except SystemExit as exit_info:  # argparse's own refusals
        status, (_, err) = exit_info.code, capsys.readouterr()
    assert status == 2
    assert message.format(tmp=tmp_path) in err and err.count("\n") == 1 and err.startswith("octcl")


def png_header_only(width: int, height: int) -> bytes:
    """A PNG that claims ``height`` x ``width`` 8-bit RGBA pixels and holds none."""
    header = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)
    return PNG_SIGNATURE + _png_chunk(b"IHDR", header) + _png_chunk(b"IDAT", zlib.compress(b"")) \
        + _png_chunk(b"IEND", b"")


def test_unexpected_failure_is_one_line_or_a_traceback_with_debug(tmp_path, capsys, monkeypatch):
    """A bug exits 1 with one line naming the exception; --debug (before or after the command) adds the traceback."""
    import octcl.maps

    def broken(*args, **kwargs):
        raise RuntimeError("wrong turn\nin two lines")

    monkeypatch.setattr(octcl.maps, "write_maps", broken)
    status, out, err = run(capsys, "maps", tmp_path / "scan.png")
    assert (status, out) == (1, "")
    assert err == ("octcl maps: internal error: RuntimeError: wrong turn / in two lines; "
                   "rerun with --debug for the traceback\n")
    for argv in (["--debug", "maps", tmp_path / "scan.png"], ["maps", tmp_path / "scan.png", "--debug"]):
        status, out, err = run(capsys, *argv)
        assert status == 1 and err.startswith("Traceback (most recent call last):")
        assert 'raise RuntimeError("wrong turn' in err
        assert err.splitlines()[-1] == "octcl maps: internal error: RuntimeError: wrong turn / in two lines"


@pytest.mark.parametrize("failure", [errno.ENOSPC, errno.EACCES, errno.EROFS])
def test_output_that_fails_while_written_keeps_the_earlier_file(tmp_path, capsys, monkeypatch, failure):
    """A full disk, a folder without permission or a read-only file system while the output is written:
    exit 2, one line, the earlier file unchanged and no temporary file left."""
    phantom = tmp_path / "small.txt"
    Phantom([0.0], [0.0], [100.0], [1.0]).save(phantom)
    scan = tmp_path / "scan.png"
    scan.write_bytes(b"previous output")

    def fail(fd):
        raise OSError(failure, os.strerror(failure))

    monkeypatch.setattr(os, "fsync", fail)
    status, out, err = run(capsys, "render", phantom, "-o", scan, "--backend", "numpy", "--quiet")
    assert (status, out) == (2, "") and err.count("\n") == 1
    assert err == f"octcl render: error: {scan}: cannot write ({os.strerror(failure)}); an earlier file there " \
                  "is unchanged\n"
    assert scan.read_bytes() == b"previous output"
    assert sorted(path.name for path in tmp_path.iterdir()) == ["scan.png", "small.txt"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes in read-only folders")
def test_read_only_folder_is_refused_before_work(tmp_path, capsys):
    phantom = tmp_path / "small.txt"
    Phantom([0.0], [0.0], [100.0], [1.0]).save(phantom)
    folder = tmp_path / "locked"
    folder.mkdir()
    (folder / "scan.png").write_bytes(b"previous output")
    folder.chmod(0o555)
    try:
        status, _, err = run(capsys, "render", phantom, "-o", folder / "scan.png")
    finally:
        folder.chmod(0o755)
    assert status == 2 and f"cannot write in {folder}" in err and err.count("\n") == 1
    assert (folder / "scan.png").read_bytes() == b"previous output"


def test_output_in_a_missing_folder_makes_the_folder(tmp_path, capsys):
    phantom = tmp_path / "small.txt"
    Phantom([0.0], [0.0], [100.0], [1.0]).save(phantom)
    status, _, _ = run(capsys, "render", phantom, "-o", tmp_path / "new" / "folder" / "scan.png", "--backend", "numpy")
    assert status == 0 and read_png_rgb(tmp_path / "new" / "folder" / "scan.png").shape == (256, 512, 3)


def test_render_kernel_variants_agree(tmp_path, capsys):
    """Both kernel variants, chosen on the command line, draw the same B-scan."""
    phantom = tmp_path / "skin.txt"
    Phantom.skin(3).save(phantom)
    images = {}
    for variant in ("work-item", "work-group"):
        assert run(capsys, "render", phantom, "-o", tmp_path / f"{variant}.png", "--kernel-variant", variant)[0] == 0
        images[variant] = read_png_rgb(tmp_path / f"{variant}.png").astype(int)
    assert np.mean(images["work-item"] == images["work-group"]) > 0.999
    with pytest.raises(SystemExit) as exit_info:
        run(capsys, "render", phantom, "-o", tmp_path / "x.png", "--kernel-variant", "warp")
    assert exit_info.value.code == 2 and "'warp'" in capsys.readouterr().err


def test_failed_render_keeps_the_previous_output(tmp_path, capsys):
    scan = tmp_path / "scan.png"
    scan.write_bytes(b"previous output")
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    assert run(capsys, "render", tmp_path / "bad.txt", "-o", scan)[0] == 2
    assert scan.read_bytes() == b"previous output"


def test_invert_summary_says_where_the_main_run_fell():
    from octcl.cli import _invert_lines

    components = {key: 0.99 for key in COMPONENT_KEYS}
    result = {"output": "p.txt", "scatterers": 10, "score": 0.99, "initial_score": 0.98, "components": components,
              "iterations": 60, "fixed_schedule": True, "stop_reason": "schedule", "falls": [], "field_iterations": 5,
              "regime": "linear", "seed": 0, "threads": 1, "reproduce": "--seed 0", "reproducible": True,
              "checkpoints": 2,
              "peak_memory_mib": 100.0, "seconds": {"total": 9.0}, "exact_share": 0.9, "avoidable_share": 0.002,
              "ceiling": {"writable_share": 0.898, "diffused_score": 0.9998}}
    assert "iterations: 60 (fixed schedule, schedule completed); regime linear, field_iterations 5" in \
        "\n".join(_invert_lines(result))
    assert ("on the target's level: 90.00 % of pixels; 89.80 % are at levels the scanner writes, 0.20 % of "
            "pixels are writable and off their level; the target moved to writable levels by error diffusion "
            "scores 0.999800") in _invert_lines(result)
    result["falls"] = [20, 40]
    assert "(fixed schedule, schedule completed; fell after steps 20, 40 and went back to the best phantom)" in \
        "\n".join(_invert_lines(result))


def test_invert_summary_says_when_the_score_was_left_out():
    from octcl.cli import _invert_lines

    result = {"output": "p.txt", "scatterers": 10, "score": None, "initial_score": None, "components": None,
              "iterations": 0, "fixed_schedule": False, "stop_reason": "ceiling", "falls": [], "field_iterations": 150,
              "regime": "linear", "seed": 0, "threads": None, "reproduce": "--seed 0", "reproducible": True,
              "checkpoints": 1, "peak_memory_mib": 100.0, "seconds": {"total": 2.6}, "exact_share": 0.9,
              "avoidable_share": 0.0,
              "ceiling": {"writable_share": 0.9, "diffused_score": None}}
    lines = _invert_lines(result)
    assert lines[0].startswith("p.txt: 10 scatterers, score left out: computing it")
    assert "past the time budget" in lines[0] and not any("msssim" in line.lower() for line in lines)


def test_phantom_stats_reads_a_phantom_as_tissue_against_its_truth(tmp_path, capsys):
    """Against itself as its truth every band with signal has the ratio 1; the attenuation map is a PNG."""
    phantom = tmp_path / "skin.txt"
    Phantom.skin(2).save(phantom)
    status, out, _ = run(capsys, "phantom-stats", phantom, "--truth", phantom, "--attenuation-map",
                         tmp_path / "mu.png", "--json")
    payload = json.loads(out)
    assert status == 0 and set(payload) == JSON_KEYS["phantom-stats"] | {"truth", "band_density_ratios"}
    assert payload["shadow_db"] > 10 and payload["energy_pct"]["max"] <= 100
    ratios = [ratio for ratio, signal in zip(payload["band_density_ratios"], payload["bands_with_signal"]) if signal]
    assert ratios and all(ratio == 1.0 for ratio in ratios)
    assert (tmp_path / "mu.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    status, human, _ = run(capsys, "phantom-stats", phantom)
    assert status == 0 and "shadow at the bottom of the visible tissue" in human


def test_entry_point_runs_as_a_program(tmp_path):
    result = subprocess.run([sys.executable, "-m", "octcl.cli", "devices", "--json"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0
    devices = json.loads(result.stdout)
    assert devices and sum(d["default"] for d in devices) == 1


@pytest.mark.clock
def test_invert_prints_a_summary(tmp_path, capsys, official_data):
    target = official_data / "Scan_Exp2_Layers_A.png"
    # A target score below stage 2's: stage 3 stops at its first exact evaluation.
    status, human, err = run(capsys, "invert", target, "-o", tmp_path / "a.txt", "--time-budget", 20,
                             "--target-score", 0.5, "--report", tmp_path / "a.json")
    assert status == 0 and "\r" not in err and "invert 100%" in err.splitlines()[-1]
    assert "iterations: 0 (deadline mode, stopped: target score reached)" in human
    with pytest.raises(json.JSONDecodeError):
        json.loads(human)
    report = json.loads((tmp_path / "a.json").read_text())
    assert f"{tmp_path / 'a.txt'}: {report['scatterers']:,} scatterers, score {report['score']:.5f}" in human
    assert "MS-SSIM" in human and "report:" in human


def test_invert_prints_json_for_one_scan_and_for_a_folder(tmp_path, capsys, official_data):
    """--json: the keys of one scan's run and of a batch's summary, and a rerun with everything done."""
    target = official_data / "Scan_Exp2_Layers_A.png"
    # A tiny fixed schedule: the keys do not depend on the mode.
    status, out, _ = run(capsys, "invert", target, "-o", tmp_path / "b.txt", "--iterations", 1,
                         "--field-iterations", 10, "--stop-rule", "none", "--json")
    assert status == 0 and set(json.loads(out)) == JSON_KEYS["invert"]
    assert json.loads(out)["reproduce"].endswith("--threads 1 --stop-rule none")
    targets = tmp_path / "targets"
    (targets / "sub").mkdir(parents=True)
    (targets / "sub" / "layers.png").write_bytes(target.read_bytes())
    status, out, err = run(capsys, "invert", "--targets", targets, "--out", tmp_path / "out",
                           "--iterations", 1, "--field-iterations", 10, "--stop-rule", "stall", "--workers", 1,
                           "--json")
    summary = json.loads(out)
    assert status == 0 and set(summary) == JSON_KEYS["invert --targets"]
    assert set(summary["scans"]["sub/layers.png"]) == {"scan", "status", *COMPONENT_KEYS, "seconds",
                                                       "peak_memory_mib", "cpu_s", "worker", "error"}
    assert summary["counts"]["inverted"] == 1 and (tmp_path / "out" / "sub" / "layers.txt").is_file()
    assert summary["options"]["schedule"]["patience"] == 2  # the stall rule, recorded for resume
    assert {key: summary["options"][key] for key in ("iterations", "field_iterations")} == {
        "iterations": 1, "field_iterations": 10}
    assert "dashboard http://127.0.0.1:" in err and "invert 100%  1/1 scans: 1 inverted" in err
    # Everything done: a rerun starts no cluster and says so.
    status, human, err = run(capsys, "invert", "--targets", targets, "--out", tmp_path / "out",
                             "--iterations", 1, "--field-iterations", 10, "--stop-rule", "stall", "--workers", 1)
    assert status == 0 and "1 scans: 1 resumed" in human and "report.html" in human
    assert "dashboard" not in err


def test_invert_fixed_schedule_repeats_byte_for_byte(tmp_path, capsys, official_data):
    """`--seed 5 --iterations 10` twice gives the same file, byte for byte; another seed another file.

    Stage 1 is cut to 20 steps and stage 3 to 10 to keep the test short (any
    step that depends on more than its inputs, the thread count and the
    device shows in the file); ``scripts/check_determinism.py`` runs whole
    schedules in fresh processes and across thread counts.
    """
    import octcl
    from octcl.host.pipeline.target import read_target

    target = official_data / "Scan_Exp2_Layers_A.png"
    schedule = ["--iterations", 10, "--field-iterations", 20]
    results = []
    for name in ("a", "b"):
        status, out, _ = run(capsys, "invert", target, "-o", tmp_path / f"{name}.txt", "--seed", 5, *schedule,
                             "--quiet", "--json")
        assert status == 0
        results.append(json.loads(out))
    assert (tmp_path / "a.txt").read_bytes() == (tmp_path / "b.txt").read_bytes()
    assert results[0]["score"] == results[1]["score"]
    first = results[0]
    assert first["fixed_schedule"] and not first["stopped_by_deadline"]
    # Stage 1 renders this scan (the scanner's own) exactly: stage 3 has nothing to refine.
    assert (first["iterations"], first["field_iterations"], first["threads"]) == (0, 20, 1)
    assert first["stop_reason"] == "ceiling" and first["exact_share"] == 1.0 and first["score"] == 1.0
    assert first["reproduce"] == "--regime linear --backend opencl --seed 5 --iterations 0 --field-iterations 20 --threads 1"
    # The reproduce options run the schedule again, the NumPy reference backend included.
    status, out, _ = run(capsys, "invert", target, "-o", tmp_path / "numpy.txt", "--seed", 5, "--backend", "numpy",
                         *schedule, "--quiet", "--json")
    reference = json.loads(out)
    assert status == 0 and reference["score"] == 1.0 and reference["exact_share"] == 1.0
    assert reference["reproduce"] == first["reproduce"].replace("--backend opencl", "--backend numpy")
    # The target as an array (what a batch runner sends a worker): in the
    # linear regime nothing is drawn at random, so another seed gives the
    # same file; in the physical regime it draws other elevations in stage 2.
    array = read_target(target)
    same = octcl.invert(array, tmp_path / "c.txt", seed=6, iterations=10, field_iterations=20, name="layers")
    assert same.target == "layers" and same.iterations == 0
    assert (tmp_path / "c.txt").read_bytes() == (tmp_path / "a.txt").read_bytes()
    physical = [octcl.invert(array, tmp_path / f"p{seed}.txt", seed=seed, iterations=2, field_iterations=20,
                             regime="physical") for seed in (5, 6)]
    assert physical[0].reproduce.startswith("--regime physical --backend opencl --seed 5 --iterations 2")
    assert (tmp_path / "p5.txt").read_bytes() != (tmp_path / "p6.txt").read_bytes()


def test_invert_fixed_schedule_past_its_budget_fails_loudly(tmp_path, capsys, official_data):
    target = official_data / "Scan_Exp2_Layers_A.png"
    output = tmp_path / "a.txt"
    status, out, err = run(capsys, "invert", target, "-o", output, "--iterations", 2, "--field-iterations", 10**6,
                           "--time-budget", 10)
    assert status == 2 and out == ""
    message = err.strip().splitlines()[-1]
    assert message.startswith("octcl invert: error: ") and str(target) in message
    assert "did not fit the time budget of 10 s" in message and "in stage 1" in message
    assert "nothing was written" in message and not output.exists()


def _save_levels(png, npy):
    """``np.save`` the grey levels of the opaque grey scan ``png`` as ``npy``, as the SynthOCT challenge ships scans."""
    np.save(npy, read_png_rgb(png)[..., 0])
    return npy


def test_npy_scans_read_as_their_pngs_in_score_maps_and_invert(tmp_path, capsys, official_data):
    """score, maps and invert of a .npy of a scan's levels give what they give for the scan's PNG."""
    pngs = {name: official_data / f"Scan_{name}.png" for name in ("Exp1_Uniform_A", "Exp1_Uniform_B", "Exp2_Layers_A")}
    npys = {name: _save_levels(png, tmp_path / f"{name}.npy") for name, png in pngs.items()}

    def components(ref, pred):
        status, out, err = run(capsys, "score", ref, pred, "--quiet", "--json")
        assert (status, err) == (0, "")
        payload = json.loads(out)
        assert (payload["ref"], payload["pred"]) == (str(ref), str(pred))
        return {key: payload[key] for key in COMPONENT_KEYS}

    expected = components(pngs["Exp1_Uniform_A"], pngs["Exp1_Uniform_B"])
    assert abs(expected["mean"] - 0.6724934) < 1e-5  # the official score of the pair
    assert components(npys["Exp1_Uniform_A"], pngs["Exp1_Uniform_B"]) == expected
    assert components(npys["Exp1_Uniform_A"], npys["Exp1_Uniform_B"]) == expected

    for kind in ("png", "npy"):
        (tmp_path / kind).mkdir()
    scans = {"png": tmp_path / "png" / "layers.png", "npy": tmp_path / "npy" / "layers.npy"}
    scans["png"].write_bytes(pngs["Exp2_Layers_A"].read_bytes())
    scans["npy"].write_bytes(npys["Exp2_Layers_A"].read_bytes())
    written = {}
    for kind, scan in scans.items():
        human, written[kind] = run_both(capsys, "maps", "maps", scan, "-o", tmp_path / f"{kind}_maps")
        assert written[kind]["scan"] == str(scan)
    for name in ("OAC", "SC", "RSC"):
        png_map, npy_map = (Path(written[kind]["maps"][name]) for kind in ("png", "npy"))
        assert npy_map.name == png_map.name == f"layers_{name}.png"
        assert npy_map.read_bytes() == png_map.read_bytes()
        official = official_data / f"Scan_Exp2_Layers_A_{name}.png"
        np.testing.assert_array_equal(read_png_rgb(npy_map), read_png_rgb(official))

    results = {}
    for kind, scan in scans.items():
        status, out, err = run(capsys, "invert", scan, "-o", tmp_path / f"{kind}.txt", "--iterations", 1,
                               "--field-iterations", 2, "--quiet", "--json")
        assert (status, err) == (0, "")
        results[kind] = json.loads(out)
        assert results[kind]["target"] == str(scan) and results[kind]["output"] == str(tmp_path / f"{kind}.txt")
    assert len(Phantom.load(tmp_path / "npy.txt")) == results["npy"]["scatterers"] > 0
    assert (tmp_path / "npy.txt").read_bytes() == (tmp_path / "png.txt").read_bytes()
    assert results["npy"]["components"] == results["png"]["components"]


#: .npy files that are not B-scans, and the message (after ``FILE: ``) every command gives for them.
BAD_NPY = {
    "float64": (np.zeros((256, 512)), "float64 array; a B-scan is a 2-D uint8 array of grey levels (256x512, rows x "
                                      "columns) (floats are not scaled or rounded: save the levels as uint8)"),
    "3-D": (np.zeros((256, 512, 3), np.uint8), "3-D array of shape (256, 512, 3); a B-scan is a 2-D uint8 array"),
    "255x512": (np.zeros((255, 512), np.uint8), "array is 255x512 (rows x columns), expected 256x512"),
    "object": (np.full((256, 512), None, dtype=object), ".npy of Python objects (dtype object), not loaded"),
    "empty": (np.zeros((0,), np.uint8), "empty array (shape (0,)); a B-scan is a 2-D uint8 array"),
    "truncated": (np.zeros((256, 512), np.uint8), "truncated .npy file: its header announces a uint8 array of shape "
                                                  "(256, 512) (131,072 bytes) but 1,000 bytes follow"),
}


@pytest.mark.parametrize("argv", [
    ["maps", "{bad}"],
    ["maps", "{bad}", "-o", "{tmp}/maps"],
    ["score", "{bad}", "{good}"],
    ["score", "{good}", "{bad}"],
    ["score", "--refs", "{tmp}/refs", "--preds", "{tmp}/preds"],
    ["invert", "{bad}", "-o", "{tmp}/x.txt", "--iterations", "1"],
])
@pytest.mark.parametrize("kind", list(BAD_NPY))
def test_npy_that_is_not_a_scan_exits_2_naming_the_file(tmp_path, capsys, official_data, kind, argv):
    array, message = BAD_NPY[kind]
    (tmp_path / "refs").mkdir(), (tmp_path / "preds").mkdir()
    bad = tmp_path / "refs" / "scan.npy"
    np.save(bad, array, allow_pickle=array.dtype == object)
    if kind == "truncated":
        bad.write_bytes(bad.read_bytes()[:-131072 + 1000])
    good = official_data / "Scan_Exp1_Uniform_A.png"
    (tmp_path / "preds" / "scan.png").write_bytes(good.read_bytes())
    status, out, err = run(capsys, *[a.format(tmp=tmp_path, bad=bad, good=good) for a in argv])
    assert (status, out) == (2, "")
    assert err.startswith(f"octcl {argv[0]}: error: {bad}: {message}") and err.count("\n") == 1
    assert sorted(path.name for path in tmp_path.iterdir()) == ["preds", "refs"]  # nothing written


@pytest.mark.clock
def test_invert_budget_starts_with_the_process():
    """``--time-budget`` counts from the process's start: a time before now, by at most the process's age."""
    import psutil

    from octcl.cli import process_started

    started = process_started()
    age = time.time() - psutil.Process().create_time()
    assert time.monotonic() - age - 0.05 <= started <= time.monotonic()


@pytest.mark.parametrize("options, message", [(["--field-schedule", "display:20,projekt:5"], "unknown stage-1 step"),
                                              (["--field-schedule", "display:20", "--regime", "physical"],
                                               "linear and tissue regimes'")])
def test_invert_refuses_a_bad_field_schedule_before_any_work(tmp_path, capsys, official_data, options, message):
    output = tmp_path / "out.txt"
    status, _, err = run(capsys, "invert", official_data / "Scan_Exp2_Layers_A.png", "-o", output, *options)
    assert status == 2 and message in err and err.count("\n") == 1
    assert not output.exists()


@pytest.mark.clock
@pytest.mark.skipif(shutil.which("sh") is None, reason="needs a POSIX shell")
def test_a_budget_counts_from_the_import_when_a_shell_ran_first_in_the_same_process():
    """``sh -c "sleep 3; exec python ..."`` keeps the shell's process, started 3 s before Python: its age says
    so, and the budget counts from at most MAX_START_TO_IMPORT_S before octcl.cli's import instead."""
    from octcl.cli import MAX_START_TO_IMPORT_S

    code = ("import time; from octcl.cli import process_age_s, process_started; "
            "print(process_age_s(), time.monotonic() - process_started())")
    command = f"sleep 3; exec {shlex.quote(sys.executable)} -c {shlex.quote(code)}"
    done = subprocess.run(["sh", "-c", command], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    age, counted = (float(value) for value in done.stdout.split())
    assert age >= 3.0 and MAX_START_TO_IMPORT_S <= counted < MAX_START_TO_IMPORT_S + 1.0


@pytest.mark.clock
def test_the_process_age_is_the_processes_own_to_the_hundredth():
    """A budget counts from the process's start: the age a child reports lies between the time it slept
    and the time its parent saw it run (psutil's creation time, with Linux's whole-second boot time, was up
    to a second off)."""
    code = "import time; time.sleep(0.3); from octcl.cli import process_age_s; print(process_age_s())"
    began = time.monotonic()
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    wall = time.monotonic() - began
    assert done.returncode == 0, done.stderr
    assert 0.3 <= float(done.stdout) <= wall + 0.02
