"""Phantom text files (load, save, validation) and the baseline generator."""

import os
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import octcl._io
import octcl.phantom
from octcl.config import DEFAULT_CONFIG, ScannerConfig
from octcl.phantom import (MAX_ROW_BYTES, Phantom, PhantomError, _format_rows, _parse_rows, _parse_rows_exact,
                           round_significant)

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
def test_save_writes_eight_significant_digits_by_default(tmp_path):
    rng = np.random.default_rng(0)
    original = Phantom(rng.uniform(-1536, 1536, 200), rng.uniform(-10, 10, 200),
                       rng.uniform(0, 1536, 200), rng.uniform(0, 100, 200))
    path = tmp_path / "p.txt"
    original.save(path)
    loaded = Phantom.load(path)
    assert len(loaded) == 200
    # 8 significant digits: relative error at most half a unit in the 8th digit.
    np.testing.assert_allclose(loaded.as_array(), original.as_array(), rtol=5.000001e-8, atol=0)
    assert not np.array_equal(loaded.as_array(), original.as_array())  # it did round
    first = path.read_text().splitlines()[0].split()
    assert len(first) == 4
    assert all(re.fullmatch(r"-?\d\.\d{7}e[+-]\d\d", token) for token in first), first


def test_save_then_load_is_exact_for_values_with_fewer_digits(tmp_path):
    original = Phantom([-1536.0, 1.23456e-3, 1536.0], [-10.0, 0.0, 2.5],
                       [0.0, 1234.56, 1536.0], [0.0, 0.01, 100.0])
    path = tmp_path / "p.txt"
    for digits in (6, 8):
        original.save(path, significant_digits=digits)
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


def awkward_values(rng, count):
    """Values whose printing is hard to get right: wide magnitudes, ties, powers of ten, signed zeros."""
    return np.concatenate([
        rng.uniform(-1536, 1536, count), rng.uniform(0, 100, count),
        rng.choice([-1, 1], count) * 10.0 ** rng.uniform(-300, 300, count),
        rng.integers(-10**6, 10**6, count) / 2.0 ** rng.integers(0, 30, count),  # binary fractions: exact ties
        [float(f"{v:.{k}f}") for v, k in zip(rng.uniform(-2000, 2000, count), rng.integers(0, 8, count))],
        [0.0, -0.0, 9.999996, 9.999995, 99.5, 0.125, 2.5, 100.0, 1536.0, 1e22, 1e23, 5e-324,
         2.2250738585072014e-308, 1.7976931348623157e308, 1e-100, 9.9999e99, np.nan, np.inf, -np.inf],
    ])


