"""0.8.5 against 0.8.6, in one process: the tissue decode's tails (np.polyfit line by line against
:func:`octcl.host.stage2.tissue.tail_sums`) and :func:`octcl.phantom.round_significant` of 262,144 energies of
10^U(−36, −10) % (every |p| > 22 through Python against the double-double). Each twice, in turn.

Example::

    python scripts/bench_round.py
"""

import time

import numpy as np
from scipy.ndimage import convolve1d
from octcl import _reference as ref
from octcl.config import DEFAULT_CONFIG
from octcl.host.stage2 import tissue
import octcl.phantom as ph

def polyfit_tails(rows_sq):  # 0.8.5's tail_sums, line by line
    signal = rows_sq > tissue.SIGNAL_SHARE * rows_sq.max()
    tails = np.zeros(rows_sq.shape[1])
    for line in range(rows_sq.shape[1]):
        rows = np.flatnonzero(signal[:, line])[-tissue.TAIL_ROWS:]
        if rows.size >= 2:
            fit = np.polyfit(rows, np.log(rows_sq[rows, line]), 1)
            ratio = min(float(np.exp(fit[0])), tissue.MAX_TAIL_RATIO)
            tails[line] = np.exp(np.polyval(fit, rows[-1])) * ratio / (1 - ratio)
    return tails

rng = np.random.default_rng(1)
field = (rng.normal(size=(256, 512)) + 1j * rng.normal(size=(256, 512))) * np.exp(-np.arange(256) / 40.0)[:, None]
rows_sq = convolve1d(tissue.local_mean_energy(field), ref.shadow_taps(DEFAULT_CONFIG), axis=1, mode="constant")
for name, tails in [("np.polyfit per line (0.8.5)", polyfit_tails), ("tail_sums (0.8.6)", tissue.tail_sums)] * 2:
    start = time.perf_counter(); value = tails(rows_sq); print(name, round(time.perf_counter() - start, 4))
print("largest relative difference", np.max(np.abs(tissue.tail_sums(rows_sq) / polyfit_tails(rows_sq) - 1)))

def through_python(values, power):  # 0.8.5: every |p| > 22 left to Python
    return ph._times_power_of_ten(values, power), np.abs(power) <= ph._EXACT_POWER
double_double = ph._times_power_of_ten_rounded
energies = 10.0 ** rng.uniform(-36, -10, 262144)
for name, rounded in [("through Python (0.8.5)", through_python), ("double-double (0.8.6)", double_double)] * 2:
    ph._times_power_of_ten_rounded = rounded
    start = time.perf_counter(); ph.round_significant(energies, 8); print("round_significant", name, round(time.perf_counter() - start, 3))
