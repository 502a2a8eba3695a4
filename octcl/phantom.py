"""Digital phantoms: clouds of point scatterers, their text format and checks.

A phantom is a set of point scatterers j with lateral position x_j, elevation
y_j and depth z_j (all in µm) and energy E_j, the percentage of the incident
energy the scatterer reflects (amplitude a_j = sqrt(E_j / 100)).

The file format is plain text, one scatterer per row: ``x y z E``, separated
by whitespace or commas; blank lines and lines starting with ``#`` are
ignored. octcl writes :data:`SIGNIFICANT_DIGITS` = 8 significant digits in
scientific notation (``'%.7e'``).

Why 8: a depth written with d digits is off by up to 0.5·10^(e−d+1) µm
(e = ⌊log10 z⌋), a carrier phase error of 2·k0 times that (2·k0 ≈ 9.67
rad/µm), and speckle follows the phase. ``scripts/bench_io.py`` writes
``Phantom.skin(0)`` (295,000 unrounded scatterers) with d digits, renders the
file and scores it against the unrounded phantom's rendering:

====== ======= ============== ================ ===========
digits file MB max phase rad pixels changed % score
====== ======= ============== ================ ===========
6      14.5    4.8e−2         5.5              0.999860
7      15.6    4.8e−3         0.48             0.999987
8      16.8    4.8e−4         0.050            0.999997
9      18.0    4.8e−5         0.008            0.999999
====== ======= ============== ================ ===========

Saving and loading take the same time at each (within the machine's noise;
docs/benchmarks.md). An inverted phantom (``orange.png``, refined for 24
iterations) lost 2.6e−5 at 6 digits and nothing at 7–9: rounding costs more
the closer the phantom's speckle matches. Six digits, the published
method's, cost up to 1.4e−4 of score, more than the 1e−4 within which
inversion schedules are compared scan by scan; 8 cost 3e−6 for 16 % more
bytes, and their step at depth, 1e−4 µm for z ≥ 1000 µm, is finer than
refinement's smallest depth step (2.5e−4 µm), whose iterates are scored on
the file's grid. Nine digits change about as many pixels (0.008 %) as the
float32 kernels differ from float64 (0.002–0.006 %) and gain 2e−6.
"""

from __future__ import annotations

import codecs
import fractions
import functools
import io
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._io import atomic_write, read_at_most
from .config import DEFAULT_CONFIG, ScannerConfig


class PhantomError(ValueError):
    """A phantom that cannot be used; the message names file, line and value."""


#: Elevation limit of the task contract for submitted phantoms (µm).
CONTRACT_Y_LIMIT_UM = 3.0
#: Elevation limit of phantoms octcl reads (the baseline generator draws |y| ≤ 10 µm).
READ_Y_LIMIT_UM = 10.0
#: Rows octcl aims for when it writes a phantom for submission.
TARGET_ROWS = 295_000

#: Significant digits of the values octcl writes (:meth:`Phantom.save`; the module docstring says why 8).
SIGNIFICANT_DIGITS = 8

#: Bytes a row may take, on average, in a file octcl reads: four values of up
#: to 24 characters ('-1.2345678901234567e-308'), their separators and the line
#: end come to about 100; 256 leaves room for padding and comments. A file
#: larger than ``max_scatterers`` such rows is refused before it is read.
MAX_ROW_BYTES = 256

#: A value as Python's float() reads it: a run of bytes between separators.
_TOKEN = re.compile(r"[^,\s]+")


