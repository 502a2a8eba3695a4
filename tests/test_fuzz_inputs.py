"""Property-based fuzzing of every input reader: phantom files, Configuration.ini, PNG and ``.npy`` scans.

Each reader gets generated files (valid ones, ones with values at and past
every limit, other separators, line ends and encodings, huge lines and
headers), mutations of them (truncations, flipped, inserted, deleted and
repeated bytes) and random bytes. It must either return what it documents
or raise its module's own error with a message that starts with the file's
name: never another exception, and never a hang (an alarm after
:data:`HANG_S` seconds fails the example with its input).

The budgets (:data:`EXAMPLES`, stated in ``docs/robustness.md``) keep the
file near half a minute on one core; ``pytest tests/test_fuzz_inputs.py
--fuzz-long[=FACTOR]`` runs FACTOR (default 50) times as many, drawn anew
each run (the default runs are derandomized: the same inputs every time).
"""

from __future__ import annotations

import contextlib
import io
import math
import signal
import struct
import zlib
from unittest import mock

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st
from PIL import Image

import octcl.phantom
from octcl._io import (MAX_IMAGE_PIXELS, PNG_SIGNATURE, ImageFormatError, decode_scan_levels, read_png_pixels,
                       read_scan_pixels)
from octcl.config import ConfigError, ScannerConfig
from octcl.host.pipeline.target import decode_target, read_target
from octcl.phantom import Phantom, PhantomError
from octcl.scorer import _read_map_for_metrics

#: Examples per input path in a default run (``--fuzz-long`` multiplies them).
EXAMPLES = {"phantom": 400, "config": 300, "png": 300, "npy": 300}
#: Seconds one example may take before it counts as a hang (the slowest take ~0.05 s).
HANG_S = 20
SHAPE = (256, 512)


@contextlib.contextmanager
def no_hang(seconds: float = HANG_S):
    """Raise TimeoutError in the main thread if the block runs longer than ``seconds``."""
    def interrupt(signum, frame):
        raise TimeoutError(f"no result after {seconds} s")

    previous = signal.signal(signal.SIGALRM, interrupt)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


# ------------------------------------------------------------ mutations
_EDITS = st.lists(st.tuples(st.sampled_from(["truncate", "flip", "insert", "delete", "repeat", "overwrite"]),
                            st.integers(0, 2**20), st.binary(min_size=1, max_size=8)), max_size=3)


def mutate(data: bytes, edits) -> bytes:
    """Apply (operation, position, bytes) edits: positions wrap to the data's length."""
    for operation, position, payload in edits:
        at = position % (len(data) + 1)
        if operation == "truncate":
            data = data[:at]
        elif operation == "flip" and at < len(data):
            data = data[:at] + bytes([data[at] ^ payload[0] or 1]) + data[at + 1:]
        elif operation == "insert":
            data = data[:at] + payload + data[at:]
        elif operation == "delete":
            data = data[:at] + data[at + len(payload):]
        elif operation == "repeat":  # a long run of one slice: huge lines, huge headers
            data = data[:at] + data[at:at + len(payload)] * (payload[0] * 40) + data[at:]
        elif operation == "overwrite":
            data = data[:at] + payload + data[at + len(payload):]
    return data


def files(valid: st.SearchStrategy[bytes]) -> st.SearchStrategy[tuple[bytes, bool]]:
    """(bytes, edited): a generated file, mutated a third of the time, or random bytes."""
    edited = st.tuples(valid, _EDITS.filter(bool)).map(lambda pair: (mutate(*pair), True))
    return st.one_of(valid.map(lambda data: (data, False)), edited,
                     st.binary(max_size=600).map(lambda data: (data, True)))


# ------------------------------------------------------------ phantom files
_LIMITS = [0.0, -0.0, 1536.0, -1536.0, 1536.0000000000002, -1536.0000000000002, 10.0, -10.0, 10.000000000000002,
           100.0, 100.00000000000001, -5e-324, 5e-324, 1e-300, 1e308, 3.0]
_ODD_TOKENS = ["nan", "NaN", "inf", "-inf", "1e999", "-1e-400", "0x10", "1_0", "+.5", "5.", ".", "e5", "1e", "--1",
               "1e+", "\u0661\u0662", "\u00a0", "1,5", "1.2.3", "٫", "9" * 400, "0." + "0" * 400 + "1"]


def _number_text(value: float, style: str) -> str:
    return {"e7": f"{value:.7e}", "e4": f"{value:.4e}", "repr": repr(value), "g": f"{value:g}",
            "f3": f"{value:.3f}", "E": f"{value:.2E}"}[style]


