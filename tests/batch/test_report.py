"""A batch's report: summary.csv and summary.json agree, report.html's table is summary.csv's, images inline."""

import base64
import html
import io
import json
import re

import numpy as np
import pytest
from PIL import Image

from octcl.host.batch import report
from octcl.host.batch.report import (COLUMNS, PICTURES, best_so_far, comparison_panel, read_summary_csv, score_plot,
                                     tissue_panel, wants_score_plot, write_reports)
from octcl.host.stage1.levels import target_magnitude
from octcl.phantom import Phantom
from octcl.render import render
from octcl.scorer import COMPONENTS
from octcl.tissue import scan_attenuation

SETTINGS = {"octcl_version": "0.1.0", "time_budget_s": 30.0, "seed": 0, "options": {}}


def make_rows(count: int) -> dict:
    """``count`` done scans with random components, one failed and one pending."""
    rng = np.random.default_rng(count)
    rows = {}
    for index in range(count):
        name = f"group {index % 2}/scan_{index}.npy"
        components = {c: float(rng.uniform(0.9, 1.0)) for c in COMPONENTS}
        rows[name] = {"scan": name, "status": "inverted" if index % 3 else "resumed", **components,
                      "mean": float(np.mean(list(components.values()))), "seconds": float(rng.uniform(10, 50)),
                      "peak_memory_mib": 900.0 + index, "cpu_s": 20.0 + index, "worker": f"host:{100 + index}",
                      "error": None}
    rows["bad.npy"] = {"scan": "bad.npy", "status": "failed", "error": 'bad.npy: float64 array, <"quoted">'}
    rows["later.png"] = {"scan": "later.png", "status": "pending", "error": None}
    return rows


def pictures(name):
    levels = np.random.default_rng(len(name)).integers(0, 256, (256, 512), dtype=np.uint8)
    trace = [{"time_s": 1.0, "score": None}, {"time_s": 2.0, "score": 0.9}, {"time_s": 3.0, "score": 0.95}]
    return {"panel": comparison_panel(levels, levels, name), "plot": score_plot({name: trace}, name)}


def test_summary_files_and_html_table_agree(tmp_path, report_table):
    rows = make_rows(5)
    summary = write_reports(tmp_path, rows, SETTINGS, "local cluster", 12.0, pictures)
    done = [row for row in rows.values() if row["status"] in ("inverted", "resumed")]
    medians = {c: float(np.median([row[c] for row in done])) for c in COMPONENTS}
    assert summary["medians"] == medians and summary["score"] == pytest.approx(np.mean(list(medians.values())))
    assert summary["counts"] == {"inverted": 3, "resumed": 2, "failed": 1, "pending": 1}

    csv_rows = read_summary_csv(tmp_path / "summary.csv")
    assert [row["scan"] for row in csv_rows] == list(rows)
    assert json.loads((tmp_path / "summary.json").read_text()) == json.loads(json.dumps(summary))
    for row in csv_rows:  # the CSV holds the rows exactly (floats round-trip)
        assert {k: v for k, v in row.items() if v not in (None, "")} == \
            {k: v for k, v in rows[row["scan"]].items() if v is not None}

    html = (tmp_path / "report.html").read_text()
    table = report_table(html)
    assert table == [{column: row[column] or None for column in COLUMNS} for row in csv_rows]
    assert f"{summary['score']:.5f}" in html


def test_a_scan_whose_score_was_left_out_is_listed_and_left_out_of_the_medians(tmp_path, report_table):
    """A scan inverted under a budget too short to score it (its components None): its row stays, the medians
    and global score are those of the scored scans, and the summary and page say how many were left out."""
    rows = make_rows(5)
    unscored = next(name for name, row in rows.items() if row["status"] == "inverted")
    rows[unscored].update(dict.fromkeys((*COMPONENTS, "mean")))
    summary = write_reports(tmp_path, rows, SETTINGS, "local cluster", 12.0, pictures)
    scored = [row for row in rows.values() if row["status"] in ("inverted", "resumed") and row["mean"] is not None]
    assert len(scored) == 4 and summary["unscored"] == 1
    assert summary["medians"] == {c: float(np.median([row[c] for row in scored])) for c in COMPONENTS}
    page = (tmp_path / "report.html").read_text()
    assert "1 left out: their time budget left no time to score them" in page
    assert f"{html.escape(unscored)}: score left out</h2>" in page
    assert [row for row in report_table(page) if row["scan"] == unscored][0]["mean"] is None


