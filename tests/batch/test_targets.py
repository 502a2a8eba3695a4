"""Batch targets: recursive discovery, mirrored outputs, and when a scan counts as done."""

import json

import numpy as np
import pytest

from octcl.host.batch.targets import completed_report, find_scans, settings_record, sha256
from octcl.host.stage3.refine import Phase, RefineSchedule


def touch(path, data=b"x"):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


def test_targets_are_found_recursively_and_outputs_mirror_the_tree(tmp_path):
    targets, out = tmp_path / "targets", tmp_path / "targets" / "out"
    for name in ("Male/1990-2000/Cheek/a.npy", "Male/1990-2000/Cheek/b.png", "c.png", "Female/d.npy"):
        touch(targets / name)
    # Not targets: map files, a batch's own pictures, hidden files and folders, other files, the output folder.
    for name in ("c_OAC.png", "c_SC.png", "c_RSC.png", "Female/d.panel.png", "Female/d.score.png", "c.tissue.png",
                 ".e.npy",
                 ".cache/f.npy", "notes.txt", "out/g.npy"):
        touch(targets / name)
    scans = find_scans(targets, out)
    assert [scan.name for scan in scans] == ["Female/d.npy", "Male/1990-2000/Cheek/a.npy",
                                             "Male/1990-2000/Cheek/b.png", "c.png"]
    cheek = scans[1]
    assert cheek.target == targets / "Male/1990-2000/Cheek/a.npy"
    assert cheek.output("phantom") == out / "Male/1990-2000/Cheek/a.txt"
    assert cheek.output("report") == out / "Male/1990-2000/Cheek/a.report.json"
    assert cheek.output("panel") == out / "Male/1990-2000/Cheek/a.panel.png"
    assert cheek.output("plot") == out / "Male/1990-2000/Cheek/a.score.png"


def test_a_scans_pictures_are_this_runs_only(tmp_path):
    """The pictures written are read back; a later run without an attenuation panel (another regime) or a score
    plot (scored once) leaves none of the earlier run's; a scan missing its panel has no pictures to show."""
    scan = find_scans(touch(tmp_path / "t/a.png").parent, tmp_path / "out")[0]
    scan.output("panel").parent.mkdir(parents=True)
    tissue_run = {"panel": b"panel 1", "plot": b"plot 1", "tissue": b"tissue 1"}
    scan.write_pictures(tissue_run)
    assert scan.read_pictures() == tissue_run
    scan.write_pictures({"panel": b"panel 2", "plot": b"plot 2"})
    assert scan.read_pictures() == {"panel": b"panel 2", "plot": b"plot 2"} and not scan.output("tissue").exists()
    scan.write_pictures({"panel": b"panel 3"})
    assert scan.read_pictures() == {"panel": b"panel 3"} and not scan.output("plot").exists()
    scan.output("panel").unlink()
    assert scan.read_pictures() is None


def test_clashing_and_missing_targets_are_refused(tmp_path):
    touch(tmp_path / "t/x/a.png"), touch(tmp_path / "t/x/a.npy")
    with pytest.raises(ValueError, match=r"would write the same outputs: x/a\.npy; x/a\.png"):
        find_scans(tmp_path / "t", tmp_path / "out")
    touch(tmp_path / "empty/a_OAC.png")
    with pytest.raises(FileNotFoundError, match=r"empty: no target scans"):
        find_scans(tmp_path / "empty", tmp_path / "out")
    with pytest.raises(FileNotFoundError, match=r"missing: no such folder"):
        find_scans(tmp_path / "missing", tmp_path / "out")


def test_settings_record_holds_the_options_as_json():
    schedule = RefineSchedule(phases=(Phase(4, 0.01, 0.02),), restarts=())
    record = settings_record(30, 1, {"schedule": schedule})
    assert record["time_budget_s"] == 30.0 and record["seed"] == 1 and record["octcl_version"]
    assert record["options"]["schedule"]["phases"] == [{"iterations": 4, "lr_z_um": 0.01, "lr_u": 0.02,
                                                        "terms": "all", "relative_exponent": 0.0,
                                                        "patience": None}]
    assert json.loads(json.dumps(record)) == record
    with pytest.raises(TypeError, match="invert option of type .* has no JSON form"):
        settings_record(30, 1, {"progress": print})


@pytest.fixture
def done_scan(tmp_path):
    """A scan with the outputs of a finished run: (scan, target SHA-256, settings)."""
    target = touch(tmp_path / "t/a.npy", np.zeros(4, np.uint8).tobytes())
    (scan,) = find_scans(tmp_path / "t", tmp_path / "out")
    settings = settings_record(30, 0, {})
    phantom = b"0 0 1 1\n"
    touch(scan.output("phantom"), phantom)
    record = {**settings, "target_sha256": sha256(target.read_bytes()), "phantom_sha256": sha256(phantom)}
    touch(scan.output("report"), json.dumps({"components": {}, "batch": record}).encode())
    return scan, record["target_sha256"], settings


def test_a_complete_scan_with_the_same_target_and_settings_is_done(done_scan):
    scan, target_sha256, settings = done_scan
    assert completed_report(scan, target_sha256, settings)["batch"]["target_sha256"] == target_sha256


@pytest.mark.parametrize("change", ["target", "budget", "seed", "version", "options"])
def test_another_target_or_setting_is_not_done(done_scan, change):
    scan, target_sha256, settings = done_scan
    changed = {"budget": {"time_budget_s": 31.0}, "seed": {"seed": 1}, "version": {"octcl_version": "0.0.0"},
               "options": {"options": {"schedule": {}}}}.get(change, {})
    assert completed_report(scan, sha256(b"other") if change == "target" else target_sha256,
                            {**settings, **changed}) is None


@pytest.mark.parametrize("damage", ["phantom changed", "phantom missing", "report missing", "report cut",
                                    "report without record"])
def test_incomplete_outputs_are_not_done(done_scan, damage):
    scan, target_sha256, settings = done_scan
    if damage == "phantom changed":
        scan.output("phantom").write_bytes(b"0 0 1 2\n")
    elif damage == "phantom missing":
        scan.output("phantom").unlink()
    elif damage == "report missing":
        scan.output("report").unlink()
    elif damage == "report cut":
        scan.output("report").write_bytes(scan.output("report").read_bytes()[:20])
    else:
        scan.output("report").write_text('{"components": {}}')
    assert completed_report(scan, target_sha256, settings) is None
