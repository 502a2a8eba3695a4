"""Progress on standard error: a redrawn bar on a terminal, occasional plain lines elsewhere.

The fraction done and the time left are the caller's estimates, not a rate
measured here: an inversion ends at whichever comes first of its time
budget and the end of its iteration schedule (:class:`octcl.host.pipeline.invert.
InvertProgress`), which no steps-per-second extrapolation knows. On a
terminal the bar is drawn by tqdm (terminal width, redraw, clean-up),
with tqdm's own rate and remaining-time fields left out for that reason.

When the stream is not a terminal (a CI log, a pipe, a Dask worker's
log) nothing is redrawn: one plain line is written when the stage text
changes (``force=True``), at most every :data:`PLAIN_INTERVAL_S`
seconds otherwise, and one at the end, so a 10-minute inversion leaves a
few dozen lines and no carriage returns. tqdm alone would either keep
drawing with carriage returns into the file or stay silent (``disable=None``);
tqdm-loggable does the periodic lines but not the stage changes.
"""

from __future__ import annotations

import math
import sys
import threading
import time

#: Least seconds between two plain progress lines on a non-terminal stream.
PLAIN_INTERVAL_S = 30.0
#: Least seconds between two redraws of the terminal bar.
REDRAW_INTERVAL_S = 0.1
#: Seconds between redraws of the terminal bar while no update comes.
TICK_S = 1.0


def format_seconds(seconds: float) -> str:
    """``42s``, ``7m05s`` or ``1h02m``."""
    if not math.isfinite(seconds):
        return "?"
    seconds = max(0, int(round(seconds)))
    if seconds < 60:
        return f"{seconds}s"
    if seconds < 3600:
        return f"{seconds // 60}m{seconds % 60:02d}s"
    return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m"


class ProgressDisplay:
    """Progress of one piece of work: ``label  45%|████      | text  elapsed 9s  eta 12s``.

    Parameters
    ----------
    label : str
        What is being done.
    stream : file, optional
        Where to write; standard error by default.
    enabled : bool
        False draws nothing (``--quiet``).

    Attributes
    ----------
    terminal : bool
        The stream is a terminal: a redrawn bar; else plain lines.

    Notes
    -----
    On a terminal a background thread redraws the bar every
    :data:`TICK_S` seconds between updates, with the elapsed time running
    and the time left counting down from the last estimate (and, where a
    time left is given, the fraction taken as the share of time e/(e + l)
    moving with it), so a step that takes seconds (compiling kernels, an
    exact evaluation) does not freeze the clock on screen.
    """

    def __init__(self, label: str, stream=None, enabled: bool = True):
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.terminal = enabled and hasattr(self.stream, "isatty") and self.stream.isatty()
        self.start = time.monotonic()
        self._last_write = -math.inf
        self._state, self._written = None, True  # (fraction, text, seconds_left, given at)
        self._bar = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._ticker = None

    def update(self, fraction: float | None, text: str = "", seconds_left: float | None = None,
               force: bool = False) -> None:
        """Show ``fraction`` done (None: unknown), a short status ``text`` and the estimated time left.

        ``force`` writes now (a stage change); otherwise the terminal bar is
        redrawn at most every :data:`REDRAW_INTERVAL_S` seconds and plain
        lines at most every :data:`PLAIN_INTERVAL_S` seconds; :meth:`close`
        writes the last state if it was held back.
        """
        if not self.enabled:
            return
        now = time.monotonic()
        with self._lock:
            self._state, self._written = (fraction, text, seconds_left, now), False
            interval = REDRAW_INTERVAL_S if self.terminal else PLAIN_INTERVAL_S
            if force or now - self._last_write >= interval:
                self._write(now)
        if self.terminal and self._ticker is None:
            self._ticker = threading.Thread(target=self._tick, name="progress-ticker", daemon=True)
            self._ticker.start()

    def _write(self, now: float) -> None:
        """Write the latest state as of ``now`` (the lock held)."""
        fraction, text, seconds_left, given = self._state
        age = now - given
        parts = [text, f"elapsed {format_seconds(now - self.start)}"]
        if seconds_left is not None:
            parts.append(f"eta {format_seconds(max(seconds_left - age, 0.0))}")
            if fraction is not None and seconds_left > 0:
                # A fraction e/(e + l) of time after age more seconds: (e + age)/(e + l).
                fraction += min(age, seconds_left) * (1.0 - fraction) / seconds_left
        line = "  ".join(part for part in parts if part)
        percent = None if fraction is None else 100.0 * min(max(fraction, 0.0), 1.0)
        if self.terminal:
            self._draw(percent, line)
        else:
            prefix = self.label if percent is None else f"{self.label} {percent:3.0f}%"
            self.stream.write(f"{prefix}  {line}\n")
            self.stream.flush()
        self._last_write, self._written = now, True

    def _draw(self, percent, line) -> None:
        # The text goes into the format itself: tqdm's postfix field would
        # put ", " before it.
        text = line.replace("{", "{{").replace("}", "}}")
        known = percent is not None
        bar_format = ("{desc} {percentage:3.0f}%|{bar}| " if known else "{desc}  ") + text
        if self._bar is None:
            # Imported here: tqdm's import (its version lookup through importlib.metadata)
            # is 35 ms of every command's start-up, and only a terminal bar needs it.
            from tqdm import tqdm

            self._bar = tqdm(total=100 if known else None, file=self.stream, dynamic_ncols=True,
                             leave=True, desc=self.label, mininterval=0, bar_format=bar_format)
        if known and self._bar.total:
            self._bar.n = percent
        self._bar.bar_format = bar_format
        self._bar.refresh()

    def _tick(self) -> None:
        while not self._stop.wait(TICK_S):
            now = time.monotonic()
            with self._lock:
                if self._state is not None and now - self._last_write >= TICK_S:
                    self._write(now)

    def close(self) -> None:
        """Write the last state if it was held back, and end the line."""
        self._stop.set()
        if self._ticker is not None:
            self._ticker.join()
        with self._lock:
            if self.enabled and not self._written:
                self._write(time.monotonic())
            if self._bar is not None:
                self._bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
