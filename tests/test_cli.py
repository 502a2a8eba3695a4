"""The ``octcl`` command: happy paths on real data and one-line errors with exit status 2."""

import json
import subprocess
import sys

import numpy as np
import pytest

from octcl._io import read_png_rgb
from octcl.cli import main
from octcl.phantom import Phantom


def run(capsys, *argv):
    status = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def test_phantom_render_maps_score_reproduce_an_official_scan(tmp_path, capsys, official_data):
    phantom = tmp_path / "layers.txt"
    assert run(capsys, "phantom", "baseline", "--kind", "layers", "--seed", 42, "-o", phantom)[0] == 0
    scan = tmp_path / "layers.png"
    assert run(capsys, "render", phantom, "-o", scan)[0] == 0
    status, out, _ = run(capsys, "maps", scan, "--json")
    assert status == 0 and sorted(json.loads(out)) == ["OAC", "RSC", "SC"]
    official = official_data / "Scan_Exp2_Layers_A.png"
    status, out, _ = run(capsys, "score", official, scan, "--json")
    result = json.loads(out)
    assert status == 0 and set(result) >= {"msssim_Struct", "one_minus_lpips_RSC", "mean"}
    assert result["msssim_Struct"] > 0.9999
    ours, theirs = read_png_rgb(scan)[..., 0], read_png_rgb(official)[..., 0]
    assert np.mean(ours == theirs) > 0.999


def test_score_directories_writes_csv(tmp_path, capsys, official_data):
    refs, preds = tmp_path / "refs", tmp_path / "preds"
    refs.mkdir(), preds.mkdir()
    for name in ("Scan_Exp1_Uniform_A.png",):
        (refs / name).write_bytes((official_data / name).read_bytes())
        (preds / name).write_bytes((official_data / "Scan_Exp1_Uniform_B.png").read_bytes())
    status, out, _ = run(capsys, "score", "--refs", refs, "--preds", preds, "--csv", tmp_path / "s.csv")
    assert status == 0 and "global score" in out
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
])
def test_bad_input_exits_2_with_one_line_reason(tmp_path, capsys, argv, message):
    (tmp_path / "bad.png").write_text("not an image")
    (tmp_path / "bad_phantom.txt").write_text("1 2 3 4\n1 2 3 abc\n")
    status, out, err = run(capsys, *[a.format(tmp=tmp_path) for a in argv])
    assert status == 2
    assert message in err and err.count("\n") == 1 and err.startswith("octcl ")


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


def test_entry_point_runs_as_a_program(tmp_path):
    result = subprocess.run([sys.executable, "-m", "octcl.cli", "devices", "--json"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0
    devices = json.loads(result.stdout)
    assert devices and sum(d["default"] for d in devices) == 1
