"""Shared pytest fixtures."""

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The reference data folder, /work/shared/data (see its README.md)."""
    path = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    assert path.is_dir(), f"reference data folder missing: {path}"
    return path


@pytest.fixture(scope="session")
def lpips_weights() -> Path:
    """The cached LPIPS weights; fails (not skips) with the fetch hint when missing."""
    from octcl._lpips import WeightsMissingError, check_weights

    try:
        return check_weights()
    except WeightsMissingError as exc:
        pytest.fail(str(exc), pytrace=False)


@pytest.fixture(scope="session")
def official_uniform_metrics(shared_data) -> dict:
    """Official MS-SSIM and LPIPS of Uniform_A against Uniform_B: {map: {metric: value}}."""
    import csv

    with open(shared_data / "official" / "metrics_exp1_uniform.csv", newline="") as handle:
        return {
            row["Map_Type"]: {"MS-SSIM": float(row["MS-SSIM"]), "LPIPS": float(row["LPIPS"])}
            for row in csv.DictReader(handle)
        }


@pytest.fixture(scope="session")
def official_uniform_maps(shared_data) -> tuple[dict, dict]:
    """The official Struct/OAC/SC/RSC map PNGs of Uniform_A and Uniform_B as the metric reads them."""
    from octcl.scorer import _read_map_for_metrics

    def maps(scan):
        suffixes = {"Struct": "", "OAC": "_OAC", "SC": "_SC", "RSC": "_RSC"}
        return {
            name: _read_map_for_metrics(shared_data / "official" / f"Scan_{scan}{suffix}.png")
            for name, suffix in suffixes.items()
        }

    return maps("Exp1_Uniform_A"), maps("Exp1_Uniform_B")


@pytest.fixture(scope="session")
def official_reference():
    """``rendering(kind, seed)``: float64 reference rendering of a baseline phantom, made once per session."""
    from octcl.phantom import Phantom
    from octcl.render import render

    cache = {}

    def rendering(kind, seed):
        if (kind, seed) not in cache:
            cache[kind, seed] = render(Phantom.baseline(kind, seed), backend="numpy")
        return cache[kind, seed]

    return rendering


@pytest.fixture(scope="session")
def report_table():
    """``report_table(html_text)``: the scans table of a batch's report.html as {column: cell} rows.

    A cell is its ``data-value`` as a float (None where empty) for number
    columns, else its text.
    """
    from html.parser import HTMLParser

    class Table(HTMLParser):
        def __init__(self):
            super().__init__()
            self.inside, self.header, self.rows, self.cell = False, [], [], None

        def handle_starttag(self, tag, attrs):
            attrs = dict(attrs)
            if tag == "table" and attrs.get("id") == "scans":
                self.inside = True
            elif self.inside and tag == "tr":
                self.rows.append([])
            elif self.inside and tag in ("td", "th"):
                value = attrs.get("data-value")
                self.cell = {"value": None if value in (None, "") else float(value), "numeric": value is not None,
                             "text": "", "header": tag == "th"}

        def handle_data(self, data):
            if self.cell is not None:
                self.cell["text"] += data

        def handle_endtag(self, tag):
            if tag == "table":
                self.inside = False
            elif self.inside and tag in ("td", "th") and self.cell is not None:
                self.rows[-1].append(self.cell)
                self.cell = None

    def parse(text: str) -> list[dict]:
        table = Table()
        table.feed(text)
        header, *rows = table.rows
        names = [cell["text"] for cell in header]
        return [{name: cell["value"] if cell["numeric"] else (cell["text"] or None)
                 for name, cell in zip(names, row)} for row in rows]

    return parse
