"""The scanner's depth order: NumPy's classic (pre-SIMD) ``np.argsort``.

``tests/data/depth_order_numpy_1_24_4.npz`` holds arrays ``values_<name>``
and the ``order_<name>`` that ``np.argsort(values)`` of NumPy 1.24.4 (the
classic introsort) returned for them on an x86-64 machine: 2,000 baseline
phantom depths from 500–520 µm (1,279 distinct), an organ pipe
(0, 0, 1, 1, …, 499, 499, …, 0, 0) that drives the quicksort into its
heapsort fallback, 2,000 draws from {−inf, −2.5, −0.0, +0.0, 1e−300, 3, inf,
NaN}, 2,001 integers below 100, and arrays of 17 and 2 elements. The
installed NumPy may sort differently, so these orders are the independent
check; the rest compares the OpenCL kernel with the pure-Python path.
"""

from pathlib import Path

import numpy as np
import pytest

from octcl.device import depth_order as D
from octcl import _reference as ref

FIXTURE = Path(__file__).parents[1] / "data" / "depth_order_numpy_1_24_4.npz"


def fixture_cases():
    """(name, values, NumPy 1.24.4 order) for every array of the fixture."""
    with np.load(FIXTURE) as data:
        names = [name[len("values_"):] for name in data.files if name.startswith("values_")]
        return [(name, data["values_" + name], data["order_" + name].astype(np.int64)) for name in names]


NUMPY_1_24_CASES = fixture_cases()


