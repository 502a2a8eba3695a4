"""One scan of a batch as a worker runs it (octcl/host/batch/worker.py)."""

import io

import numpy as np

from octcl.host.batch.report import comparison_panel, tissue_panel
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