def test_html_is_self_contained_with_every_panel_inline(tmp_path, monkeypatch):
    rows = make_rows(4)
    write_reports(tmp_path, rows, SETTINGS, None, 1.0, pictures)
    html = (tmp_path / "report.html").read_text()
    assert not re.search(r'(src|href)="(?!data:image/png;base64,|#)', html)  # nothing fetched from elsewhere
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', html)
    assert len(images) == 2 * 4  # a panel and a plot per done scan
    sizes = [Image.open(io.BytesIO(base64.b64decode(data))).size for data in images]
    assert sizes[0] == (4 * 512, 2 * (256 + 16) + 16) and sizes[1] == (640, 320)
    assert "<script>" in html and 'class="sortable"' in html
    # Panels in order of score, lowest first; each linked from its table row.
    done = sorted((row for row in rows.values() if row["status"] != "failed" and "mean" in row),
                  key=lambda row: row["mean"])
    headings = re.findall(r'<section id="([^"]+)"><h2>([^<]+):', html)
    assert [name for _, name in headings] == [row["scan"] for row in done]
    assert all(f'href="#{anchor}"' in html for anchor, _ in headings)
    assert "&lt;&quot;quoted&quot;&gt;" in html  # text is escaped

    monkeypatch.setattr(report, "REPORT_PANELS", 1)
    write_reports(tmp_path, rows, SETTINGS, None, 1.0, pictures)
    html = (tmp_path / "report.html").read_text()
    assert len(re.findall(r"data:image/png", html)) == 2 and "Panels of the 1 lowest-scoring scans" in html
    assert re.findall(r'<section id="[^"]+"><h2>([^<]+):', html) == [done[0]["scan"]]


def test_a_tissue_scan_shows_its_attenuation_panel_after_the_other_two(tmp_path):
    """A scan with a ``tissue`` picture has three images in its section, in PICTURES' order; the others two."""
    rows = make_rows(4)
    tissue_scan = next(name for name, row in rows.items() if row["status"] == "inverted")
    target = render(Phantom.skin(1)).levels
    attenuation = np.zeros(target.shape)

    def with_tissue(name):
        found = pictures(name)
        if name == tissue_scan:
            found["tissue"] = tissue_panel(target, attenuation, name)
        return found

    write_reports(tmp_path, rows, SETTINGS, None, 1.0, with_tissue)
    page = (tmp_path / "report.html").read_text()
    sections = dict(re.findall(r'<section id="[^"]+"><h2>([^<]+):(.*?)</section>', page, re.S))
    assert len(re.findall(r"<img ", sections[tissue_scan])) == 3
    assert all(len(re.findall(r"<img ", body)) == 2 for name, body in sections.items() if name != tissue_scan)
    alts = re.findall(r'<img alt="([^"]+)"', sections[tissue_scan])
    assert alts == [html.escape(f"{tissue_scan}: {what}") for what in PICTURES.values()]


def test_the_tissue_panel_shows_the_phantoms_attenuation_on_the_targets_scale():
    """Three panels side by side, the two µ panels on one colour scale: a phantom whose µ is the target's own
    estimate looks as the middle panel does (the same mean colour over the same region), one with a third of
    it is darker, one with µ = 0 is one colour (the colour map's bottom); the target's OAC map never changes."""
    target = render(Phantom.skin(1)).levels
    estimate = scan_attenuation(target_magnitude(target))
    same, third, flat = (np.asarray(Image.open(io.BytesIO(tissue_panel(target, mu, "t"))).convert("RGB"))
                         .astype(float) for mu in (estimate, estimate / 3, np.zeros(target.shape)))
    assert same.shape == (340, 1500, 3)
    assert np.array_equal(same[:, :480], flat[:, :480])
    rows = slice(100, 200)  # depth pixels ~60–160, inside the axes; the µ panels' axes start 465 pixels apart
    middle, right = (slice(600, 850), slice(1065, 1315))

    def mean_colour(image, columns):
        return image[rows, columns].reshape(-1, 3).mean(axis=0)

    np.testing.assert_allclose(mean_colour(same, right), mean_colour(same, middle), atol=2.0)
    assert mean_colour(third, right).sum() < 0.6 * mean_colour(third, middle).sum()
    assert len(np.unique(flat[rows, right].reshape(-1, 3), axis=0)) == 1


def test_comparison_panel_shows_target_above_rendering():
    rng = np.random.default_rng(3)
    target, rendering = (rng.integers(0, 256, (256, 512), dtype=np.uint8) for _ in range(2))
    panel = np.asarray(Image.open(io.BytesIO(comparison_panel(target, rendering, "title"))))
    np.testing.assert_array_equal(panel[32:32 + 256, :512], target)
    np.testing.assert_array_equal(panel[32 + 256 + 16:32 + 2 * 256 + 16, :512], rendering)


def test_best_so_far_is_what_the_file_holds():
    trace = [{"time_s": 1.0, "score": None}, {"time_s": 2.0, "score": 0.9}, {"time_s": 3.0, "score": 0.8},
             {"time_s": 4.0, "score": 0.95}]
    assert best_so_far(trace) == ([2.0, 3.0, 4.0], [0.9, 0.9, 0.95])


def test_a_run_scored_once_has_no_score_plot():
    """A default linear run's trace (the field, unscored, then its start's one score) has nothing to plot."""
    once = [{"time_s": 2.1, "stage": "field", "score": None}, {"time_s": 2.4, "stage": "initial", "score": 0.9999}]
    assert not wants_score_plot(once)
    assert wants_score_plot(once + [{"time_s": 3.0, "stage": "refine", "score": 0.99991}])