_NUMBER = st.one_of(
    st.tuples(st.one_of(st.sampled_from(_LIMITS), st.floats(-2000, 2000), st.floats(allow_nan=True)),
              st.sampled_from(["e7", "e4", "repr", "g", "f3", "E"])).map(lambda pair: _number_text(*pair)),
    st.sampled_from(_ODD_TOKENS))
_LINE = st.one_of(
    st.tuples(st.lists(_NUMBER, min_size=4, max_size=4), st.sampled_from([" ", "\t", ",", ", ", " ,", "  ", ";"]),
              st.sampled_from(["", " ", "\t"])).map(lambda parts: parts[2] + parts[1].join(parts[0])),
    st.lists(_NUMBER, min_size=0, max_size=6).map(" ".join),
    st.sampled_from(["", "# x y z E", "  # comment é", "#" + "#" * 3000, " " * 3000, "1 2 3 4 # trailing"]))
_PHANTOM_TEXT = st.tuples(st.lists(_LINE, max_size=12), st.sampled_from(["\n", "\r\n", "\r", "\u2028"]),
                          st.booleans()).map(lambda parts: parts[1].join(parts[0]) + (parts[1] if parts[2] else ""))
_PHANTOM_FILE = st.tuples(_PHANTOM_TEXT, st.sampled_from(["utf-8", "utf-8", "utf-8-sig", "utf-16", "latin-1"])).map(
    lambda pair: pair[0].encode(pair[1], errors="replace"))


def test_phantom_reader_loads_or_names_the_file(tmp_path, fuzz_settings):
    """Phantom.load of any file: the rows the line-by-line reference reads (the fast reader switched off gives
    the same rows or the same error), or a PhantomError starting with the path; the row limit small enough to
    be crossed (and with it the file-size limit, 256 bytes a row)."""
    path = tmp_path / "phantom.txt"

    @fuzz_settings(EXAMPLES["phantom"])
    @given(file=files(_PHANTOM_FILE), max_rows=st.integers(1, 8), truncate=st.booleans())
    def check(file, max_rows, truncate):
        path.write_bytes(file[0])
        config = ScannerConfig(max_scatterers=max_rows)
        outcomes = []
        for fast in (True, False):
            with no_hang(), mock.patch.object(octcl.phantom, "_parse_rows",
                                              octcl.phantom._parse_rows if fast else lambda data: None):
                try:
                    outcomes.append(Phantom.load(path, config, truncate=truncate).as_array())
                except PhantomError as exc:
                    assert str(exc).startswith(f"{path}:"), exc
                    outcomes.append(str(exc))
        fast, reference = outcomes
        if isinstance(reference, str):
            assert fast == reference
            seen.add("refused")
        else:
            assert isinstance(fast, np.ndarray) and fast.shape == reference.shape
            np.testing.assert_array_equal(fast, reference)
            assert 1 <= len(fast) <= max_rows and np.isfinite(fast).all()
            seen.add("loaded")

    seen = set()
    check()
    assert seen == {"loaded", "refused"}  # the inputs reach both outcomes


# ------------------------------------------------------------ Configuration.ini
_KEYS = ["A-scan pixel numbers", "vertical pixel size mcm", "central wavelength mcm", "number of a-scans in b-scan",
         "Xmax mcm", "beam radius mcm", "number of scatterers in b-scan", "number of b-scans", "Ymax mcm",
         "scan filename", "NUMBER OF SCATTERERS IN B-SCAN"]
_CONFIG_VALUE = st.one_of(
    st.integers(-10, 10**6).map(str), st.sampled_from(["256", "512", "300000", "0", "-1", "1e300", "1e400", "nan",
                                                       "inf", "2.5", "1e-320", "", "abc", "255", "8192",
                                                       "1" * 500, "4096", "16777216"]),
    st.floats(allow_nan=True).map(repr), st.text(max_size=20))
_CONFIG_LINE = st.one_of(
    st.tuples(st.sampled_from(_KEYS), st.sampled_from([" = ", "=", ": ", " : "]), _CONFIG_VALUE).map("".join),
    st.sampled_from(["[Parameters]", "[parameters]", "[Other]", "; comment", "# comment", "", "  indented = 1",
                     "no separator", "[Parameters", "%(x)s = 1", "x" * 5000]))
_CONFIG_FILE = st.tuples(st.booleans(), st.lists(_CONFIG_LINE, max_size=10), st.sampled_from(["\n", "\r\n", "\r"]),
                         st.sampled_from(["utf-8", "utf-8-sig", "utf-16", "latin-1"])).map(
    lambda parts: parts[2].join(["[Parameters]"] * parts[0] + parts[1]).encode(parts[3], errors="replace"))


