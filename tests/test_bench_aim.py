"""scripts/bench_aim.py: single moves of the first round's pixels, each scored alone from the aim."""

from __future__ import annotations

import numpy as np

from conftest import load_script


class FakeSearch:
    """A proposal that moves three pixels two levels up; predicted changes −3, −2, −1 (1e−6) there."""

    def __init__(self, aim):
        self.picks = np.array([5, 17, 30])
        self.proposed = aim.copy()
        self.proposed.flat[self.picks] += 2

    def proposal(self, aim):
        return self.proposed, self.picks

    def predicted_change(self, aim):
        change = np.zeros(aim.size)
        change[self.picks] = [-3e-6, -2e-6, -1e-6]
        return change


def fake_exact(levels):
    """Components that see the image: ``msssim_SC`` its sum, ``mean`` its sum (1e−6 a level)."""
    total = float(np.sum(levels, dtype=np.int64)) * 1e-6
    return {"msssim_SC": total, "mean": total}


def test_each_pick_is_moved_alone_and_scored_from_the_aim(capsys):
    script = load_script("bench_aim")
    aim = np.full((4, 8), 60, np.uint8)
    script.single_moves(FakeSearch(aim), fake_exact, aim, count=2)
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "  single moves (first 2 of the first round's 3):"
    # Each line is one pixel moved from the aim, not the moves added up: +2 levels is +2e-06 every time.
    assert lines[1].startswith("    (0,5) level 60->62: predicted -3.00e-06, score +2.00e-06; msssim_SC +2.0e-06")
    assert lines[2].startswith("    (2,1) level 60->62: predicted -2.00e-06, score +2.00e-06")
    assert len(lines) == 3
