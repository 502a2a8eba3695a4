"""What a batch leaves to read: ``summary.csv``, ``summary.json`` and a self-contained ``report.html``.

- ``summary.csv``: one row per scan, :data:`COLUMNS` (the 8 score
  components, their mean, seconds, peak memory, status, ...).
- ``summary.json``: the same rows under ``scans``, the per-component medians
  over the scans that have a phantom, the global score (the mean of those
  8 medians, as SynthOCT ranks a set), counts by status and the settings.
- ``report.html``: one file with everything inline (images as base64 PNG,
  a few lines of script to sort the table by any column): the global score,
  the table, and per scan its comparison panel (target and rendering of the
  phantom, each as scan, OAC, SC and RSC) with its best score against time
  where the run scored more than once (:func:`wants_score_plot`) and, in
  the tissue regime, the phantom's attenuation beside its target's
  (:func:`tissue_panel`).
  Panels are embedded for the :data:`REPORT_PANELS` lowest-scoring scans
  (about 0.3 MB each), the ones worth a look; every scan keeps its own
  ``NAME.panel.png`` (and ``NAME.score.png``) beside its phantom.

Statuses: ``inverted`` (this run), ``resumed`` (done by an earlier run with
the same target and settings, :func:`octcl.host.batch.targets.completed_report`),
``failed`` (with its one-line reason in ``error``), ``pending`` (not run:
the batch was interrupted).
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
import math

import numpy as np

from octcl._io import atomic_write
from octcl.scorer import COMPONENTS, global_score

#: Columns of summary.csv, in order.
COLUMNS = ("scan", "status", *COMPONENTS, "mean", "seconds", "peak_memory_mib", "cpu_s", "worker", "error")
#: Columns holding numbers (empty where a scan has none).
NUMERIC = (*COMPONENTS, "mean", "seconds", "peak_memory_mib", "cpu_s")
#: Statuses of a scan that has a phantom.
DONE = ("inverted", "resumed")
#: Scans whose panels report.html embeds, lowest scores first.
REPORT_PANELS = 100
#: The four maps of a panel row, as labelled.
PANEL_MAPS = ("scan", "OAC", "SC", "RSC")
#: The pictures of a scan's section, in order, with what each shows: the comparison panel of every scan, the
#: score plot of a scan scored more than once (:func:`wants_score_plot`), the attenuation panel
#: (:func:`tissue_panel`) of a scan inverted in the tissue regime.
PICTURES = {"panel": "target and rendering, scan, OAC, SC and RSC", "plot": "best exact score against time",
            "tissue": "the target's OAC map and attenuation beside the phantom's own"}


def _png(image) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format="PNG")
    return buffer.getvalue()


def comparison_panel(target: np.ndarray, render_levels: np.ndarray, title: str) -> bytes:
    """PNG of the target (top row) and the rendering (bottom row), each as scan, OAC, SC and RSC.

    ``target`` is in either form of :mod:`octcl.host.pipeline.target`, ``render_levels``
    the rendering's (Nz, Nx) levels. Full resolution, one pixel per scan
    pixel, so speckle can be compared; the maps are the official
    processor's (:func:`octcl.maps.map_levels`) of the scan the task
    contract reads.
    """
    from PIL import Image, ImageDraw

    from octcl.maps import map_levels

    from ..pipeline.target import target_scan

    rows = []
    for image in (target, render_levels):
        scan = target_scan(image)
        maps = map_levels(scan)
        rows.append([np.rint(scan * 255).astype(np.uint8), maps["OAC"], maps["SC"], maps["RSC"]])
    height, width = render_levels.shape
    label = 16
    image = Image.new("L", (4 * width, 2 * (height + label) + label), 255)
    draw = ImageDraw.Draw(image)
    draw.text((4, 2), title, fill=0)
    for r, (row_name, row) in enumerate(zip(("target", "rendering"), rows)):
        top = label + r * (height + label)
        for c, (map_name, levels) in enumerate(zip(PANEL_MAPS, row)):
            draw.text((c * width + 4, top + 2), f"{row_name} {map_name}", fill=0)
            image.paste(Image.fromarray(levels), (c * width, top + label))
    return _png(image)


def tissue_panel(target: np.ndarray, attenuation_per_mm: np.ndarray, title: str) -> bytes:
    """PNG (matplotlib) of the target's OAC map beside its µ and the phantom's µ, on one colour scale.

    Left, the target's OAC map as the scorer compares it (:func:`octcl.maps.map_levels`: the depth-resolved
    estimate on the grey levels read as 40 dB, shown from its minimum to its 99th percentile, so without a
    unit). Middle, µ (mm⁻¹) of the target by the same estimator on the magnitudes the scanner's own 51 dB
    display stands for (:func:`octcl.tissue.scan_attenuation`; it overestimates towards the bottom of the data,
    where it takes all the light to be gone). Right, ``attenuation_per_mm`` (Nz, Nx), the
    phantom's µ from its own transmission (:func:`octcl.tissue.attenuation_map`): a phantom that makes the
    scan's dimming by shadowing shows the middle panel's µ, one that paints it into its energies shows about
    0. The two µ panels share a colour scale up to the 99th percentile of both over the target's visible
    tissue (:data:`octcl.tissue.VISIBLE_LEVEL`).
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from octcl.maps import map_levels
    from octcl.tissue import VISIBLE_LEVEL, scan_attenuation

    from ..pipeline.target import target_scan
    from ..stage1.levels import target_levels, target_magnitude

    scan = target_scan(target)
    levels = target_levels(scan)
    target_attenuation = scan_attenuation(target_magnitude(levels))
    visible = levels >= VISIBLE_LEVEL
    if not visible.any():
        visible = np.ones_like(visible)
    top = max(float(np.percentile(np.concatenate([target_attenuation[visible], attenuation_per_mm[visible]]), 99)),
              1e-3)
    figure = Figure(figsize=(15, 3.4), dpi=100, layout="constrained")
    axes = figure.subplots(1, 3)
    axes[0].imshow(map_levels(scan)["OAC"], cmap="gray", vmin=0, vmax=255, aspect="auto")
    axes[0].set_title("target: OAC map (the scorer's)")
    for ax, data, name in ((axes[1], target_attenuation, "target: µ, depth-resolved estimate (51 dB)"),
                           (axes[2], attenuation_per_mm, "phantom: µ from its own transmission")):
        shown = ax.imshow(data, cmap="magma", vmin=0, vmax=top, aspect="auto")
        ax.set_title(name)
    figure.colorbar(shown, ax=axes[1:], label="µ (mm⁻¹)")
    for ax in axes:
        ax.set(xlabel="A-scan", ylabel="depth pixel")
    figure.suptitle(title)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return buffer.getvalue()