def test_configuration_reader_loads_or_names_the_file(tmp_path, fuzz_settings):
    """ScannerConfig.from_ini of any file: a configuration whose B-scan octcl can read back, or a ConfigError
    starting with the path."""
    path = tmp_path / "Configuration.ini"

    @fuzz_settings(EXAMPLES["config"])
    @given(file=files(_CONFIG_FILE))
    def check(file):
        path.write_bytes(file[0])
        try:
            with no_hang():
                config = ScannerConfig.from_ini(path)
        except ConfigError as exc:
            assert str(exc).startswith(f"{path}:"), exc
            seen.add("refused")
            return
        assert config.depth_pixels * config.a_scans <= MAX_IMAGE_PIXELS
        assert all(math.isfinite(value) and value > 0 for value in vars(config).values())
        seen.add("loaded")

    seen = set()
    check()
    assert seen == {"loaded", "refused"}


# ------------------------------------------------------------ PNG scans
def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


@st.composite
def _png_files(draw) -> bytes:
    """A PNG by Pillow (any mode, small or B-scan sized), or one whose header, with a valid checksum, says
    anything (sizes up to 2^32 - 1, any bit depth and colour type) over little or no data."""
    if draw(st.booleans()):
        mode = draw(st.sampled_from(["L", "LA", "RGB", "RGBA", "P", "I;16", "1"]))
        shape = draw(st.sampled_from([SHAPE, (1, 1), (3, 7), (256, 511)]))
        seed = draw(st.integers(0, 3))
        levels = np.random.default_rng(seed).integers(0, 256 if seed else 2, shape, dtype=np.uint8)
        buffer = io.BytesIO()
        Image.fromarray(levels).convert(mode).save(buffer, format="PNG",
                                                   **({"interlace": 1} if draw(st.booleans()) else {}))
        return buffer.getvalue()
    width, height = (draw(st.one_of(st.sampled_from([0, 1, 256, 512, 4096, 4097, 2**31, 2**32 - 1]),
                                    st.integers(0, 2**32 - 1))) for _ in range(2))
    header = struct.pack(">IIBBBBB", width, height, draw(st.sampled_from([1, 2, 4, 8, 16, 0, 255])),
                         draw(st.sampled_from([0, 2, 3, 4, 6, 1, 7])), 0, 0, draw(st.sampled_from([0, 1, 2])))
    body = draw(st.sampled_from([b"", zlib.compress(b""), zlib.compress(bytes(512 * 1024)),
                                 zlib.compress(bytes(4 * 513))]))
    return PNG_SIGNATURE + _png_chunk(b"IHDR", header) + _png_chunk(b"IDAT", body) + _png_chunk(b"IEND", b"")


def _png_bytes(levels: np.ndarray, mode: str) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(levels).convert(mode).save(buffer, format="PNG")
    return buffer.getvalue()


_GREY_ALPHA_SCAN = _png_bytes(np.arange(256 * 512, dtype=np.uint32).reshape(SHAPE).astype(np.uint8), "LA")


def test_png_readers_read_or_name_the_file(tmp_path, fuzz_settings):
    """Every PNG reader (pixels as stored, with and without a shape; B-scan levels; the metric's map reading;
    an inversion target) returns the documented array or raises ImageFormatError starting with the file."""
    path = tmp_path / "scan.png"

    @fuzz_settings(EXAMPLES["png"])
    @given(file=files(_png_files()), shape=st.sampled_from([None, SHAPE]))
    @example(file=(_GREY_ALPHA_SCAN, False), shape=SHAPE)  # found by this test: the metric's reader took it
    def check(file, shape):
        data = file[0]
        path.write_bytes(data)
        readers = {
            "pixels": lambda: read_png_pixels(path, shape),
            "scan pixels": lambda: read_scan_pixels(path, shape),
            "levels": lambda: decode_scan_levels(data, SHAPE, str(path)),
            "map": lambda: _read_map_for_metrics(path),
            "target": lambda: read_target(path),
            "target bytes": lambda: decode_target(data, name=str(path)),
        }
        for name, read in readers.items():
            try:
                with no_hang():
                    array = read()
            except ImageFormatError as exc:
                assert str(exc).startswith(f"{path}:"), (name, exc)
                seen.add("refused")
                continue
            seen.add(f"{name} read")
            assert isinstance(array, np.ndarray) and array.size <= 4 * MAX_IMAGE_PIXELS, name
            if name in ("pixels", "scan pixels"):
                assert array.dtype == np.uint8 and array.ndim == 3 and array.shape[2] in (1, 2, 3, 4)
                assert shape is None or array.shape[:2] == shape
            elif name == "map":
                assert array.ndim == 2 and array.dtype == np.float64 and 0 <= array.min() <= array.max() <= 1
            else:
                assert array.dtype == np.uint8 and array.shape[:2] == SHAPE, name

    seen = set()
    check()
    assert seen == {"refused", "pixels read", "scan pixels read", "levels read", "map read", "target read",
                    "target bytes read"}


