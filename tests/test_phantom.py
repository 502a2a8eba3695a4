"""Phantom text files (load, save, validation) and the baseline generator."""

import os
import re

import numpy as np
import pytest

import octcl._io
from octcl.config import ScannerConfig
from octcl.phantom import Phantom, PhantomError

SMALL = ScannerConfig(max_scatterers=5)


def write(tmp_path, text, name="phantom.txt"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def legacy_recipe(seed, count):
    """The baseline generator, independently: NumPy's legacy global RNG, then '%.4e'."""
    state = np.random.get_state()
    try:
        np.random.seed(seed)
        x = (np.random.rand(count) - 0.5) * 3072.0
        y = (np.random.rand(count) - 0.5) * 20.0
        z = np.random.rand(count) * 1536.0
    finally:
        np.random.set_state(state)
    return x, y, z


def as_written(value):
    return float("%.4e" % value)


# ---------------------------------------------------------------- round trip
def test_save_then_load_keeps_six_significant_digits(tmp_path):
    rng = np.random.default_rng(0)
    original = Phantom(rng.uniform(-1536, 1536, 200), rng.uniform(-10, 10, 200),
                       rng.uniform(0, 1536, 200), rng.uniform(0, 100, 200))
    path = tmp_path / "p.txt"
    original.save(path)
    loaded = Phantom.load(path)
    assert len(loaded) == 200
    # 6 significant digits: relative error at most half a unit in the 6th digit.
    np.testing.assert_allclose(loaded.as_array(), original.as_array(), rtol=5.000001e-6, atol=0)
    assert not np.array_equal(loaded.as_array(), original.as_array())  # it did round
    first = path.read_text().splitlines()[0].split()
    assert len(first) == 4
    assert all(re.fullmatch(r"-?\d\.\d{5}e[+-]\d\d", token) for token in first), first


def test_save_then_load_is_exact_for_six_digit_values(tmp_path):
    original = Phantom([-1536.0, 1.23456e-3, 1536.0], [-10.0, 0.0, 2.5],
                       [0.0, 1234.56, 1536.0], [0.0, 0.01, 100.0])
    path = tmp_path / "p.txt"
    original.save(path)
    assert np.array_equal(Phantom.load(path).as_array(), original.as_array())


def test_load_accepts_whitespace_commas_blank_and_comment_lines(tmp_path):
    path = write(tmp_path, "# x y z E\n"
                           "\n"
                           "1.0 2.0 3.0 4.0\n"
                           "   # indented comment\n"
                           "5,6,7,8\n"
                           "-9.5,\t-1e0 ,  1.5e+02\t50\n"
                           "   \t  \n"
                           "1e1, 0, 0, 1e2,\n")
    loaded = Phantom.load(path)
    np.testing.assert_array_equal(loaded.as_array(), [[1, 2, 3, 4], [5, 6, 7, 8],
                                                      [-9.5, -1, 150, 50], [10, 0, 0, 100]])


def test_load_without_trailing_newline(tmp_path):
    path = write(tmp_path, "1 2 3 4\n5 6 7 8")
    assert len(Phantom.load(path)) == 2


# ------------------------------------------------------------------ baseline
@pytest.mark.parametrize("seed", [42, 101])
def test_uniform_baseline_is_the_legacy_recipe_rounded_by_percent_4e(seed):
    count = 2000
    phantom = Phantom.baseline("uniform", seed, count=count)
    x, y, z = legacy_recipe(seed, count)
    for column, values in ((phantom.x_um, x), (phantom.y_um, y), (phantom.z_um, z)):
        for j in (0, 1, 17, 999, count - 1):
            assert column[j] == as_written(values[j])
    np.testing.assert_allclose(phantom.x_um, x, rtol=5e-5)
    assert np.all(phantom.energy_pct == 1.0)


def test_official_size_baseline_matches_recipe_at_sampled_rows():
    phantom = Phantom.baseline("uniform", 42)
    assert len(phantom) == 300_000
    x, y, z = legacy_recipe(42, 300_000)
    for j in (0, 1, 123_456, 299_999):
        assert (phantom.x_um[j], phantom.y_um[j], phantom.z_um[j]) == (
            as_written(x[j]), as_written(y[j]), as_written(z[j]))
    assert np.abs(phantom.x_um).max() <= 1536 and np.abs(phantom.y_um).max() <= 10
    assert 0 <= phantom.z_um.min() and phantom.z_um.max() <= 1536


def test_layers_baseline_energy_follows_unrounded_depth():
    count = 5000
    phantom = Phantom.baseline("layers", 42, count=count)
    x, y, z = legacy_recipe(42, count)
    expected = np.where(z <= 400.0, 0.01, 2.5)
    np.testing.assert_array_equal(phantom.energy_pct, expected)
    np.testing.assert_array_equal(phantom.z_um, [as_written(v) for v in z])
    assert set(np.unique(phantom.energy_pct)) == {0.01, 2.5}


def test_baseline_rejects_unknown_kind():
    with pytest.raises(PhantomError, match="'rings'"):
        Phantom.baseline("rings")


def test_amplitude_is_sqrt_of_energy_fraction():
    phantom = Phantom([0, 0, 0], [0, 0, 0], [1, 2, 3], [100.0, 25.0, 1.0])
    np.testing.assert_allclose(phantom.amplitude, [1.0, 0.5, 0.1], rtol=1e-15)


def test_columns_of_different_length_are_refused():
    with pytest.raises(PhantomError, match="differ in length"):
        Phantom([0, 1], [0, 1], [0, 1], [1])


# ---------------------------------------------------------------- bad files
GOOD = "0 0 100 1\n"


@pytest.mark.parametrize("line, fragments", [
    ("1 2 3", ["found 3", "'1 2 3'"]),
    ("1 2 3 4 5", ["found 5", "'1 2 3 4 5'"]),
    ("1 2 abc 4", ["z", "'abc'", "not a number"]),
    ("1 2 3 nan", ["E", "'nan'", "not finite"]),
    ("1 -inf 3 4", ["y", "'-inf'", "not finite"]),
    ("1 2 3 1e5000", ["E", "'1e5000'", "not finite"]),
    ("0 0 100 -0.5", ["E = -0.5", "[0, 100]"]),
    ("0 0 100 100.01", ["E = 100.01", "[0, 100]"]),
    ("0 0 -1e-3 1", ["z = -1e-3", "[0, 1536]"]),
    ("0 0 1536.1 1", ["z = 1536.1", "[0, 1536]"]),
    ("1537 0 100 1", ["x = 1537", "[-1536, 1536]"]),
    ("-1536.5 0 100 1", ["x = -1536.5", "[-1536, 1536]"]),
    ("0 10.5 100 1", ["y = 10.5", "[-10, 10]"]),
    ("0 -11 100 1", ["y = -11", "[-10, 10]"]),
])
def test_bad_row_error_names_file_line_and_value(tmp_path, line, fragments):
    path = write(tmp_path, "# header\n" + GOOD + "\n" + line + "\n" + GOOD)
    with pytest.raises(PhantomError) as caught:
        Phantom.load(path)
    message = str(caught.value)
    assert message.startswith(f"{path}:4:"), message
    for fragment in fragments:
        assert fragment in message, message


def test_range_limits_themselves_are_accepted(tmp_path):
    path = write(tmp_path, "-1536 -10 0 0\n1536 10 1536 100\n")
    np.testing.assert_array_equal(Phantom.load(path).as_array(),
                                  [[-1536, -10, 0, 0], [1536, 10, 1536, 100]])


def test_y_limit_is_configurable(tmp_path):
    path = write(tmp_path, "0 5 100 1\n")
    assert len(Phantom.load(path)) == 1
    with pytest.raises(PhantomError, match=r":1: y = 5 outside \[-3, 3\]"):
        Phantom.load(path, y_limit_um=3.0)


def test_ranges_follow_the_config(tmp_path):
    path = write(tmp_path, "0 0 700 1\n")
    small_depth = ScannerConfig(depth_pixels=100)  # 600 µm deep
    with pytest.raises(PhantomError, match=r":1: z = 700 outside \[0, 600\]"):
        Phantom.load(path, config=small_depth)


@pytest.mark.parametrize("text", ["", "\n\n  \n", "# only\n# comments\n\n"])
def test_file_without_rows_is_refused(tmp_path, text):
    path = write(tmp_path, text)
    with pytest.raises(PhantomError) as caught:
        Phantom.load(path)
    assert str(caught.value) == f"{path}: empty phantom (no scatterer rows)"


def test_too_many_rows_is_an_error_that_mentions_truncation(tmp_path):
    path = write(tmp_path, "".join(f"{i} 0 {i} 1\n" for i in range(7)))
    with pytest.raises(PhantomError) as caught:
        Phantom.load(path, config=SMALL)
    message = str(caught.value)
    assert str(path) in message and "7 rows" in message and "first 5" in message
    assert "truncate=True" in message and "--truncate" in message


def test_truncate_keeps_exactly_the_first_rows(tmp_path):
    path = write(tmp_path, "# comment\n" + "".join(f"{i} 0 {i} 1\n\n" for i in range(7)))
    loaded = Phantom.load(path, config=SMALL, truncate=True)
    np.testing.assert_array_equal(loaded.x_um, [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(loaded.z_um, [0, 1, 2, 3, 4])


def test_truncated_rows_are_not_validated(tmp_path):
    # The scanner never reads rows past the limit, so a bad value there is harmless.
    path = write(tmp_path, "".join(f"{i} 0 {i} 1\n" for i in range(5)) + "0 0 -5 1\n")
    assert len(Phantom.load(path, config=SMALL, truncate=True)) == 5


def test_exactly_max_rows_is_accepted(tmp_path):
    path = write(tmp_path, "".join(f"{i} 0 {i} 1\n" for i in range(5)))
    assert len(Phantom.load(path, config=SMALL)) == 5


def test_binary_file_is_refused_as_not_text(tmp_path):
    path = tmp_path / "scan.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe")
    with pytest.raises(PhantomError) as caught:
        Phantom.load(path)
    assert str(caught.value).startswith(f"{path}: not a text file"), str(caught.value)


def test_directory_is_refused(tmp_path):
    with pytest.raises(PhantomError) as caught:
        Phantom.load(tmp_path)
    assert str(caught.value) == f"{tmp_path}: is a directory, not a phantom file"


def test_missing_file_is_refused(tmp_path):
    path = tmp_path / "nope.txt"
    with pytest.raises(PhantomError) as caught:
        Phantom.load(path)
    assert str(caught.value) == f"{path}: no such file"


# ------------------------------------------------------------ validate()
def test_validate_reports_first_bad_scatterer():
    phantom = Phantom([0, 0, 2000], [0, 0, 0], [1, -1, 1], [1, 1, 1])
    with pytest.raises(PhantomError, match=r"scatterer 2: z = -1.0 outside \[0, 1536\]"):
        phantom.validate()
    assert [v[:2] for v in phantom.range_violations()] == [(1, "z"), (2, "x")]


def test_validate_rejects_more_rows_than_the_scanner_reads():
    phantom = Phantom(np.zeros(6), np.zeros(6), np.ones(6), np.ones(6))
    with pytest.raises(PhantomError, match="6 scatterers.*at most 5"):
        phantom.validate(SMALL)
    phantom.validate(ScannerConfig(max_scatterers=6))


def test_validate_contract_y_limit():
    phantom = Phantom([0], [4.0], [1], [1])
    phantom.validate()
    with pytest.raises(PhantomError, match="y = 4.0"):
        phantom.validate(y_limit_um=3.0)


# ----------------------------------------------------------- atomic save
class FailingHandle:
    """Wraps a file object; every write stores half its data, then fails as a full disk would."""

    def __init__(self, handle):
        self._handle = handle
        self.writes = 0

    def write(self, data):
        self.writes += 1
        self._handle.write(data[: len(data) // 2])
        raise OSError("No space left on device")

    def __getattr__(self, name):
        return getattr(self._handle, name)

    def __enter__(self):
        self._handle.__enter__()
        return self

    def __exit__(self, *exc):
        return self._handle.__exit__(*exc)


def test_failed_write_leaves_earlier_file_intact_and_no_temp_file(tmp_path, monkeypatch):
    path = tmp_path / "p.txt"
    Phantom([1.0], [2.0], [3.0], [4.0]).save(path)
    before = path.read_bytes()
    real_fdopen = os.fdopen
    monkeypatch.setattr(octcl._io.os, "fdopen", lambda *a, **k: FailingHandle(real_fdopen(*a, **k)))
    with pytest.raises(OSError, match="No space left"):
        Phantom(np.arange(100.0), np.zeros(100), np.ones(100), np.ones(100)).save(path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.txt"]


def test_failed_sync_leaves_no_file_behind(tmp_path, monkeypatch):
    path = tmp_path / "sub" / "new.txt"

    def fail(fd):
        raise OSError("I/O error")

    monkeypatch.setattr(octcl._io.os, "fsync", fail)
    with pytest.raises(OSError, match="I/O error"):
        Phantom([1.0], [2.0], [3.0], [4.0]).save(path)
    assert list(path.parent.iterdir()) == []


def test_save_replaces_an_existing_file(tmp_path):
    path = tmp_path / "p.txt"
    Phantom(np.zeros(3), np.zeros(3), np.ones(3), np.ones(3)).save(path)
    Phantom([5.0], [0.0], [6.0], [7.0]).save(path)
    np.testing.assert_array_equal(Phantom.load(path).as_array(), [[5, 0, 6, 7]])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.txt"]