@dataclass
class Phantom:
    """A digital phantom: point scatterers with position (µm) and energy (%).

    Attributes
    ----------
    x_um, y_um, z_um : ndarray of float64, shape (N,)
        Lateral position, elevation and depth of each scatterer in µm.
    energy_pct : ndarray of float64, shape (N,)
        E_j, percentage of energy reflected, in [0, 100].
    """

    x_um: np.ndarray
    y_um: np.ndarray
    z_um: np.ndarray
    energy_pct: np.ndarray

    def __post_init__(self):
        columns = [np.ascontiguousarray(c, dtype=np.float64).reshape(-1) for c in
                   (self.x_um, self.y_um, self.z_um, self.energy_pct)]
        if len({c.size for c in columns}) != 1:
            raise PhantomError(f"columns differ in length: {[c.size for c in columns]}")
        self.x_um, self.y_um, self.z_um, self.energy_pct = columns

    def __len__(self) -> int:
        return self.x_um.size

    @property
    def amplitude(self) -> np.ndarray:
        """a_j = sqrt(E_j / 100), the field amplitude reflectivity."""
        return np.sqrt(self.energy_pct / 100.0)

    def as_array(self) -> np.ndarray:
        """(N, 4) array of ``x y z E`` rows."""
        return np.stack([self.x_um, self.y_um, self.z_um, self.energy_pct], axis=1)

    # ------------------------------------------------------------------ checks
    def range_violations(self, config: ScannerConfig = DEFAULT_CONFIG,
                         y_limit_um: float = READ_Y_LIMIT_UM) -> list[tuple[int, str, float, str]]:
        """List (row index, column, value, allowed range) of out-of-range values.

        The ranges are |x| ≤ Xmax/2, |y| ≤ ``y_limit_um``, 0 ≤ z ≤ Nz·Δz and
        0 ≤ E ≤ 100; non-finite values are always violations.
        """
        half_width = config.xmax_um / 2
        depth = config.depth_range_um
        checks = (
            ("x", self.x_um, -half_width, half_width),
            ("y", self.y_um, -y_limit_um, y_limit_um),
            ("z", self.z_um, 0.0, depth),
            ("E", self.energy_pct, 0.0, 100.0),
        )
        violations = []
        for name, values, low, high in checks:
            bad = ~((values >= low) & (values <= high))  # also catches NaN
            for row in np.flatnonzero(bad)[:5]:
                violations.append((int(row), name, float(values[row]), f"[{low:g}, {high:g}]"))
        return sorted(violations)

    def validate(self, config: ScannerConfig = DEFAULT_CONFIG,
                 y_limit_um: float = READ_Y_LIMIT_UM, source: str = "phantom") -> None:
        """Raise :class:`PhantomError` for out-of-range values or too many rows."""
        if len(self) > config.max_scatterers:
            raise PhantomError(
                f"{source}: {len(self):,} scatterers, but the scanner reads at most "
                f"{config.max_scatterers:,} (number of scatterers in b-scan)"
            )
        violations = self.range_violations(config, y_limit_um)
        if violations:
            row, name, value, allowed = violations[0]
            raise PhantomError(
                f"{source}: scatterer {row + 1}: {name} = {value!r} outside {allowed}"
                + (f" ({len(violations) - 1} more shown by Phantom.range_violations)"
                   if len(violations) > 1 else "")
            )

    # --------------------------------------------------------------------- I/O
    @classmethod
    def load(cls, path, config: ScannerConfig = DEFAULT_CONFIG, truncate: bool = False,
             y_limit_um: float = READ_Y_LIMIT_UM) -> "Phantom":
        """Read and validate a phantom text file.

        Parameters
        ----------
        path : str or Path
            Rows of ``x y z E`` (whitespace or comma separated), UTF-8, with
            or without a byte-order mark, any line ends.
        config : ScannerConfig
            Gives the lateral and depth ranges and the row limit.
        truncate : bool
            The scanner reads at most ``config.max_scatterers`` rows. With
            ``truncate=True`` the extra rows are dropped the same way (and
            only the first ``max_scatterers·MAX_ROW_BYTES`` bytes of the file
            are read); without it a longer file is an error.
        y_limit_um : float
            Largest allowed |y|.

        Raises
        ------
        PhantomError
            Naming the file, the line and the offending value.

        Notes
        -----
        A file is read whole only up to ``max_scatterers·MAX_ROW_BYTES``
        bytes (76.8 MB for 300,000 rows); a larger one is refused before
        reading unless ``truncate``. Loading a file of that largest size
        peaks at about 3.2 times its size in memory (``scripts/bench_io.py``).
        """
        path = Path(path)
        data, cut = _read_bytes(path, config.max_scatterers, truncate)
        values = _parse_rows(data)
        phantom = None if values is None else cls(*values[:config.max_scatterers if truncate else None].T)
        if phantom is None or not phantom._loadable(config, y_limit_um):
            # The exact reader words the error (or reads what the fast one could not).
            phantom = cls(*_parse_rows_exact(path, data, config, truncate, y_limit_um).T)
        if cut and len(phantom) < config.max_scatterers:
            raise PhantomError(
                f"{path}: the first {len(data):,} bytes hold only {len(phantom):,} rows; octcl "
                f"reads at most {MAX_ROW_BYTES} bytes a row to find the first {config.max_scatterers:,}")
        return phantom

    def _loadable(self, config: ScannerConfig, y_limit_um: float) -> bool:
        """Whether :meth:`load` would accept these rows: 1 … max_scatterers of them, all in range."""
        return 0 < len(self) <= config.max_scatterers and not self.range_violations(config, y_limit_um)

    def save(self, path, significant_digits: int = SIGNIFICANT_DIGITS) -> None:
        """Write ``x y z E`` rows in scientific notation, atomically.

        Every value is written as ``format(v, f'.{significant_digits - 1}e')``
        writes it, one row per line, values separated by one space. The
        default 8 digits round depths near 1536 µm to 1e−4 µm, up to 5e−4 rad
        of carrier phase; 6 digits round them to 0.01 µm, up to 0.05 rad
        (the module docstring gives what that does to the score).
        """
        if not 1 <= significant_digits <= 17:
            raise ValueError(f"significant_digits must be in 1…17, got {significant_digits}")
        text = _format_rows(self.as_array(), significant_digits)
        with atomic_write(path, "wb") as handle:
            handle.write(text)

    # ----------------------------------------------------------------- makers
    @classmethod
    def baseline(cls, kind: str = "uniform", seed: int = 42, count: int = 300_000) -> "Phantom":
        """The SynthOCT baseline generator's phantom, as the scanner read it.

        Reproduces the official recipe with NumPy's legacy Mersenne-Twister
        stream (``np.random.seed(seed)`` then ``np.random.rand``)::

            x = (rand(N) − 0.5)·3072,  y = (rand(N) − 0.5)·20,  z = rand(N)·1536
            uniform: E = 1;  layers: E = 0.01 for z ≤ 400, 2.5 for z > 400

        and rounds every value to 5 significant digits, as the official file
        was written with ``%.4e`` and read back by the scanner.
        """
        if kind not in ("uniform", "layers"):
            raise PhantomError(f"unknown baseline kind {kind!r}; use 'uniform' or 'layers'")
        rng = np.random.RandomState(seed)
        x = (rng.rand(count) - 0.5) * 3072.0
        y = (rng.rand(count) - 0.5) * 20.0
        z = rng.rand(count) * 1536.0
        if kind == "uniform":
            energy = np.full(count, 1.0)
        else:
            energy = np.where(z <= 400.0, 0.01, 2.5)
        return cls(*(round_significant(c, 5) for c in (x, y, z, energy)))


    @classmethod
    def skin(cls, seed: int = 0, config: ScannerConfig = DEFAULT_CONFIG,
             count: int = TARGET_ROWS) -> "Phantom":
        """A skin-like test scene: layers, vessels, a cyst and shadowing reflectors.

        Scatterers fill the tissue below an undulating surface
        z_s(x) = 120 + 30·sin(2πx/1400 + φ1) + 10·sin(2πx/350 + φ2) µm:

        - epidermis, 0–70 µm below the surface: E = 0.6 %;
        - dermal–epidermal junction, 70–85 µm: E = 2.5 % (a bright band);
        - dermis: E = 1.2 %·exp(−(z − z_s)/600 µm), plus a faint 10 % random texture;
        - 3 vessels (ellipses, 60–140 µm across) and 1 cyst (a 220 µm disc):
          E = 0.002 % inside (dark, with their own shadowless bottom edges);
        - 6 small strong reflectors (E = 10 %) at the junction cast partial
          shadows into the dermis below them.

        ``seed`` draws the phases, vessel and reflector positions and the
        scatterer cloud (|y| ≤ 3 µm, inside the contract ranges).
        """
        rng = np.random.default_rng(seed)
        half_width, depth = config.xmax_um / 2, config.depth_range_um
        phase1, phase2 = rng.uniform(0, 2 * np.pi, 2)

        def surface(x):
            return 120 + 30 * np.sin(2 * np.pi * x / 1400 + phase1) + 10 * np.sin(2 * np.pi * x / 350 + phase2)

        reflectors = 6
        bulk = count - reflectors * 40
        x = rng.uniform(-half_width, half_width, bulk)
        top = surface(x)
        z = top + rng.uniform(0, 1, bulk) * (depth - top)
        below = z - top
        energy = np.where(below < 70, 0.6, np.where(below < 85, 2.5, 1.2 * np.exp(-below / 600)))
        energy *= 1 + 0.1 * rng.standard_normal(bulk)
        dark = np.zeros(bulk, dtype=bool)
        for _ in range(3):
            cx, cz = rng.uniform(-0.8, 0.8) * half_width, rng.uniform(350, 1100)
            rx, rz = rng.uniform(30, 70), rng.uniform(30, 70)
            dark |= ((x - cx) / rx) ** 2 + ((z - cz) / rz) ** 2 < 1
        cx, cz = rng.uniform(-0.8, 0.8) * half_width, rng.uniform(500, 1200)
        dark |= (x - cx) ** 2 + (z - cz) ** 2 < 110**2
        energy[dark] = 0.002
        # Strong reflectors: 40 scatterers each within a few µm, E = 10 %.
        centres = rng.uniform(-0.9, 0.9, reflectors) * half_width
        rx = np.repeat(centres, 40) + rng.uniform(-15, 15, reflectors * 40)
        rz = surface(rx) + 78 + rng.uniform(-2, 2, reflectors * 40)
        x = np.concatenate([x, rx])
        z = np.concatenate([z, rz])
        energy = np.concatenate([energy, np.full(reflectors * 40, 10.0)])
        y = rng.uniform(-CONTRACT_Y_LIMIT_UM, CONTRACT_Y_LIMIT_UM, x.size)
        return cls(np.clip(x, -half_width, half_width), y, np.clip(z, 0, depth), np.clip(energy, 0, 100))