@pytest.mark.parametrize("digits", range(1, 18))
def test_written_text_is_pythons_e_format(digits):
    rng = np.random.default_rng(digits)
    values = awkward_values(rng, 2000 if digits <= 12 else 200)
    rows = values[:values.size // 4 * 4].reshape(-1, 4)
    spec = f".{digits - 1}e"
    expected = "".join(" ".join(format(v, spec) for v in row) + "\n" for row in rows.tolist())
    assert _format_rows(rows, digits).decode() == expected


@pytest.mark.parametrize("digits", [1, 5, 6, 9, 15, 17])
def test_round_significant_is_percent_e_read_back(digits):
    values = awkward_values(np.random.default_rng(100 + digits), 2000)
    expected = np.array([float(f"%.{digits - 1}e" % v) for v in values.tolist()])
    np.testing.assert_array_equal(round_significant(values, digits), expected)
    assert np.array_equal(np.signbit(round_significant(values, digits)), np.signbit(expected))


def test_powers_of_ten_beyond_the_exact_ones_round_correctly_where_certain():
    """m·10^p for |p| > 22, where 10^p is not a float64: the double-double product, where it says it is certain
    (nearly always), is the float nearest the exact value (fractions), and on tokens of the 1e−36 to 1e−11 % of a
    linear-regime phantom's energies the parser and round_significant match Python."""
    from fractions import Fraction
    from octcl.phantom import _times_power_of_ten_rounded

    rng = np.random.default_rng(11)
    significand = rng.integers(10**7, 10**8, 4000).astype(np.float64)
    significand[:8] = [10**7, 10**8 - 1, 12345678, 50000000, 2**26, 2**26 + 1, 99999999, 10**7 + 1]
    power = rng.integers(-300, 300, 4000)
    power[:2000] = rng.integers(-60, 60, 2000)
    values, certain = _times_power_of_ten_rounded(significand, power)
    assert certain[np.abs(power) <= 22].all() and certain[(np.abs(power) <= 280)].mean() > 0.999
    for m, p, value in zip(significand[certain].tolist(), power[certain].tolist(), values[certain].tolist()):
        assert value == float(Fraction(int(m)) * Fraction(10) ** p), (m, p)
    energies = 10.0 ** rng.uniform(-36, -11, 20000)
    np.testing.assert_array_equal(round_significant(energies, 8), [float("%.7e" % v) for v in energies.tolist()])
    rows = np.stack([energies[:5000], energies[5000:10000], energies[10000:15000], energies[15000:]], axis=1)
    tokens = [[format(v, ".7e") for v in row] for row in rows.tolist()]
    assert _parse_rows(_format_rows(rows, 8)).tobytes() == np.array([[float(t) for t in row] for row in tokens]).tobytes()


@pytest.mark.parametrize("digits", [4, 6, 7, 9, 12, 17])
def test_save_load_round_trip_reads_back_the_printed_values(tmp_path, digits):
    rng = np.random.default_rng(digits)
    x, z = rng.uniform(-1500, 1500, 3000), rng.uniform(0, 1500, 3000)  # in range once rounded
    original = Phantom(np.append(x, [-1536.0, 0.0, -0.0]), np.append(rng.uniform(-9.9, 9.9, 3000), [10.0, 0, 0]),
                       np.append(z, [1536.0, 0.0, 1e-30]), np.append(rng.uniform(0, 99.9, 3000), [100.0, 0, 1e-7]))
    path = tmp_path / "p.txt"
    original.save(path, significant_digits=digits)
    expected = np.array([[float(format(v, f".{digits - 1}e")) for v in row] for row in original.as_array().tolist()])
    loaded = Phantom.load(path)
    np.testing.assert_array_equal(loaded.as_array(), expected)
    assert np.array_equal(np.signbit(loaded.as_array()), np.signbit(expected))


def rows_of(*columns):
    """Hypothesis: an (N, 4) float64 array whose columns are drawn from the given float strategies."""
    return st.integers(1, 40).flatmap(lambda count: st.tuples(
        *(arrays(np.float64, count, elements=column) for column in columns)).map(lambda c: np.stack(c, axis=1)))


@settings(max_examples=300, deadline=None)
@given(rows=rows_of(*[st.floats(width=64)] * 4), digits=st.integers(1, 17))
@example(rows=np.array([[0.0, 0.0, 0.0, -7.46141353e-39]]), digits=1)  # a negative value beyond 1e±22
def test_any_float_is_written_as_python_writes_it_and_read_back_as_float_reads_it(rows, digits):
    spec = f".{digits - 1}e"
    tokens = [[format(v, spec) for v in row] for row in rows.tolist()]
    text = _format_rows(rows, digits)
    assert text.decode() == "".join(" ".join(row) + "\n" for row in tokens)
    values = _parse_rows(text)
    if np.isfinite(rows).all():  # 'nan' and 'inf' are left to the line-by-line reader, which refuses them
        expected = np.array([[float(token) for token in row] for row in tokens])
        assert values.tobytes() == expected.tobytes()  # bit for bit, signed zeros included
    else:
        assert values is None


IN_RANGE = (st.floats(-1536, 1536), st.floats(-10, 10), st.floats(0, 1536), st.floats(0, 100))


@settings(max_examples=150, deadline=None)
@given(rows=rows_of(*IN_RANGE), digits=st.integers(4, 17))  # 3 digits write 1536 as 1.54e+03
@example(rows=np.array([[-1e-30, -2.5e-300, 5e-324, 99.99609375]]), digits=6)
def test_save_load_round_trip_is_exact_at_the_written_precision(rows, digits):
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "p.txt"
        Phantom(*rows.T).save(path, significant_digits=digits)
        loaded = Phantom.load(path).as_array()
    spec = f".{digits - 1}e"
    expected = np.array([[float(format(v, spec)) for v in row] for row in rows.tolist()])
    assert loaded.tobytes() == expected.tobytes()
    # The text is within half a unit of its last digit of v, and the double
    # read from it no farther from the text than v: within a unit of v.
    relative = np.abs(loaded - rows) / np.maximum(np.abs(rows), np.finfo(float).tiny)
    assert relative.max() <= 10.0 ** (1 - digits)


def test_byte_order_mark_and_crlf_line_ends_are_read(tmp_path):
    rows = "# x y z E\r\n1.00000e+00 2.0 3e1 4\r\n\r\n-5, 6, 7, 8\r\n"
    plain = write(tmp_path, rows.replace("\r\n", "\n"), "plain.txt")
    windows = tmp_path / "windows.txt"
    windows.write_bytes(b"\xef\xbb\xbf" + rows.encode())
    np.testing.assert_array_equal(Phantom.load(windows).as_array(), [[1, 2, 30, 4], [-5, 6, 7, 8]])
    np.testing.assert_array_equal(Phantom.load(windows).as_array(), Phantom.load(plain).as_array())
    written = tmp_path / "written.txt"
    Phantom([1.5, -2.0], [0.25, 0.0], [3.0, 1000.0], [4.0, 0.5]).save(written)
    windows.write_bytes(b"\xef\xbb\xbf" + written.read_bytes().replace(b"\n", b"\r\n"))
    np.testing.assert_array_equal(Phantom.load(windows).as_array(), Phantom.load(written).as_array())


def test_bad_value_in_a_crlf_file_names_its_line(tmp_path):
    path = tmp_path / "windows.txt"
    path.write_bytes(b"\xef\xbb\xbf0 0 100 1\r\n\r\n0 0 100 -1\r\n")
    with pytest.raises(PhantomError, match=r":3: E = -1 outside \[0, 100\]"):
        Phantom.load(path)


def test_lines_with_separators_but_no_values_are_skipped(tmp_path):
    path = write(tmp_path, ", 1 2 3 4\n,,,\n , \n5,,6 ,7\t8 ,\n")
    np.testing.assert_array_equal(Phantom.load(path).as_array(), [[1, 2, 3, 4], [5, 6, 7, 8]])


@pytest.mark.parametrize("text", [
    "1.00000e+00 2.00000e+00 3.00000e+00 4.00000e+00\n-1.50000e+03 -1.00000e+01 1.53600e+03 1.00000e-02\n",
    "1.0E+00,2.5E-01,3.0E+02,4.0E+00\r\n",          # upper-case, commas, CRLF: still '%.1E'
    "1.5 2.0 3 4\n-1536 -10 0 0\n",                  # plain decimals: np.loadtxt
    "1.000000000000000000e+00 2.000000000000000000e+00 3.000000000000000000e+00 4.0e+00\n",
])
def test_common_formats_take_the_fast_reader(tmp_path, monkeypatch, text):
    path = write(tmp_path, text)
    expected = Phantom.load(path).as_array()

    def refuse(*args):
        raise AssertionError("the exact reader ran")

    monkeypatch.setattr(octcl.phantom, "_parse_rows_exact", refuse)
    np.testing.assert_array_equal(Phantom.load(path).as_array(), expected)


def random_phantom_text(rng) -> str:
    """A small phantom file in a random style, often with something odd or wrong in it."""
    decimals, letter = int(rng.integers(0, 7)), str(rng.choice(["e", "E"]))
    styles = [lambda v: f"{v:.{decimals}{letter}}", lambda v: f"{v:.3f}", lambda v: repr(v), lambda v: f"{v:g}"]
    style = styles[int(rng.integers(0, len(styles)))]
    odd_tokens = ["1e5000", "nan", "-inf", "abc", "1e", "-", "1.2.3", "0x10", "1_0", "\u0661", "+.5", "5.",
                  "1e-5000", "--1", "1-2", "\u00b5", "1,5", "#"]
    odd_lines = ["", "   ", ",,", "# comment", "  # indented µm comment", "1 2 3", "1 2 3 4 5", "\t,\t",
                 "0 0 100 1 # trailing", ", 0 0 100 1", "\ufeff0 0 1 1"]
    separators = [" ", " ", "\t", ",", ", ", "  ", " ,", "\u00a0"]
    line_ends = ["\n", "\n", "\r\n", "\r", "\x0b", "\x0c", "\u2028"]
    odd = rng.random() < 0.6
    lines = []
    for _ in range(int(rng.integers(1, 8))):
        if odd and rng.random() < 0.15:
            lines.append(str(rng.choice(odd_lines)))
            continue
        row = [rng.uniform(-1536, 1536), rng.uniform(-10, 10), rng.uniform(0, 1536), rng.uniform(0, 100)]
        tokens = [style(v) for v in row]
        if odd and rng.random() < 0.2:
            tokens[int(rng.integers(0, 4))] = str(rng.choice(odd_tokens))
        separator = str(rng.choice(separators)) if odd else " "
        lines.append(separator.join(tokens))
    line_end = str(rng.choice(line_ends)) if odd else "\n"
    text = line_end.join(lines) + (line_end if rng.random() < 0.8 else "")
    return ("\ufeff" if rng.random() < 0.2 else "") + text


def outcome(read, path):
    try:
        return read(path).tobytes()
    except PhantomError as exc:
        return str(exc)


def test_fast_reader_agrees_with_the_exact_reader_on_random_files(tmp_path):
    """Phantom.load must return what the line-by-line reader returns, or raise its message."""
    rng = np.random.default_rng(7)
    config = ScannerConfig(max_scatterers=6)

    def exact(path):
        return _parse_rows_exact(path, path.read_bytes(), config, False, 10.0)

    for number in range(400):
        path = tmp_path / f"{number}.txt"
        path.write_bytes(random_phantom_text(rng).encode())
        assert outcome(lambda p: Phantom.load(p, config).as_array(), path) == outcome(exact, path), \
            path.read_bytes()


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


def octcl_file_with(tmp_path, line_number, line, rows=3000):
    """A phantom as octcl writes it (``rows`` rows, 6 digits) with line ``line_number`` replaced by ``line``."""
    rng = np.random.default_rng(line_number)
    path = tmp_path / "written.txt"
    Phantom(rng.uniform(-1536, 1536, rows), rng.uniform(-3, 3, rows), rng.uniform(0, 1536, rows),
            rng.uniform(0, 100, rows)).save(path, significant_digits=6)
    lines = path.read_bytes().split(b"\n")
    lines[line_number - 1] = line.encode()
    path.write_bytes(b"\n".join(lines))
    return path


@pytest.mark.parametrize("line, message", [
    ("1.00000e+00 2.00000e+00 3.00000e+00", "expected 4 columns (x y z E), found 3: '1.00000e+00 2.00000e+00 3.00000e+00'"),
    ("1.00000e+00 2.00000e+00 3.00000e+00 4.00000e+00 5.00000e+00",
     "expected 4 columns (x y z E), found 5: '1.00000e+00 2.00000e+00 3.00000e+00 4.00000e+00 5.00000e+00'"),
    ("1.00000e+00 2.0000O0e+00 3.00000e+00 4.00000e+00", "y = '2.0000O0e+00' is not a number"),
    ("1.00000e+00 2.00000e+00 3.00000e+00 nan", "E = 'nan' is not finite"),
    ("1.00000e+400 2.00000e+00 3.00000e+00 4.00000e+00", "x = '1.00000e+400' is not finite"),
    ("1.00000e+00 2.00000e+00 3.00000e+00 -1.00000e-02", "E = -1.00000e-02 outside [0, 100]"),
    ("1.00000e+00 2.00000e+00 1.53601e+03 4.00000e+00", "z = 1.53601e+03 outside [0, 1536]"),
    ("-1.53700e+03 2.00000e+00 3.00000e+00 4.00000e+00", "x = -1.53700e+03 outside [-1536, 1536]"),
    ("1.00000e+00 1.05000e+01 3.00000e+00 4.00000e+00", "y = 1.05000e+01 outside [-10, 10]"),
])
def test_errors_in_files_the_fast_reader_takes_keep_file_line_and_value(tmp_path, line, message):
    """An octcl-written file goes to the fast reader; a bad row in it is still reported as before."""
    path = octcl_file_with(tmp_path, 2345, line)
    with pytest.raises(PhantomError) as caught:
        Phantom.load(path)
    assert str(caught.value) == f"{path}:2345: {message}"


def test_too_many_rows_in_a_file_the_fast_reader_takes_keeps_its_message(tmp_path):
    path = octcl_file_with(tmp_path, 1, "# header", rows=3001)
    with pytest.raises(PhantomError) as caught:
        Phantom.load(path, config=ScannerConfig(max_scatterers=2999))
    assert str(caught.value) == (f"{path}: 3,000 rows, but the scanner reads only the first 2,999 (number of "
                                 "scatterers in b-scan); use --truncate (Phantom.load(..., truncate=True)) "
                                 "to keep those")
    assert len(Phantom.load(path, config=ScannerConfig(max_scatterers=3000))) == 3000


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


def test_file_far_larger_than_the_rows_allowed_is_refused_before_reading(tmp_path, monkeypatch):
    path = tmp_path / "huge.txt"
    with open(path, "wb") as handle:  # sparse: 8 GB that reading would have to go through
        handle.truncate(8 * 2**30)
    monkeypatch.setattr(octcl.phantom, "_parse_rows", None)  # nothing may get as far as parsing
    with pytest.raises(PhantomError) as caught:
        Phantom.load(path)
    message = str(caught.value)
    limit = DEFAULT_CONFIG.max_scatterers * MAX_ROW_BYTES
    assert message.startswith(f"{path}: {8 * 2**30:,} bytes"), message
    assert f"{limit:,} bytes" in message and "--truncate" in message


def test_size_limit_scales_with_the_rows_the_scanner_reads(tmp_path):
    row = "1.00000e+00 0.00000e+00 1.00000e+00 1.00000e+00\n"
    path = write(tmp_path, row * (5 * MAX_ROW_BYTES // len(row) + 1))
    with pytest.raises(PhantomError, match=f"{5 * MAX_ROW_BYTES:,} bytes"):
        Phantom.load(path, config=SMALL)
    loaded = Phantom.load(path, config=SMALL, truncate=True)  # reads the first 1280 bytes only
    np.testing.assert_array_equal(loaded.as_array(), np.ones((5, 4)) * [1, 0, 1, 1])


def test_truncate_refuses_rows_longer_than_the_size_limit_allows(tmp_path):
    long_row = "0 0 1 1" + " " * 500 + "\n"
    path = write(tmp_path, long_row * 10)
    with pytest.raises(PhantomError) as caught:
        Phantom.load(path, config=SMALL, truncate=True)
    assert str(caught.value).startswith(f"{path}: the first {2 * len(long_row):,} bytes hold only 2 rows")
    path = write(tmp_path, "#" + "-" * (5 * MAX_ROW_BYTES) + "\n" + "0 0 1 1\n" * 10)
    with pytest.raises(PhantomError, match=f"no line ends within the first {5 * MAX_ROW_BYTES:,} bytes"):
        Phantom.load(path, config=SMALL, truncate=True)


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
