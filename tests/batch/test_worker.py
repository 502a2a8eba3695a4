"""One scan of a batch as a worker runs it (octcl/host/batch/worker.py)."""

import io

import numpy as np

from octcl.host.batch.report import comparison_panel, tissue_panel, wants_score_plot
from octcl.host.batch.worker import invert_scan
from octcl.phantom import CONTRACT_Y_LIMIT_UM, Phantom
from octcl.render import render
from octcl.tissue import attenuation_map, transmission_map


def test_a_tissue_scans_pictures_are_those_of_the_phantom_it_sends_back(tmp_path):
    """The comparison and attenuation panels come from invert's own maps of the written phantom (not a second
    render and transmission map): the same pictures as drawn from the phantom file the client receives."""
    levels = render(Phantom.skin(0)).levels
    data = io.BytesIO()
    np.save(data, levels)
    scan = invert_scan("skin.npy", data.getvalue(), 600.0, 0,
                       {"regime": "tissue", "iterations": 2, "field_iterations": 20})
    assert "error" not in scan, scan.get("error")
    (tmp_path / "phantom.txt").write_bytes(scan["phantom"])
    written = Phantom.load(tmp_path / "phantom.txt", y_limit_um=CONTRACT_Y_LIMIT_UM)
    score = scan["report"]["score"]
    title = f"skin.npy: score {score:.5f} after {scan['report']['seconds']['total']:.0f} s"
    assert scan["panel"] == comparison_panel(levels, render(written).levels, title)
    assert scan["tissue"] == tissue_panel(levels, attenuation_map(transmission_map(written)), "skin.npy: attenuation")
    assert "plot" in scan and wants_score_plot(scan["report"]["trace"])


def test_a_scan_scored_once_sends_no_score_plot():
    """A linear run whose start renders the target's levels stops at its one score: a panel and no plot."""
    data = io.BytesIO()
    np.save(data, render(Phantom.skin(1)).levels)
    scan = invert_scan("skin.npy", data.getvalue(), 600.0, 0, {})
    assert "error" not in scan, scan.get("error")
    assert scan["report"]["stop_reason"] == "ceiling" and "panel" in scan and "plot" not in scan
