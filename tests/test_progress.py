"""Progress display: a bar on terminals, a few plain lines elsewhere, nothing when quiet."""

import io

import pytest

from octcl import _progress
from octcl._progress import ProgressDisplay, format_seconds


class Terminal(io.StringIO):
    def isatty(self):
        return True


@pytest.mark.parametrize("seconds, text", [(0.4, "0s"), (42, "42s"), (425, "7m05s"), (3720, "1h02m"),
                                           (float("inf"), "?")])
def test_format_seconds(seconds, text):
    assert format_seconds(seconds) == text


def test_plain_lines_off_a_terminal_are_few_and_end_with_the_last_state():
    stream = io.StringIO()
    with ProgressDisplay("invert", stream) as display:
        display.update(0.0, "field 0/1500", 30.0, force=True)
        for step in range(1, 1001):  # far faster than PLAIN_INTERVAL_S: held back
            display.update(step / 1000, f"refine {step}/1000", 30.0 * (1 - step / 1000))
        display.update(1.0, "done", 0.0, force=True)
    lines = stream.getvalue().splitlines()
    assert "\r" not in stream.getvalue()
    assert lines[0].startswith("invert   0%  field 0/1500") and "eta 30s" in lines[0]
    assert len(lines) == 2 and lines[-1].startswith("invert 100%  done") and "eta 0s" in lines[-1]


def test_close_writes_a_held_back_state(monkeypatch):
    stream = io.StringIO()
    with ProgressDisplay("score", stream) as display:
        display.update(0.5, "1/2 a.png")
        display.update(1.0, "2/2 b.png")  # within PLAIN_INTERVAL_S of the first
    assert stream.getvalue().splitlines() == ["score  50%  1/2 a.png  elapsed 0s",
                                              "score 100%  2/2 b.png  elapsed 0s"]


def test_terminal_bar_shows_the_callers_fraction_and_time_left(monkeypatch):
    monkeypatch.setattr(_progress, "TICK_S", 0.05)
    stream = Terminal()
    with ProgressDisplay("invert", stream) as display:
        display.update(0.25, "refine 15/400  score 0.99621 at 21s", 60.0, force=True)
    screen = stream.getvalue()
    assert "invert  25%|" in screen and "refine 15/400  score 0.99621 at 21s" in screen
    assert "eta 1m00s" in screen and "it/s" not in screen  # the caller's estimate, not tqdm's rate


def test_terminal_ticker_counts_the_time_left_down(monkeypatch):
    monkeypatch.setattr(_progress, "TICK_S", 0.05)
    stream = Terminal()
    display = ProgressDisplay("invert", stream)
    display.update(0.5, "setup", 1.0, force=True)
    import time

    time.sleep(0.6)
    display.close()
    redraws = [part for part in stream.getvalue().split("\r") if "invert" in part]
    assert len(redraws) >= 3
    percents = [int(part.split("%")[0].split()[-1]) for part in redraws]
    assert percents == sorted(percents) and 50 < percents[-1] < 100  # 0.5 + 0.6·0.5/1 = 80 %


def test_quiet_writes_nothing():
    stream = Terminal()
    with ProgressDisplay("invert", stream, enabled=False) as display:
        display.update(0.5, "refine", 10.0, force=True)
    assert stream.getvalue() == ""