# ------------------------------------------------------------------ reading
_BOM = codecs.BOM_UTF8
#: The bytes of a file the fast reader handles: numbers and their separators.
_NUMBER_BYTES = b"0123456789+-.eE"
_SEPARATOR_BYTES = b" \t,\r\n"
_COMMENT_LINE = re.compile(rb"^[ \t]*#[^\r\n]*", re.MULTILINE)
_SCIENTIFIC = re.compile(rb"[+-]?\d(?:\.(\d+))?[eE][+-]\d\d")
_TO_WHITESPACE = bytes.maketrans(b",\r", b" \n")
#: The fast reader works through a file in chunks of lines of about this
#: many bytes, which keep its temporary arrays in a core's cache (512 KiB:
#: 0.13 s for 300,000 rows against 0.19 s for the whole file at once).
_CHUNK_BYTES = 1 << 19
#: 10^k for k = 0 … 308, each the float64 nearest to it (exact for k ≤ 22).
_POWERS_OF_TEN = np.array([float(f"1e{k}") for k in range(309)])
_EXACT_POWER = 22
#: Sign, hundreds (a 0 byte below 100), tens and units of the exponents
#: −400 … 400 as text bytes.
_EXPONENT_OFFSET = 400
_EXPONENT_TEXT = np.array([[ord("-" if n < 0 else "+"), ord("0") + abs(n) // 100 if abs(n) >= 100 else 0,
                            ord("0") + abs(n) // 10 % 10, ord("0") + abs(n) % 10]
                           for n in range(-_EXPONENT_OFFSET, _EXPONENT_OFFSET + 1)], np.uint8).T.copy()


def _read_bytes(path: Path, max_rows: int, truncate: bool) -> tuple[bytes, bool]:
    """The bytes of a phantom file, at most ``max_rows·MAX_ROW_BYTES`` of them.

    Returns ``(data, cut)``; ``cut`` says that ``truncate`` kept only the
    lines that start within that limit.
    """
    limit = max(max_rows, 1) * MAX_ROW_BYTES
    too_large = (f"more than {max_rows:,} rows take at {MAX_ROW_BYTES} bytes a row ({limit:,} bytes); "
                 f"the scanner reads only the first {max_rows:,} rows (number of scatterers in b-scan): "
                 f"use --truncate (Phantom.load(..., truncate=True)) to read only those")
    data = read_at_most(path, limit, PhantomError, "phantom file", None if truncate else too_large)
    if len(data) <= limit:
        return data, False
    if not truncate:
        raise PhantomError(f"{path}: {too_large}")
    end = max(data.rfind(b"\n", 0, limit), data.rfind(b"\r", 0, limit)) + 1
    if not end:
        raise PhantomError(f"{path}: no line ends within the first {limit:,} bytes; octcl reads "
                           f"at most {MAX_ROW_BYTES} bytes a row to find the first {max_rows:,}")
    return data[:end], True


def _parse_rows(data: bytes) -> np.ndarray | None:
    """The (N, 4) values of a phantom file's rows, or None where :func:`_parse_rows_exact` must decide.

    This is the fast reader; it returns values only for files whose every
    byte it understands (numbers, spaces, tabs, commas, line ends, ``#``
    comment lines, a leading byte-order mark) and whose every line holds
    four values or none, and then exactly the values the exact reader would
    return. Values written as ``'%.{k}e'`` writes them (k ≤ 14: octcl's own
    files, the official ones) are read by :func:`_parse_scientific_rows`, a
    chunk of lines at a time, any other decimal text by NumPy's C reader
    ``np.loadtxt``.
    """
    if data.startswith(_BOM):
        data = data[len(_BOM):]
    if b"#" in data:
        try:
            data.decode("utf-8")  # comments may hold any text, but the file must be UTF-8
        except UnicodeDecodeError:
            return None
        data = _COMMENT_LINE.sub(b"", data)
    if data.translate(None, _NUMBER_BYTES + _SEPARATOR_BYTES):
        return None  # other bytes, or a '#' that does not start a line
    parts, start = [np.empty((0, 4))], 0
    while start < len(data):
        end = data.find(b"\n", start + _CHUNK_BYTES) + 1 or len(data)
        parts.append(_parse_scientific_rows(data[start:end]))
        if parts[-1] is None:
            break
        start = end
    if parts[-1] is not None:
        values = np.concatenate(parts)
    else:
        try:
            values = np.loadtxt(io.BytesIO(data.translate(_TO_WHITESPACE)), dtype=np.float64,
                                comments=None, ndmin=2)
        except ValueError:
            return None
    return values if values.size and values.shape[1] == 4 else None


def _parse_scientific_rows(data: bytes) -> np.ndarray | None:
    """The (N, 4) values of lines of text whose values all read ``[±]D.D…De±DD``, or None.

    Tokens (runs of bytes other than separators) are found with NumPy on the
    bytes, and must lie four to a line; ``data`` holds only the bytes
    :func:`_parse_rows` lets through. Every value must have the same number
    k ≤ 14 of decimals. The significand m (k + 1 digits) is exact in
    float64, and so is 10^|p| for |p| ≤ 22, where v = m·10^p; one
    multiplication or division of the two is then correctly rounded, the
    same float64 as ``float()`` reads (Clinger, "How to read floating point
    numbers accurately", PLDI 1990). Beyond it the product with 10^p as a
    double-double is rounded where that is certain
    (:func:`_times_power_of_ten_rounded`); the rest go through ``float()``.
    """
    padded = b" " + data  # a separator before every token
    text = np.frombuffer(padded, np.uint8)
    separator = (text <= 32) | (text == ord(","))  # the alphabet leaves ' ', '\t', '\r', '\n', ','
    edges = np.flatnonzero(separator[1:] != separator[:-1]) + 1
    if not separator[-1]:
        edges = np.append(edges, text.size)
    starts, ends = edges[0::2], edges[1::2]
    if starts.size % 4:
        return None
    if not starts.size:
        return np.empty((0, 4))
    # Four values a line: the first and fourth value of each row lie on the
    # same line ('\r', '\n' or both end one), and each row on a later line.
    line_ends = np.flatnonzero((text == ord("\n")) | (text == ord("\r")))
    first, last = np.searchsorted(line_ends, starts[0::4]), np.searchsorted(line_ends, starts[3::4])
    if not (np.array_equal(first, last) and np.all(first[1:] > last[:-1])):
        return None
    first_value = _SCIENTIFIC.fullmatch(padded[starts[0]:ends[0]])
    if first_value is None:
        return None
    decimals = len(first_value.group(1) or b"")
    unsigned = 5 + (decimals + 1 if decimals else 0)  # D[.D…D]e±DD
    length = ends - starts
    if decimals > 14 or length.max() > unsigned + 1 or length.min() < unsigned:
        return None
    # Each token's last unsigned + 1 bytes, [sign or separator] D [. D…D] e ± D D,
    # gathered as rows, then transposed so that each place is one contiguous
    # row of bytes (the checks and sums below then run 40 % faster).
    windows = np.ndarray((len(padded) - unsigned,), f"S{unsigned + 1}", padded, strides=(1,))
    token = windows[ends - unsigned - 1].view(np.uint8).reshape(-1, unsigned + 1).T.copy()
    digit = token - np.uint8(ord("0"))  # bytes other than digits wrap past 9
    e = unsigned - 3
    if not ((digit[1] <= 9).all() and (digit[3:e] <= 9).all() and (digit[e + 2:] <= 9).all()
            and (decimals == 0 or (token[2] == ord(".")).all())
            and ((token[e] | 0x20) == ord("e")).all()
            and ((token[e + 1] == ord("+")) | (token[e + 1] == ord("-"))).all()
            and ((length == unsigned) | (token[0] == ord("+")) | (token[0] == ord("-"))).all()):
        return None
    significand = digit[1].astype(np.int64)
    for place in range(3, e):
        significand *= 10
        significand += digit[place]
    exponent = digit[e + 2].astype(np.int64) * 10 + digit[e + 3]
    power = np.where(token[e + 1] == ord("-"), -exponent, exponent) - decimals
    values, certain = _times_power_of_ten_rounded(significand.astype(np.float64), power)
    values[token[0] == ord("-")] *= -1
    for index in np.flatnonzero(~certain):  # float() reads the sign too
        values[index] = float(padded[starts[index]:ends[index]])
    return values.reshape(-1, 4)


def _parse_rows_exact(path: Path, data: bytes, config: ScannerConfig, truncate: bool,
                      y_limit_um: float) -> np.ndarray:
    """The rows of a phantom file read line by line with ``float()``, and every check of :meth:`Phantom.load`.

    The reference for :func:`_parse_rows` and the one that words the errors
    (file, line, value). It is slow (a regular expression and Python floats
    for each line, about 1.3 s for 300,000 rows), so :meth:`Phantom.load`
    uses it only for files the fast reader leaves to it or finds fault with.
    """
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise PhantomError(f"{path}: not a text file ({exc.reason} at byte {exc.start})") from None
    line_numbers, rows = [], []
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped.startswith("#"):
            continue
        tokens = _TOKEN.findall(stripped)
        if not tokens:
            continue
        if len(tokens) != 4:
            raise PhantomError(
                f"{path}:{number}: expected 4 columns (x y z E), found {len(tokens)}: {stripped[:80]!r}"
            )
        line_numbers.append(number)
        rows.append(tokens)
    if not rows:
        raise PhantomError(f"{path}: empty phantom (no scatterer rows)")
    if len(rows) > config.max_scatterers:
        if not truncate:
            raise PhantomError(
                f"{path}: {len(rows):,} rows, but the scanner reads only the first "
                f"{config.max_scatterers:,} (number of scatterers in b-scan); "
                f"use --truncate (Phantom.load(..., truncate=True)) to keep those"
            )
        rows, line_numbers = rows[:config.max_scatterers], line_numbers[:config.max_scatterers]
    try:
        values = np.array(rows, dtype=np.float64)  # float() of each token
    except ValueError:
        for number, tokens in zip(line_numbers, rows):  # find the first token that is not a number
            for column, token in zip("xyzE", tokens):
                try:
                    float(token)
                except ValueError:
                    raise PhantomError(f"{path}:{number}: {column} = {token!r} is not a number") from None
    finite = np.isfinite(values)
    if not finite.all():
        row, column = np.argwhere(~finite)[0]
        raise PhantomError(
            f"{path}:{line_numbers[row]}: {'xyzE'[column]} = {rows[row][column]!r} is not finite")
    violations = Phantom(*values.T).range_violations(config, y_limit_um)
    if violations:
        row, name, value, allowed = violations[0]
        raise PhantomError(
            f"{path}:{line_numbers[row]}: {name} = {rows[row]['xyzE'.index(name)]} outside {allowed}")
    return values


# ------------------------------------------------------------------ writing
def _times_power_of_ten(values: np.ndarray, power: np.ndarray) -> np.ndarray:
    """values·10^power, by one multiplication (power ≥ 0) or division (power < 0) by 10^|power|.

    Each is correctly rounded where 10^|power| is exact (|power| ≤ 22), else
    within about one unit in the last place.
    """
    factor = _POWERS_OF_TEN[np.abs(power)]
    scaled = values / factor
    return np.multiply(values, factor, out=scaled, where=power >= 0)


@functools.cache
def _powers_of_ten_double_double() -> tuple[np.ndarray, np.ndarray]:
    """10^k for k = −308 … 308 (index k + 308) as hi + lo, hi the float64 nearest 10^k and lo the float64 nearest
    10^k − hi: within 2^−106 of 10^k relative (lo of the subnormal powers is 0, and they are not used)."""
    hi, lo = np.empty(617), np.empty(617)
    for k in range(-308, 309):
        exact = fractions.Fraction(10) ** k
        hi[k + 308] = float(exact)
        lo[k + 308] = float(exact - fractions.Fraction(hi[k + 308]))
    return hi, lo


def _two_product(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """p, e with p = fl(a·b) and p + e = a·b exactly (Dekker, "A floating-point technique for extending the
    available precision", Numer. Math. 18, 1971: each factor split into halves of 26 and 27 bits)."""
    product = a * b
    a_hi = a * 134217729.0  # 2^27 + 1
    a_hi = a_hi - (a_hi - a)
    b_hi = b * 134217729.0
    b_hi = b_hi - (b_hi - b)
    a_lo, b_lo = a - a_hi, b - b_hi
    return product, ((a_hi * b_hi - product) + a_hi * b_lo + a_lo * b_hi) + a_lo * b_lo


def _times_power_of_ten_rounded(values: np.ndarray, power: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """values·10^power correctly rounded to float64, and a mask of the results that are certain.

    ``values`` are integers below 2^53. Where |power| ≤ 22 one operation with the exact 10^|power|
    (:func:`_times_power_of_ten`) is correctly rounded. Beyond, values·(hi + lo) with 10^power as a
    double-double (:func:`_powers_of_ten_double_double`): hi's product exact as p + e (:func:`_two_product`),
    e + values·lo within 2^−104 of the rest, so s + t = p + (e + values·lo) (two-sum, s its rounding) is within
    about 2^−103·|s| of the true product. s is the true product's rounding unless a rounding boundary (a
    midpoint between neighbouring floats, |t| = ulp(s)/2) lies between them: certain where |t| stays 2^−96·|s|
    away from ulp(s)/2, s is not a power of two (whose lower neighbour is nearer) and the result is a normal
    float within 1e±290; the uncertain ones are for Python's text to round (none of 262,144 random values of
    1e−36 to 1e−10 at 8 digits). A phantom decoded in the linear regime has energies of 1e−36 % to 1e−11 %, most
    beyond 1e−15 (|p| > 22 at 8 digits), which stage 3 rounds as the file holds them and a reader reads back: on
    two first-generation EPYC cores :func:`round_significant` of 262,144 values spread over 1e−36 to 1e−10 took
    0.45 s through Python and 0.057 s this way; of orange.png's decoded phantom (1.5e−26 to 3.6e−11 %) 0.16 and
    0.02 s, and its ``Phantom.load`` 0.25 and 0.15 s (docs/benchmarks.md, "Phantom values read without
    Python"). ``tests/test_phantom.py`` compares the products with exact fractions.
    """
    rounded = _times_power_of_ten(values, power)
    large = np.abs(power) > _EXACT_POWER
    certain = ~large
    if large.any():
        hi, lo = _powers_of_ten_double_double()
        index = np.clip(power[large], -308, 308) + 308
        magnitude = values[large]
        with np.errstate(over="ignore", invalid="ignore"):  # past 1e290: uncertain, for Python
            product, error = _two_product(magnitude, hi[index])
            error = error + magnitude * lo[index]
            total = product + error
            tail = (product - total) + error  # |product| ≥ |error|: fast two-sum
            half_ulp = np.spacing(np.abs(total)) / 2
        _, fraction = np.frexp(total)
        certain[large] = ((np.abs(np.abs(tail) - half_ulp) > np.abs(total) * 2.0**-96) & (np.abs(fraction) != 0.5)
                          & (np.abs(total) > 1e-290) & (np.abs(total) < 1e290) & (np.abs(power[large]) <= 308))
        rounded[large] = total
    return rounded, certain


def _decimal_digits(values: np.ndarray, digits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Significand and exponent of each value as ``'%.{digits-1}e'`` prints it.

    Returns ``(significand, exponent, certain)``: float64 integers with
    |v| ≈ significand·10^(exponent − digits + 1), 10^(digits−1) ≤ significand
    < 10^digits (0 for a zero), and a mask of the values for which they are
    certain. The scaled value s = |v|·10^(digits − 1 − exponent) is computed
    in float64 within 2^−52 relative; its rounding to an integer is certain
    unless s lies within s·2^−50 of a tie (a half-integer). Left uncertain:
    those near-ties (about 2·s·2^−50 of all values: 2e−9 at 6 digits, 2e−6
    at 9), values beyond 1e±280 and non-finite ones, and every value for
    more than 15 digits (s must stay exact below 2^53). Callers format the
    uncertain ones with Python.
    """
    magnitude = np.abs(values)
    usable = (magnitude > 1e-280) & (magnitude < 1e280) & (digits <= 15)  # NaN is not usable
    if not usable.all():
        magnitude[~usable] = 1.0
    exponent = np.floor(np.log10(magnitude)).astype(np.int64)
    scaled = _times_power_of_ten(magnitude, digits - 1 - exponent)
    # log10 may round across a power of ten: move those exponents back.
    moved = np.flatnonzero((scaled >= 10.0**digits) | (scaled < 10.0 ** (digits - 1)))
    if moved.size:
        exponent[moved] += np.where(scaled[moved] >= 10.0**digits, 1, -1)
        scaled[moved] = _times_power_of_ten(magnitude[moved], digits - 1 - exponent[moved])
    significand = np.rint(scaled)
    distance = np.abs(np.subtract(scaled, significand))
    scaled *= -(2.0**-50)
    scaled += 0.5
    certain = distance < scaled  # |s − rint(s)| < 0.5 − s·2^−50
    certain &= usable
    carried = np.flatnonzero(significand >= 10.0**digits)  # 9.9999996 → 1.00000e+01
    significand[carried] /= 10
    exponent[carried] += 1
    zero = values == 0
    significand[zero], exponent[zero], certain[zero] = 0, 0, True
    return significand, exponent, certain


def _format_rows(rows: np.ndarray, digits: int) -> bytes:
    """The text of (N, 4) rows, each value as ``format(v, f'.{digits-1}e')`` writes it.

    The characters of value i are column i of a byte array, one row per
    place (sign, digits, '.', 'e', exponent, separator), filled from
    :func:`_decimal_digits` with whole-row NumPy operations (two digits at a
    time from a table); a 0 byte marks an unused place (a positive sign, the
    hundreds of a two-digit exponent) and is dropped when the columns are
    joined. The values it leaves uncertain are formatted by Python. NumPy
    has no vectorised '%e' (``np.savetxt`` formats row by row in Python),
    hence this.
    """
    rows = np.asarray(rows, dtype=np.float64)
    values = rows.reshape(-1)
    significand, exponent, certain = _decimal_digits(values, digits)
    fraction = digits - 1
    e = 2 + (fraction + 1 if fraction else 0)  # [sign] D [. D…D] e ± [D]DD separator
    places = np.empty((e + 6, values.size), np.uint8)
    places[0] = np.signbit(values).view(np.uint8) * np.uint8(ord("-"))
    if fraction:
        places[2] = ord(".")
    # Digits from the last, two at a time: significand = 100·q + r, r = 10·t + u.
    digit_places = [1] + list(range(3, e))
    remaining = significand.astype(np.uint32 if digits <= 9 else np.uint64)
    for place in range(len(digit_places) - 1, -1, -2):
        quotient = remaining // 100
        pair = (remaining - quotient * 100).astype(np.uint8)
        remaining = quotient
        tens = pair // 10
        places[digit_places[place]] = pair - tens * 10 + ord("0")
        if place:
            places[digit_places[place - 1]] = tens + ord("0")
    places[e] = ord("e")
    exponent_index = exponent + _EXPONENT_OFFSET
    for place, table in enumerate(_EXPONENT_TEXT, start=e + 1):
        places[place] = table[exponent_index]
    places[e + 5] = ord(" ")
    places[e + 5, rows.shape[-1] - 1::rows.shape[-1]] = ord("\n")
    spec = f".{fraction}e"
    for index in np.flatnonzero(~certain):
        token = format(values[index], spec).encode()
        places[:-1, index] = 0
        places[:len(token), index] = np.frombuffer(token, np.uint8)
    text = np.ascontiguousarray(places.T)
    return text[text != 0].tobytes()


def round_significant(values: np.ndarray, digits: int) -> np.ndarray:
    """Round to ``digits`` significant digits exactly as ``'%.{digits-1}e'`` prints and ``float()`` reads.

    From :func:`_decimal_digits`: v = ±m·10^p is read back by one correctly
    rounded operation where |p| ≤ 22 (see :func:`_parse_scientific_rows`);
    the uncertain and out-of-range values go through Python's text. Any
    shape; the result has the shape of ``values``.
    """
    shape = np.shape(values)
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    significand, exponent, certain = _decimal_digits(values, digits)
    power = exponent - (digits - 1)
    rounded, exact = _times_power_of_ten_rounded(significand, power)
    rounded = np.copysign(rounded, values)
    fmt = f"%.{digits - 1}e"
    for index in np.flatnonzero(~(certain & exact)):
        rounded[index] = float(fmt % values[index])
    return rounded.reshape(shape)


__all__ = ["Phantom", "PhantomError", "TARGET_ROWS", "CONTRACT_Y_LIMIT_UM", "SIGNIFICANT_DIGITS"]