def organ_pipe(count):
    half = np.arange(count // 2)
    return np.concatenate([half, half[::-1]]).astype(np.float64)


def tied_arrays(seed=11, count=60):
    """Arrays with many ties: few distinct values, sorted runs, organ pipes, rounded depths."""
    rng = np.random.default_rng(seed)
    arrays = []
    for i in range(count):
        n = int(rng.integers(17, 4000))
        pattern = i % 5
        if pattern == 0:
            values = rng.integers(0, max(2, n // 3), n)
        elif pattern == 1:
            values = rng.integers(0, 4, n)
        elif pattern == 2:
            values = np.sort(rng.integers(0, 40, n))[::-1 if i % 2 else 1]
        elif pattern == 3:
            values = organ_pipe(n) // int(rng.integers(1, 4))
        else:
            values = np.round(rng.uniform(0.0, 1536.0, n), 0)
        arrays.append(np.asarray(values, dtype=np.float64))
    return arrays


@pytest.fixture
def heapsort_ranges(monkeypatch):
    """Lengths of the ranges the pure-Python path hands to its heapsort fallback."""
    lengths = []
    heapsort = D._heapsort_range

    def recording(key, order, first, n):
        lengths.append(n)
        heapsort(key, order, first, n)

    monkeypatch.setattr(D, "_heapsort_range", recording)
    return lengths


# ------------------------------------------------------- NumPy 1.24.4 orders
@pytest.mark.parametrize("values, expected", [case[1:] for case in NUMPY_1_24_CASES],
                         ids=[case[0] for case in NUMPY_1_24_CASES])
def test_matches_numpy_1_24_argsort(values, expected):
    keys = D.sort_keys(values)
    np.testing.assert_array_equal(D.introsort_argsort_python(keys), expected)
    np.testing.assert_array_equal(D.introsort_argsort_opencl(keys), expected)
    np.testing.assert_array_equal(D.depth_order(values, backend="python"), expected)
    np.testing.assert_array_equal(D.depth_order(values, backend="opencl"), expected)


def test_fixture_exercises_unstable_ties_and_the_heapsort_fallback(heapsort_ranges):
    cases = {name: (values, expected) for name, values, expected in NUMPY_1_24_CASES}
    unstable = [name for name, (values, expected) in cases.items()
                if not np.array_equal(expected, np.argsort(values, kind="stable"))]
    assert set(unstable) >= {"phantom_depths", "organ_pipe", "signed_specials", "small_integers", "tiny_17"}
    D.introsort_argsort_python(D.sort_keys(cases["organ_pipe"][0]))
    assert heapsort_ranges


# ------------------------------------------------------ OpenCL against Python
def test_opencl_equals_python_on_tied_arrays(heapsort_ranges):
    reached_heapsort = 0
    for values in tied_arrays():
        keys = D.sort_keys(values)
        heapsort_ranges.clear()
        expected = D.introsort_argsort_python(keys)
        reached_heapsort += bool(heapsort_ranges)
        np.testing.assert_array_equal(D.introsort_argsort_opencl(keys), expected)
        assert np.all(np.diff(values[expected]) >= 0)
    assert reached_heapsort >= 5  # the organ pipes


def test_heapsort_fallback_on_large_organ_pipe(heapsort_ranges):
    values = organ_pipe(50_000)
    keys = D.sort_keys(values)
    expected = D.introsort_argsort_python(keys)
    assert heapsort_ranges
    np.testing.assert_array_equal(D.introsort_argsort_opencl(keys), expected)
    assert np.all(np.diff(values[expected]) >= 0)


@pytest.mark.parametrize("count", [0, 1, 2, 16, 17, 1000])
def test_tiny_and_all_equal_arrays(count):
    rng = np.random.default_rng(count)
    for values in (rng.integers(0, 3, count).astype(np.float64), np.full(count, 7.0)):
        keys = D.sort_keys(values)
        expected = D.introsort_argsort_python(keys)
        assert sorted(expected.tolist()) == list(range(count))
        np.testing.assert_array_equal(D.introsort_argsort_opencl(keys), expected)
        np.testing.assert_array_equal(D.depth_order(values, backend="opencl"), expected)
        assert np.all(np.diff(values[expected]) >= 0)
        if count <= D.SMALL_PARTITION + 1:  # insertion sort only: stable
            np.testing.assert_array_equal(expected, np.argsort(values, kind="stable"))


# ------------------------------------------------------------------ short-cuts
@pytest.mark.parametrize("backend", ["python", "opencl"])
def test_without_ties_the_stable_sort_is_returned_directly(monkeypatch, backend):
    def must_not_run(*args):
        raise AssertionError("the introsort ran although no depths are tied")

    monkeypatch.setattr(D, "introsort_argsort_python", must_not_run)
    monkeypatch.setattr(D, "introsort_argsort_opencl", must_not_run)
    z = np.random.default_rng(5).uniform(0.0, 1536.0, 100_000)
    np.testing.assert_array_equal(D.depth_order(z, backend=backend), np.argsort(z, kind="stable"))


def test_without_ties_every_path_gives_the_stable_order():
    z = np.random.default_rng(6).permutation(5000) * 0.3 - 700.0
    keys = D.sort_keys(z)
    stable = np.argsort(z, kind="stable")
    np.testing.assert_array_equal(D.introsort_argsort_python(keys), stable)
    np.testing.assert_array_equal(D.introsort_argsort_opencl(keys), stable)


def test_guess_changes_speed_not_result():
    rng = np.random.default_rng(8)
    tied = np.round(rng.uniform(0.0, 300.0, 20_000), 1)
    continuous = rng.uniform(0.0, 300.0, 20_000)
    for z in (tied, continuous):
        expected = D.depth_order(z, backend="opencl")
        for guess in (expected, rng.permutation(z.size), np.argsort(z + rng.normal(0.0, 0.5, z.size))):
            np.testing.assert_array_equal(D.depth_order(z, backend="opencl", guess=guess), expected)
    with pytest.raises(ValueError, match="guess"):
        D.depth_order(tied, guess=np.arange(3))


# ---------------------------------------------------------------- the keys
def test_sort_keys_order_exactly_as_numpy_compares_doubles():
    rng = np.random.default_rng(9)
    specials = [-np.inf, -1e308, -1.0, -5e-324, -0.0, 0.0, 5e-324, 2.2e-308, 1.0, 1e308, np.inf]
    z = np.concatenate([rng.normal(0.0, 1e3, 3000), rng.choice(specials, 1000),
                        np.nextafter(1.0, [0.0, 2.0])])
    keys = D.sort_keys(z)
    a, b = rng.integers(0, z.size, (2, 20_000))
    np.testing.assert_array_equal(keys[a] < keys[b], z[a] < z[b])
    np.testing.assert_array_equal(keys[a] == keys[b], z[a] == z[b])
    with_nan = D.sort_keys([np.nan, -np.nan, np.inf, -np.nan])
    assert with_nan[0] == with_nan[1] == with_nan[3] > with_nan[2]


def test_auto_falls_back_to_python_without_opencl(monkeypatch):
    from octcl.device.runtime import OpenCLUnavailableError

    def no_opencl(*args):
        raise OpenCLUnavailableError("no OpenCL platform found")

    values = organ_pipe(3000)
    expected = D.depth_order(values, backend="opencl")
    monkeypatch.setattr(D, "introsort_argsort_opencl", no_opencl)
    np.testing.assert_array_equal(D.depth_order(values), expected)


def test_rejects_unknown_backend():
    with pytest.raises(ValueError, match="backend"):
        D.depth_order([1.0, 1.0], backend="cuda")


# ------------------------------------------------------------ where it is used
def test_reference_uses_the_classic_order():
    z = np.round(np.random.default_rng(10).uniform(0.0, 100.0, 3000), 0)
    expected = D.depth_order(z, backend="opencl")
    assert not np.array_equal(expected, np.argsort(z, kind="stable"))
    np.testing.assert_array_equal(ref.depth_order(z), expected)