def best_so_far(trace: list[dict]) -> tuple[list[float], list[float]]:
    """(seconds, best exact score so far) at each exact evaluation of an invert report's trace.

    The best so far is what the phantom file holds at that time.
    """
    times, scores, best = [], [], -np.inf
    for entry in trace:
        if entry.get("score") is not None:
            best = max(best, entry["score"])
            times.append(entry["time_s"])
            scores.append(best)
    return times, scores


def wants_score_plot(trace: list[dict]) -> bool:
    """Whether an invert report's trace has a score against time to plot: two exact evaluations or more.

    A default run of the linear regime scores once, when its start is at
    its aimed levels (stage 3 then stops, ``stop_reason`` ``ceiling``): a
    plot of one point says nothing the table does not, and drawing it cost
    a worker 0.11 s a scan and matplotlib's import once.
    """
    return len(best_so_far(trace)[0]) >= 2


def score_plot(traces: dict[str, list[dict]], title: str, size=(6.4, 3.2)) -> bytes:
    """PNG (matplotlib) of the best exact score against seconds, one line per ``{name: invert trace}``."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    figure = Figure(figsize=size, dpi=100, layout="constrained")
    axes = figure.add_subplot()
    for name, trace in traces.items():
        axes.plot(*best_so_far(trace), marker=".", label=name)
    axes.set(xlabel="seconds", ylabel="best exact score", title=title)
    axes.grid(alpha=0.3)
    if len(traces) > 1:
        axes.legend()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return buffer.getvalue()


def summarise(rows: dict[str, dict], settings: dict, cluster: str | None, wall_s: float) -> dict:
    """The summary of a batch: rows by scan name, medians, global score, counts, settings."""
    done = [row for row in rows.values() if row["status"] in DONE]
    summary = {"scans": rows,
               "counts": {status: sum(row["status"] == status for row in rows.values())
                          for status in (*DONE, "failed", "pending")},
               **settings, "cluster": cluster, "wall_s": wall_s}
    if done:
        summary["median_seconds"] = float(np.median([row["seconds"] for row in done]))
    # A scan whose score a time budget left out (its ``mean`` None) has a phantom but no components.
    scored = [row for row in done if row.get("mean") is not None]
    summary["unscored"] = len(done) - len(scored)
    if scored:
        medians, score = global_score(scored)
        summary.update(medians=medians, score=score)
    return summary


def _csv_text(rows: dict[str, dict]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(COLUMNS)
    for row in rows.values():
        writer.writerow(["" if row.get(column) is None else
                         repr(float(row[column])) if column in NUMERIC else row[column] for column in COLUMNS])
    return buffer.getvalue()


def read_summary_csv(path) -> list[dict]:
    """summary.csv's rows as dicts, numbers as floats (None where empty)."""
    with open(path, newline="", encoding="utf-8") as handle:
        return [{column: (float(value) if value else None) if column in NUMERIC else value
                 for column, value in row.items()} for row in csv.DictReader(handle)]


_STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #222; }
h1 { margin-bottom: 0.2em; } .score { font-size: 2.2em; font-weight: bold; }
table { border-collapse: collapse; font-size: 0.85em; margin: 1em 0; }
th, td { border: 1px solid #ccc; padding: 3px 7px; text-align: right; }
td:first-child, th:first-child, td.text { text-align: left; }
th { background: #eee; position: sticky; top: 0; }
table.sortable th { cursor: pointer; } th[aria-sort="ascending"]::after { content: " \\25B2"; }
th[aria-sort="descending"]::after { content: " \\25BC"; }
tr.failed td { background: #fde8e8; } tr.pending td { color: #888; }
.wide { overflow-x: auto; }
section { margin: 2em 0; border-top: 1px solid #ccc; } section img { max-width: 100%; display: block; }
.meta { color: #555; }
"""

# Sort the scans table by the clicked column: numbers by data-value, text as text.
_SCRIPT = """
document.querySelectorAll("table.sortable th").forEach((th, column) => th.addEventListener("click", () => {
  const body = th.closest("table").tBodies[0];
  const ascending = th.getAttribute("aria-sort") !== "ascending";
  th.closest("tr").querySelectorAll("th").forEach(h => h.removeAttribute("aria-sort"));
  th.setAttribute("aria-sort", ascending ? "ascending" : "descending");
  const key = row => { const cell = row.cells[column]; const v = cell.dataset.value;
    return v === undefined ? cell.textContent : v === "" ? NaN : parseFloat(v); };
  const rows = Array.from(body.rows).sort((a, b) => {
    const x = key(a), y = key(b);
    if (typeof x === "number" && typeof y === "number") {
      if (isNaN(x) || isNaN(y)) return isNaN(x) - isNaN(y);
      return ascending ? x - y : y - x; }
    return ascending ? String(x).localeCompare(y) : String(y).localeCompare(x); });
  rows.forEach(row => body.appendChild(row));
}));
"""


def _cell(row: dict, column: str) -> str:
    value = row.get(column)
    if column in NUMERIC:
        shown = "" if value is None else f"{value:.0f}" if column in ("seconds", "peak_memory_mib", "cpu_s") \
            else f"{value:.5f}"
        return f'<td data-value="{"" if value is None else repr(float(value))}">{shown}</td>'
    text = html.escape("" if value is None else str(value))
    if column == "scan" and row["status"] in DONE:
        text = f'<a href="#{html.escape(_anchor(row["scan"]))}">{text}</a>'
    return f'<td class="text">{text}</td>'


def _anchor(name: str) -> str:
    return "scan-" + "".join(c if c.isalnum() else "-" for c in name)


def _image(data: bytes, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(data).decode()}">'


def report_html(summary: dict, images: dict[str, dict[str, bytes]]) -> str:
    """The page: global score, medians, the sortable scans table, and each scan's ``{kind: PNG}`` pictures
    (:data:`PICTURES`' kinds, in its order)."""
    rows = summary["scans"]
    counts = ", ".join(f"{n} {status}" for status, n in summary["counts"].items() if n)
    score = f"{summary['score']:.5f}" if "score" in summary else "none (no scan inverted and scored)"
    if summary.get("unscored"):
        score += (f" (over the scored scans; {summary['unscored']} left out: their time budget left no time to "
                  "score them)")
    parts = [
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        "<title>octcl batch report</title>", f"<style>{_STYLE}</style></head><body>",
        "<h1>octcl batch report</h1>",
        f'<p>Global score (mean of the 8 per-component medians): <span class="score">{score}</span></p>',
        f'<p class="meta">{len(rows)} scans: {html.escape(counts)}. Time budget {summary["time_budget_s"]:g} s '
        f'per scan, seed {summary["seed"]}, octcl {html.escape(summary["octcl_version"])}; '
        f'{html.escape(summary["cluster"] or "no cluster needed")}; {summary["wall_s"]:.0f} s wall.</p>',
    ]
    if "medians" in summary:
        parts += ['<table class="medians"><thead><tr><th>median</th>',
                  *(f"<th>{c}</th>" for c in COMPONENTS), "</tr></thead><tbody><tr><td>all scans</td>",
                  *(f"<td>{summary['medians'][c]:.5f}</td>" for c in COMPONENTS), "</tr></tbody></table>"]
    parts += ['<div class="wide"><table class="sortable" id="scans"><thead><tr>',
              *(f"<th>{column}</th>" for column in COLUMNS), "</tr></thead><tbody>"]
    for row in rows.values():
        parts += [f'<tr class="{html.escape(row["status"])}">', *(_cell(row, column) for column in COLUMNS), "</tr>"]
    parts.append("</tbody></table></div>")
    if len(images) < sum(row["status"] in DONE for row in rows.values()):
        parts.append(f"<p>Panels of the {len(images)} lowest-scoring scans; every scan's are in its "
                     "NAME.panel.png (and NAME.score.png where it was scored more than once).</p>")
    for name, pictures in images.items():
        row = rows[name]
        shown_score = "score left out" if row["mean"] is None else f"{row['mean']:.5f}"
        parts += [f'<section id="{html.escape(_anchor(name))}"><h2>{html.escape(name)}: {shown_score}</h2>',
                  f'<p class="meta">{row["status"]}, {row["seconds"]:.0f} s, peak memory '
                  f'{row["peak_memory_mib"]:.0f} MiB</p>',
                  *(_image(pictures[kind], f"{name}: {what}") for kind, what in PICTURES.items() if kind in pictures),
                  "</section>"]
    parts += [f"<script>{_SCRIPT}</script>", "</body></html>"]
    return "\n".join(parts)


def write_reports(out_dir, rows: dict[str, dict], settings: dict, cluster: str | None, wall_s: float,
                  images) -> dict:
    """Write summary.csv, summary.json and report.html into ``out_dir`` (each atomically); return the summary.

    ``images(name)`` returns a scan's ``{kind: PNG}`` (:data:`PICTURES`' kinds; ``panel`` and ``plot`` at
    least), or None if it has none.
    """
    from pathlib import Path

    out_dir = Path(out_dir)
    summary = summarise(rows, settings, cluster, wall_s)
    with atomic_write(out_dir / "summary.csv", "w") as handle:
        handle.write(_csv_text(rows))
    with atomic_write(out_dir / "summary.json", "w") as handle:
        json.dump(summary, handle, indent=1)
    shown = sorted((row for row in rows.values() if row["status"] in DONE),
                   key=lambda row: math.inf if row["mean"] is None else row["mean"])
    embedded = {}
    for row in shown[:REPORT_PANELS]:
        pair = images(row["scan"])
        if pair is not None:
            embedded[row["scan"]] = pair
    with atomic_write(out_dir / "report.html", "w") as handle:
        handle.write(report_html(summary, embedded))
    return summary


__all__ = ["COLUMNS", "PICTURES", "REPORT_PANELS", "best_so_far", "comparison_panel", "read_summary_csv", "report_html",
           "score_plot", "summarise", "tissue_panel", "write_reports"]
