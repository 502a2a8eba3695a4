"""Virtual Scanner configuration (the ``Configuration.ini`` of SynthOCT).

The scanner is fixed by the SynthOCT 2026 task; the defaults below are its
values. A ``Configuration.ini`` file with a ``[Parameters]`` section (keys
case-insensitive) may override them, as the official scanner allows.
"""

from __future__ import annotations

import configparser
import math
from dataclasses import dataclass, fields
from pathlib import Path

from ._io import MAX_IMAGE_PIXELS, reading_errors


class ConfigError(ValueError):
    """A Configuration.ini that cannot be used; the message names file, key and value."""


@dataclass(frozen=True)
class ScannerConfig:
    """Geometry and optics of the Virtual Scanner.

    Attributes
    ----------
    depth_pixels : int
        Nz, samples per A-scan (rows of the B-scan).
    pixel_size_um : float
        Δz, the depth pixel size in µm.
    wavelength_um : float
        λ, centre wavelength in µm.
    a_scans : int
        Nx, A-scans per B-scan (columns).
    xmax_um : float
        Lateral scan length in µm; A-scan i sits at x_i = (i − Nx/2)·Δx.
    beam_radius_um : float
        w0, the Gaussian beam radius in µm.
    max_scatterers : int
        The scanner reads at most this many phantom rows.
    """

    depth_pixels: int = 256
    pixel_size_um: float = 6.0
    wavelength_um: float = 1.3
    a_scans: int = 512
    xmax_um: float = 3072.0
    beam_radius_um: float = 10.0
    max_scatterers: int = 300_000

    # INI key (lower case) of each field.
    _INI_KEYS = {
        "a-scan pixel numbers": "depth_pixels",
        "vertical pixel size mcm": "pixel_size_um",
        "central wavelength mcm": "wavelength_um",
        "number of a-scans in b-scan": "a_scans",
        "xmax mcm": "xmax_um",
        "beam radius mcm": "beam_radius_um",
        "number of scatterers in b-scan": "max_scatterers",
    }

    def __post_init__(self):
        for field in fields(self):
            value = getattr(self, field.name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"{field.name} must be a positive finite number, got {value!r}")
        if self.depth_pixels % 2:
            raise ConfigError(f"depth_pixels must be even, got {self.depth_pixels}")
        if self.depth_pixels * self.a_scans > MAX_IMAGE_PIXELS:
            raise ConfigError(
                f"depth_pixels x a_scans = {self.depth_pixels} x {self.a_scans}: a B-scan of more than "
                f"{MAX_IMAGE_PIXELS:,} pixels, which octcl could not read back")

    @property
    def lateral_pitch_um(self) -> float:
        """Δx = Xmax / Nx, the distance between neighbouring A-scans in µm."""
        return self.xmax_um / self.a_scans

    @property
    def depth_range_um(self) -> float:
        """Nz·Δz, the depth covered by one A-scan in µm (1536 by default)."""
        return self.depth_pixels * self.pixel_size_um

    @property
    def k0_rad_per_um(self) -> float:
        """k0 = 2π/λ, the centre wavenumber in rad/µm (a scatterer at depth z has the carrier e^{−2i·k0·z})."""
        return 2 * math.pi / self.wavelength_um

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns) of the B-scan: (Nz, Nx)."""
        return (self.depth_pixels, self.a_scans)

    @classmethod
    def from_ini(cls, path) -> "ScannerConfig":
        """Read the ``[Parameters]`` section of a Configuration.ini.

        Keys not listed in physics-relevant settings (``scan filename``,
        ``scatterers coordinates file``) are ignored. A key that must be fixed
        for a single B-scan (``number of b-scans`` = 1, ``ymax mcm`` = 0) is
        checked, since octcl renders one B-scan.
        """
        path = Path(path)
        parser = configparser.ConfigParser(interpolation=None)
        try:
            with reading_errors(path, ConfigError, "Configuration.ini file"), open(path, encoding="utf-8") as handle:
                parser.read_file(handle)
        except UnicodeDecodeError as exc:
            raise ConfigError(f"{path}: not a text file ({exc.reason} at byte {exc.start})") from None
        except configparser.Error as exc:
            raise ConfigError(f"{path}: not a valid INI file ({exc.message.splitlines()[0]})") from None
        if not parser.has_section("Parameters"):
            raise ConfigError(f"{path}: no [Parameters] section")
        section = parser["Parameters"]
        values = {}
        for key, name in cls._INI_KEYS.items():
            if key not in section:
                continue
            text = section[key]
            kind = int if name in ("depth_pixels", "a_scans", "max_scatterers") else float
            try:
                number = float(text)
            except ValueError:
                raise ConfigError(f"{path}: [Parameters] {key} = {text!r} is not a number") from None
            if kind is int:
                if not number.is_integer():
                    raise ConfigError(
                        f"{path}: [Parameters] {key} = {text!r} is not a whole number") from None
                number = int(number)
            values[name] = number
        for key, required in (("number of b-scans", 1.0), ("ymax mcm", 0.0)):
            if key in section:
                try:
                    ok = float(section[key]) == required
                except ValueError:
                    ok = False
                if not ok:
                    raise ConfigError(
                        f"{path}: [Parameters] {key} = {section[key]!r}; octcl renders a single "
                        f"B-scan and needs {required:g}"
                    )
        try:
            return cls(**values)
        except ConfigError as exc:
            # Name the INI key (and its text) behind the field the check refused.
            for key, name in cls._INI_KEYS.items():
                if str(exc).startswith(name + " ") and key in section:
                    raise ConfigError(
                        f"{path}: [Parameters] {key} = {section[key]!r}: {exc}") from None
            raise ConfigError(f"{path}: {exc}") from None


DEFAULT_CONFIG = ScannerConfig()
