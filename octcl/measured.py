"""Durations measured on this machine, kept in octcl's cache for the next run's clock.

A time budget is decided before the work it covers: whether torch's import
fits, how much of the budget stage 1 may take and what it must leave for
the decode, the first write and the run's close. What those cost depends on
the machine more than on the scan: the default's decode of a 256×512 field
took 0.58–0.65 s on one 2-core EPYC VM and 1.05–1.10 s on another of the
first Zen generation, the first write 0.2–0.3 s against 0.30–0.33 s
(``octcl invert`` reports; docs/benchmarks.md, "Budgets on a slower
machine"), and torch's import 1.0–1.2 s for a CPU build against 2.9–5.3 s
for a CUDA one (:mod:`octcl.torch_import`).

:class:`MeasuredTimes` keeps the last ``kept`` figures of each named span
in one JSON file of the cache folder (:func:`octcl.device.runtime.cache_dir`),
and answers their median or the longest: a run measures its spans where it pays them, and
the next run's clock starts from what this machine did, not from another
machine's constant. A file that cannot be read counts as empty, and one that
cannot be written is left as it is: the clock then falls back on its
defaults.
"""

from __future__ import annotations

import json
import statistics


class MeasuredTimes:
    """Named spans (s) measured on this machine, the last ``kept`` of each, in the cache file ``filename``.

    Parameters
    ----------
    filename : str
        The JSON file in octcl's cache folder: ``{name: [seconds, ...]}``.
    kept : int
        Figures kept per name, the newest last.
    """

    def __init__(self, filename: str, kept: int = 5):
        self.filename, self.kept = filename, kept

    @property
    def path(self):
        from .device.runtime import cache_dir

        return cache_dir() / self.filename

    def _read(self) -> dict:
        try:
            measured = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return {}
        return measured if isinstance(measured, dict) else {}

    def times(self, name: str) -> list[float]:
        """The figures kept for ``name``, oldest first (the non-negative numbers of its entry)."""
        values = self._read().get(name)
        if not isinstance(values, list):
            return []
        return [float(value) for value in values if isinstance(value, (int, float)) and value >= 0]

    def median(self, name: str) -> float | None:
        """The median of the figures kept for ``name``, or None where there are none."""
        values = self.times(name)
        return statistics.median(values) if values else None

    def longest(self, name: str, default: float) -> float:
        """The longest of the figures kept for ``name``, or ``default`` where there are none."""
        values = self.times(name)
        return max(values) if values else default

    def record(self, name: str, seconds: float) -> None:
        """Keep ``seconds`` for ``name`` (the last :attr:`kept` stay); a cache that cannot be written is left."""
        from ._io import atomic_write

        measured = self._read()
        measured[name] = [*self.times(name), round(float(seconds), 3)][-self.kept:]
        try:
            with atomic_write(self.path, "w") as handle:
                json.dump(measured, handle, indent=1)
        except OSError:
            pass


__all__ = ["MeasuredTimes"]
