"""Digital phantoms: clouds of point scatterers, their text format and checks.

A phantom is a set of point scatterers j with lateral position x_j, elevation
y_j and depth z_j (all in µm) and energy E_j, the percentage of the incident
energy the scatterer reflects (amplitude a_j = sqrt(E_j / 100)).

The file format is plain text, one scatterer per row: ``x y z E``, separated
by whitespace or commas; blank lines and lines starting with ``#`` are
ignored. octcl writes 6 significant digits in scientific notation.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._io import atomic_write
from .config import DEFAULT_CONFIG, ScannerConfig


class PhantomError(ValueError):
    """A phantom that cannot be used; the message names file, line and value."""


#: Elevation limit of the task contract for submitted phantoms (µm).
CONTRACT_Y_LIMIT_UM = 3.0
#: Elevation limit of phantoms octcl reads (the baseline generator draws |y| ≤ 10 µm).
READ_Y_LIMIT_UM = 10.0
#: Rows octcl aims for when it writes a phantom for submission.
TARGET_ROWS = 295_000

_SEPARATORS = re.compile(r"[,\s]+")


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
            Rows of ``x y z E`` (whitespace or comma separated).
        config : ScannerConfig
            Gives the lateral and depth ranges and the row limit.
        truncate : bool
            The scanner reads at most ``config.max_scatterers`` rows. With
            ``truncate=True`` the extra rows are dropped the same way; without
            it a longer file is an error.
        y_limit_um : float
            Largest allowed |y|.

        Raises
        ------
        PhantomError
            Naming the file, the line and the offending value.
        """
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise PhantomError(f"{path}: no such file") from None
        except UnicodeDecodeError as exc:
            raise PhantomError(f"{path}: not a text file ({exc.reason} at byte {exc.start})") from None
        except IsADirectoryError:
            raise PhantomError(f"{path}: is a directory, not a phantom file") from None

        line_numbers, rows = [], []
        for number, line in enumerate(text.splitlines(), start=1):
            stripped = line.strip()
            if not stripped or stripped.startswith("#"):
                continue
            tokens = _SEPARATORS.split(stripped.strip(","))
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
            values = np.array(rows, dtype=np.float64)
        except ValueError:
            values = None
        if values is None:  # find the first token that is not a number
            for number, tokens in zip(line_numbers, rows):
                for column, token in zip("xyzE", tokens):
                    try:
                        float(token)
                    except ValueError:
                        raise PhantomError(
                            f"{path}:{number}: {column} = {token!r} is not a number") from None
        finite = np.isfinite(values)
        if not finite.all():
            row, column = np.argwhere(~finite)[0]
            raise PhantomError(
                f"{path}:{line_numbers[row]}: {'xyzE'[column]} = {rows[row][column]!r} is not finite")
        phantom = cls(*values.T)
        violations = phantom.range_violations(config, y_limit_um)
        if violations:
            row, name, value, allowed = violations[0]
            raise PhantomError(
                f"{path}:{line_numbers[row]}: {name} = {rows[row]['xyzE'.index(name)]} outside {allowed}")
        return phantom

    def save(self, path, significant_digits: int = 6) -> None:
        """Write ``x y z E`` rows in scientific notation, atomically.

        Six significant digits (the default) round depths near 1536 µm to
        0.01 µm, i.e. up to 0.05 rad of carrier phase (2·k0 ≈ 9.67 rad/µm);
        inverted phantoms, whose speckle depends on that phase, are written
        with more.
        """
        if not 1 <= significant_digits <= 17:
            raise ValueError(f"significant_digits must be in 1…17, got {significant_digits}")
        spec = f".{significant_digits - 1}e"
        text = "\n".join(" ".join(format(v, spec) for v in row) for row in self.as_array().tolist())
        with atomic_write(path, "w") as handle:
            handle.write(text + "\n" if text else "")

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
        return cls(*(_round_significant(c, 5) for c in (x, y, z, energy)))


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


def _round_significant(values: np.ndarray, digits: int) -> np.ndarray:
    """Round to ``digits`` significant digits exactly as ``'%.{digits-1}e'`` prints."""
    fmt = f"%.{digits - 1}e"
    return np.array([float(fmt % v) for v in values.tolist()])


__all__ = ["Phantom", "PhantomError", "TARGET_ROWS", "CONTRACT_Y_LIMIT_UM"]
