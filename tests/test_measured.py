"""Durations measured on this machine (octcl/measured.py): kept per name in the cache, the last few, read back."""

import pytest

from octcl.measured import MeasuredTimes


@pytest.fixture
def cache(monkeypatch, tmp_path):
    monkeypatch.setenv("OCTCL_CACHE_DIR", str(tmp_path))
    return tmp_path


def test_the_last_figures_of_a_name_are_kept_and_their_median_answered(cache):
    times = MeasuredTimes("spans.json", kept=3)
    assert times.times("decode") == [] and times.median("decode") is None
    for seconds in (5.0, 1.0, 2.0, 4.0):
        times.record("decode", seconds)
    times.record("write", 0.25)
    assert times.times("decode") == [1.0, 2.0, 4.0] and times.median("decode") == 2.0
    assert times.longest("decode", 9.0) == 4.0 and times.longest("render", 9.0) == 9.0
    assert MeasuredTimes("spans.json").times("write") == [0.25]  # another instance reads the same file
    assert (cache / "spans.json").exists()


@pytest.mark.parametrize("contents", ["not json", "[1, 2]", '{"decode": "fast"}', '{"decode": [-1, "x", 2.5]}'])
def test_a_file_that_cannot_be_read_as_figures_counts_as_empty_and_is_mended_by_a_record(cache, contents):
    (cache / "spans.json").write_text(contents)
    times = MeasuredTimes("spans.json")
    assert times.times("decode") == ([2.5] if "2.5" in contents else [])
    times.record("decode", 1.0)
    assert times.times("decode")[-1] == 1.0


def test_a_cache_that_cannot_be_written_is_left_as_it_is(monkeypatch, tmp_path):
    blocked = tmp_path / "file"
    blocked.write_text("")
    monkeypatch.setenv("OCTCL_CACHE_DIR", str(blocked / "cache"))  # a folder below a file: no write can succeed
    times = MeasuredTimes("spans.json")
    times.record("decode", 1.0)
    assert times.times("decode") == []
