"""A one-line progress bar on standard error, for work that takes seconds or more.

It draws only on a terminal; in logs and pipes it stays silent so that
``--json`` output and CI logs are clean.
"""

from __future__ import annotations

import sys
import time


class ProgressBar:
    """``[#####-----]  45%  label  text  elapsed/eta`` redrawn in place.

    Parameters
    ----------
    label : str
        What is being done.
    total : int
        Number of steps (0 for unknown).
    stream : file, optional
        Where to draw; standard error by default.
    """

    WIDTH = 24

    def __init__(self, label: str, total: int = 0, stream=None):
        self.label, self.total = label, total
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.start = time.monotonic()
        self._last_draw = 0.0

    def update(self, done: int, text: str = "", total: int | None = None, force: bool = False) -> None:
        """Redraw with ``done`` of ``total`` steps and a short status ``text``."""
        if total is not None:
            self.total = total
        now = time.monotonic()
        if not self.enabled or (not force and now - self._last_draw < 0.1):
            return
        self._last_draw = now
        elapsed = now - self.start
        if self.total:
            fraction = min(max(done / self.total, 0.0), 1.0)
            filled = int(round(fraction * self.WIDTH))
            bar = f"[{'#' * filled}{'-' * (self.WIDTH - filled)}] {100 * fraction:3.0f}%"
            eta = f" eta {elapsed / fraction - elapsed:4.0f}s" if 0 < fraction < 1 else ""
        else:
            bar, eta = f"[{done}]", ""
        line = f"\r{bar}  {self.label}  {text}  {elapsed:4.0f}s{eta}"
        self.stream.write(line[:160].ljust(100))
        self.stream.flush()

    def close(self) -> None:
        """End the line."""
        if self.enabled:
            self.stream.write("\n")
            self.stream.flush()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