# ------------------------------------------------------------ .npy scans
@st.composite
def _npy_files(draw) -> bytes:
    """A ``.npy`` by NumPy (any dtype, shape and order), or one whose header text says anything a header can
    (huge, negative or many dimensions, odd dtypes, object arrays, other versions, long padding)."""
    if draw(st.booleans()):
        dtype = draw(st.sampled_from(["u1", "u2", "f4", "f8", "i8", "?", "c8", "S3", "U2", "V4",
                                      "u1,u1", "(2,)u1"]))
        shape = draw(st.sampled_from([SHAPE, (512, 256), (256, 512, 3), (0,), (2, 3), ()]))
        array = np.zeros(shape, dtype)
        buffer = io.BytesIO()
        np.save(buffer, np.asfortranarray(array) if draw(st.booleans()) else array)
        return buffer.getvalue()
    shape = tuple(draw(st.lists(st.one_of(st.sampled_from([0, 1, 256, 512, -1, 2**31, 2**63 - 1, 2**64]),
                                          st.integers(-2, 600)), max_size=4)))
    descr = draw(st.sampled_from(["'|u1'", "'<f8'", "'|O'", "'>u2'", "'|V0'", "'|S0'", "[('a', '|u1')]",
                                  "'|b1'", "'x'", "3", "'<M8[s]'", "'|u1', 'extra': 1"]))
    fortran = draw(st.sampled_from(["False", "True", "0", "'no'"]))
    text = f"{{'descr': {descr}, 'fortran_order': {fortran}, 'shape': {shape!r}, }}"
    text += " " * draw(st.sampled_from([0, 10, 70000])) + "\n"
    version = draw(st.sampled_from([(1, 0), (2, 0), (3, 0), (9, 9)]))
    length = struct.pack("<H" if version == (1, 0) else "<I", len(text) % (2**16 if version == (1, 0) else 2**32))
    payload = bytes(draw(st.sampled_from([0, 100, 256 * 512, 256 * 512 - 1])))
    return b"\x93NUMPY" + bytes(version) + length + text.encode("latin-1") + payload


# NumPy parses a .npy header with ast.literal_eval, which warns about the odd escapes of generated headers.
@pytest.mark.filterwarnings("ignore:invalid escape sequence:DeprecationWarning")
def test_npy_reader_reads_or_names_the_file(tmp_path, fuzz_settings):
    """decode_scan_levels, decode_target and the scan file reader (read_scan_pixels, as octcl score and maps
    read) of any bytes starting as a ``.npy``: a (256, 512) uint8 array (levels, or their grey RGBA pixels), or an
    ImageFormatError starting with the file's name; nothing is unpickled."""
    source = "Male/Cheek/scan.npy"
    path = tmp_path / "scan.npy"

    @fuzz_settings(EXAMPLES["npy"])
    @given(file=files(_npy_files()))
    # Found by this test: shapes whose size overflows, dtypes of no bytes, headers that tokenize refuses.
    @example(file=(b"\x93NUMPY\x01\x00N\x00{'descr': '<f8', 'fortran_order': False, "
                   b"'shape': (0, 9223372036854775807), }\n", True))
    @example(file=(b"\x93NUMPY\x01\x008\x00{'descr': '|V0', 'fortran_order': False, 'shape': (), }\n", True))
    @example(file=(b"\x93NUMPY\x01\x00\x10\x00{'descr': ('|u1',\n", True))
    def check(file):
        data = file[0]
        path.write_bytes(data)
        readers = [(lambda: decode_scan_levels(data, SHAPE, source), source, SHAPE),
                   (lambda: decode_target(data, name=source), source, SHAPE),
                   (lambda: read_scan_pixels(path), str(path), SHAPE + (4,))]
        for read, name, shape in readers:
            try:
                with no_hang():
                    levels = read()
            except ImageFormatError as exc:
                assert str(exc).startswith(f"{name}:"), exc
                seen.add("refused")
                continue
            assert levels.dtype == np.uint8 and levels.shape == shape
            seen.add("read")

    seen = set()
    check()
    assert seen == {"read", "refused"}
