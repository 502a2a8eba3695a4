"""Invert a target B-scan into a digital phantom: stages 1–3 under a time budget.

1. A complex reflectivity field on the pixel grid whose linear
   (shadowing-free) rendering matches the target;
2. point scatterers (x, y, z, E) that reproduce that field;
3. :func:`octcl.host.stage3.refine.refine` — Adam on every scatterer's depth and
   log-energy through the OpenCL scanner and its adjoint, judged by the
   exact score.

Stages 1–2 come in three regimes (:data:`REGIMES`):

- ``linear`` (the default), :mod:`octcl.host.stage1.projections`: a schedule of named
  steps (:mod:`octcl.host.stage1.solve`: a display fit, projections onto the
  target's level intervals, a hinge fit and, where the target has levels
  the scanner cannot write, the aim step) finds the field in 4–5 s on two
  cores (a second candidate only where the first falls short), and an exact
  decode puts two rows in every cell at energies so small (E ≲ 1e−10 %)
  that shadowing changes no display level. The phantom is a numerical device:
  it renders as the target, but its energies are not tissue-like.
- ``physical``, the published pipeline: :func:`octcl.host.stage1.display.fit_field`
  (1500 Adam steps on the display, 10–12 s) and
  :func:`octcl.host.stage2.capped.decode_field` (amplitude-capped children at
  random elevations, shadowing ≤ 1e−4 per A-scan); slower and lower
  scoring, kept to reproduce the published method.
- ``tissue``: the linear regime's stage 1, the field of least norm that
  renders as its field does (:func:`octcl.host.stage1.start.least_norm_twin`),
  then :func:`octcl.host.stage2.tissue.decode_tissue` of it (the rows at tissue scale,
  each divided by the light the rows above leave it, the scale from the
  light left below the data) and stage 3 with shadowing on
  (:data:`TISSUE_SCHEDULE`: the pixel term alone, then L-BFGS onto the levels). The
  result carries the phantom's figures as tissue
  (:func:`octcl.tissue.tissue_figures`).

Measured on the development set: docs/benchmarks.md ("the linear regime").

The output file is only ever replaced by a complete, validated phantom
(:meth:`octcl.phantom.Phantom.save` writes a temporary file and renames it),
first right after stage 2, then whenever the exact score improves (at most
every ``CHECKPOINT_INTERVAL_S`` seconds) and at the end; a process killed at
any moment leaves the last checkpoint, or no file before the first.

Two modes. In deadline mode (the default) the stages share out the time
budget, so how far each gets depends on the machine's speed and load; the
result records the iteration counts reached, and whether the clock decided
anything (:attr:`InvertResult.reproducible`): a run it did not is repeated
byte for byte by the same call and by its fixed schedule. A fixed schedule
(``iterations``) runs by iteration counts alone, takes no decision from the
clock, and writes the same file, byte for byte, every time, at any torch
thread count (``docs/reproducibility.md``); there the budget is only a
ceiling that fails the run loudly.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from octcl._io import atomic_write, check_output_path
from octcl.config import DEFAULT_CONFIG, ScannerConfig
from octcl.measured import MeasuredTimes
from octcl.phantom import CONTRACT_Y_LIMIT_UM, TARGET_ROWS, Phantom
from octcl.torch_import import import_torch_in_background, torch_import_s

from ..stage1.backend import BACKENDS, make_backend
from ..stage1.ceiling import WRITABLE, aimed_levels, ceiling_image, measure_ceiling
from ..stage1.levels import target_levels
from ..stage1.start import DISPLAY_ITERATIONS
from ..stage3.refine import Phase, RefineProgress, RefineSchedule, TimeBudgetExceeded, RefineClock, check_target_score, refine
from ..threads import available_cores
from .target import check_target, read_target, target_scan, target_struct_for_metrics

#: Least time between two checkpoint writes during refinement, in seconds.
#: Formatting and writing 262,000–295,000 rows takes 0.1–0.4 s
#: (``scripts/bench_io.py``; in a background thread, on the same two cores).
CHECKPOINT_INTERVAL_S = 20.0
#: Stages 1–2 by name (module docstring), the default first.
REGIMES = ("linear", "physical", "tissue")
#: Share of the time budget stage 1 may use, and its cap in seconds. In the
#: physical regime stage 1 usually ends first at its 1500 iterations (11–12 s
#: on two idle cores); its length matters little for the end result: on
#: orange.png a 5 s stage 1 ended at 0.99944 after 281 s, the full 11 s one
#: at 0.99950 after 318 s.
FIELD_BUDGET_FRACTION = 0.08
FIELD_BUDGET_CAP_S = 45.0
#: Seconds the linear regime keeps back from stage 1 for stage 2 and the first
#: write of its phantom where this machine has measured neither (:func:`write_reserve_s`): the exact decode took
#: 0.58–0.65 s and the write 0.2–0.3 s on two cores of an AMD EPYC
#: (``octcl invert`` reports, ``seconds.decode`` and
#: ``seconds.checkpoint_writes``); 1.05–1.10 s and 0.30–0.33 s on two of the first Zen generation, where the
#: decode to its tolerance (octcl 0.8.5, :data:`octcl.host.stage2.exact.DECODE_TOLERANCE`) takes 0.38–0.47 s.
LINEAR_WRITE_RESERVE_S = 1.0
#: The same for the tissue regime, whose decode (:func:`octcl.host.stage2.tissue.decode_tissue`) took 1.7 s on two
#: cores (skin phantom, seed 5; 2.5 s before its pairs were chosen again only where a cell left its own), and
#: 1.6–2.2 s to its tolerance on two first-generation Zen cores (``--time-budget 30`` runs, octcl 0.8.5).
TISSUE_WRITE_RESERVE_S = 4.0
#: Seconds of the close after the first write where this machine has measured none (:func:`write_reserve_s`):
#: stage 3's setup and its input's render, when no step follows (0.43–0.68 s on two first-generation Zen cores,
#: ``seconds.refine`` of ``--time-budget 3`` runs).
CLOSE_S = 0.5
#: The spans a run measures and the next run's clock starts from (:mod:`octcl.measured`), per grid
#: (``NZxNX``): per regime, its decode and first write (``"<regime> first write NZxNX"``), the close after
#: it in a run whose stage 3 took no step (``"close NZxNX"``, stage 3's seconds less its exact scores), and
#: the tissue figures (``"tissue figures NZxNX"``).
SPANS = MeasuredTimes("invert_spans.json")
#: Stage 1's seconds at least, however little of the budget is left.
MIN_FIELD_BUDGET_S = 0.2
#: Share of the seconds left before the run's exit that the tissue regime's least-norm twin may take
#: (:func:`octcl.host.stage1.start.least_norm_twin`, at most its 200 hinge iterations); the rest goes to the
#: decode and stage 3. The twin's iterations cost 30–40 ms each on two first-generation Zen cores, where 200 of them
#: took 6–8 s of a 30 s budget and left stage 3 a few dozen steps, inside its pixel phase. There, under
#: ``--regime tissue --time-budget 30`` (the twin at 90–115 of its iterations), orange.png and two plainly quantised
#: skin renderings scored 0.99832, 0.99368, 0.99438 where the whole of what stage 1 left gave 0.99653–0.99745,
#: 0.98564–0.99043 and 0.95473–0.96360 (two runs each), and skins 6 and 7 0.99808 and 0.99892 against 0.99804
#: and 0.99389, their shadows and bands as close to the truth's (docs/benchmarks.md). On a faster machine (the
#: twin's 200 iterations in 2 s) and at the default budget the share is more than the twin takes.
TWIN_SHARE = 0.15
#: Stage 1's Adam steps by regime unless given (the learning rate anneals
#: over them); in the linear regime those of the first display fit
#: (:data:`octcl.host.stage1.start.DISPLAY_ITERATIONS`, where the choice is measured).
FIELD_ITERATIONS = {"physical": 1500, "linear": DISPLAY_ITERATIONS, "tissue": DISPLAY_ITERATIONS}
#: Stage 3's schedule in the linear regime: short steps while they gain.
#: From a linear start the physical regime's schedule fell at once (its
#: first 20 steps took Uniform B from 0.99964 to 0.9979; steps 4× shorter,
#: lr_z_um 0.0005 and lr_u 0.005, still to 0.9988, and so did the pixel
#: term alone): the start has most pixels at the target's very level, and
#: an Adam step moves every scatterer. So the main run is 10 steps at
#: (lr_z_um, lr_u) = (1e−4, 1e−3), then restarts of 10 steps at half that
#: from the best phantom, each repeated while it gains 1e−5 (at most 10).
#: On the development set it gained on skin_1 (+4.0e−5) and, in an
#: earlier run, on skin_0 and skin_2 (+4.1e−5, +4.7e−5); where the start is
#: already at its best it stops after 20 steps, about 12 s
#: (docs/benchmarks.md, "the linear regime").
LINEAR_SCHEDULE = RefineSchedule(phases=(Phase(10, 0.0001, 0.001),),
                                 restarts=(Phase(10, 0.00005, 0.0005),) * 10, score_every=10)
#: Stage 3's schedule in the tissue regime: the pixel term alone first, then the full loss at short steps. The
#: tissue decode's start renders 40–60 % of pixels at their level (shadowing between neighbouring A-scans it does
#: not compensate): on skins 6 and 7 the full loss took it to 0.9954 and 0.9946 in 40 s (60–61 % exact), the pixel
#: term alone (0.13–0.14 s a step, not 0.50–0.56) to 0.9975 and 0.9977 (84–85 %); its rates (0.001, 0.02) are the
#: best of eight pairs on skin 5; there 250 such steps and then the full loss at (0.0005, 0.005) reached 0.9992
#: in 55 s, 500 and then the full loss 0.9994 in 120 s (docs/benchmarks.md, "Stage 3 in the tissue regime").
#: From the decode at its 0.95-quantile scale (skin 5, start 0.866) the choice still holds within the noise: 250,
#: 100 and 50 pixel steps scored 0.99897, 0.99908 and 0.99909 in 20 s, 250 and 100 scored 0.99943 and 0.99953 in
#: 45 s; the pixel term alone at five rate pairs 0.99806–0.99878 in 20 s, (0.001, 0.02) 0.99870.
#: From the decode of the least-norm twin, 120 pixel steps: 250, 120 and 60 scored 0.99924, 0.99945, 0.99938
#: (skin 6), 0.99922, 0.99936, 0.99943 (orange.png), 0.99909, 0.99934, 0.99930 (plain_skin_0) and 0.99892,
#: 0.99940, 0.99932 (plain_skin_1) in 20 s; 250 and 120 within 4e−5 of each other in 45 s (on orange the pixel
#: term alone peaks after 60–80 steps and then falls: it pulls unwritable levels towards the target's own)
#: (``scripts/bench_tissue_refine.py --skin 6 --real ... --schedules tissue --pixel-steps 250 120 60``).
#: Since then the pixel phase compares with the aimed levels, not the target's (:func:`refine`'s ``aim``): on the
#: real-like targets (orange.png, plain_skin_0–3) 0.99962 / 0.99947 / 0.99950 / 0.99943 / 0.99961 against
#: 0.99947 / 0.99947 / 0.99950 / 0.99946 / 0.99958 at ``--time-budget 60``; skins, whose aim is their own levels,
#: unchanged (docs/benchmarks.md, "The pixel phase aims at the aimed levels").
#: The full loss at half the rates, (0.00025, 0.0025): after the pixel phase a step at (0.0005, 0.005) took pixels
#: off their level faster than the maps' terms gained. Whole ``--regime tissue --time-budget 30`` runs on eleven
#: targets (orange.png, it mirrored and through a gamma, plain_skin_0–5, skins 7 and 8; two Zen 4 cores): global
#: 0.99963 → 0.99967, higher on nine, lower on one (orange mirrored, by 2.6e−5). A second pixel phase at
#: (0.0005, 0.005) before it gained more on the skins and lost on all three orange scans (by 5e−5 to 1.7e−4):
#: not taken (docs/benchmarks.md, "The tissue regime's full loss at half its rates"). The restarts are as before:
#: a 30 s run does not reach them.
#: The hinge phase after the pixel phase (:mod:`octcl.host.stage3.hinge`): L-BFGS on each pixel's magnitude against
#: its aimed level's interval, through the shadowing, where Adam's fixed step holds pixels one or two levels off.
#: Stage 3 alone for 21 s from each target's tissue start (``scripts/bench_tissue_refine.py --phases``, two Zen 4
#: cores), the pixel phase then the full loss against the pixel phase, the hinge, the full loss: skin 8 0.99985 →
#: 0.99988 (93.4 → 95.4 % of pixels at their level), orange.png 0.99930 → 0.99966; with 60 pixel steps instead of
#: 120 before the hinge, skin 9 0.99982 against 0.99986, orange.png 0.99966 against 0.99967, plain_skin_1 0.99974
#: against 0.99978 (docs/benchmarks.md, "Stage 3's hinge phase"). After the hinge the full loss took pixels off
#: their level again: a default run of skin 11 scored 0.999932 at the hinge's end (44 s), then 0.99982–0.99987
#: over 180 s of the full loss and its restarts; with hinge restarts instead (each from the best, fresh L-BFGS
#: memory, repeated while one gains 1e−5), the same 0.999932 in 74 s, and orange.png 0.99987 in 84 s.
#: The pixel phase ends at a quarter of its rates: at (0.001, 0.02) to its end, its loss jumped between steps (Adam's
#: fixed step moves every scatterer about a level, and the brightest pixel's moves shift the whole display), and
#: the hinge began from pixels one or two levels off. 100 steps, then 40 at (0.00025, 0.005), against 120 at the
#: full rates, stage 3 alone for 21 s from each target's tissue start (``scripts/bench_tissue_refine.py --phases``,
#: two Zen 4 cores): plain_skin_0–5 0.999777 / 0.999784 / 0.999761 / 0.999766 / 0.999777 / 0.999782 → 0.999819 /
#: 0.999794 / 0.999802 / 0.999811 / 0.999812 / 0.999776, orange.png 0.999656 → 0.999667, with 0.4–3.7 points more
#: of their pixels at the target's level; 80 then 40 steps, the second phase at half the rates, or three phases
#: gained less on most (docs/benchmarks.md, "The pixel phase ends at a quarter of its rates").
#: Nine hinge restarts may follow (at 0.8.9, while each gained 1e−5): with one (the schedule's iterations then
#: spent), a default run of skin 11 stopped at 500 iterations still gaining (0.999957, 98.6 % of pixels at their
#: level, 94 s); with nine it went on to 0.999965 and 98.8 % (106 s), skin 12 to 0.999969 and 98.9 % (87 s), both
#: stopped by the gain rule (docs/benchmarks.md, "The default tissue budget").
#: The hinge's anchor weighs one pixel (``hinge_anchor_weight``): at 100, whole 30 s runs on twelve targets scored
#: higher (global 0.9998137 → 0.9998182), but default runs of skins 11 and 12 ended lower (0.999965 / 0.999969 →
#: 0.999932 / 0.999930, 98.8 / 98.9 → 97.2 / 97.6 % of pixels at their level) (docs/benchmarks.md, "Where the
#: hinge loses time").
#: After the hinge, 150 more iterations and the restarts weigh dark pixels more (γ = ½, :mod:`octcl.host.stage3.hinge`),
#: where 0.8.9's hinge ended with 1–5 % of a skin's pixels a level off, most of them dark. Whole default runs
#: (docs/benchmarks.md, "The hinge weighs dark pixels more"): γ = ½ over the hinge's second half (150 at 0, 150 at ½)
#: took the held-out skins 11–15 from a mean of 0.9999436 and 97.69 % of pixels at their level to 0.9999616 and
#: 99.03 %, but orange.png from 0.999875 (88.4 %) to 0.999808 (78.0 %): it fell at γ = ½ from step 290 and did not
#: come back. The whole 300 at 0 first, with only the restarts at ½, took orange.png to 0.999892 and skin 14 to
#: 0.999886 (0.8.9: 0.999881), skin 11 down to 0.999934. Both, as here: skins 11–15 at a mean of 0.9999638 and
#: 99.11 % (four of five at 99.3–99.6 %, skin 14 97.8 %), orange.png 0.999896 (92.6 %), 76–129 s. A 30 s run ends
#: in the γ = 0 part (its stage 3 took 141–161 steps of the 440 before the γ = ½ phase).
#: The hinge restarts end once two in a row together gained less than 5e−6 (:data:`TISSUE_MIN_GAIN`,
#: :data:`TISSUE_RESTART_PATIENCE`; the one-restart 1e−5 rule before it stopped skin 14 after its first restart at
#: 97.79 % of pixels at their level). They gain 2–11e−6 each, unevenly: with every restart run, skin 6 (a tuning
#: seed) gained 8.9, 1.8, 2.5, 4.6, … e−6 and skin 14 (held-out) 9.5, 11.0, 8.3, … 2.9e−6. On the tuning runs (skins
#: 6 and 7, orange.png through a gamma) 1e−5 and 5e−6 over two restarts stop at the same restart; on skin 14 the
#: second runs all nine (``scripts/replay_stop_rule.py``). Whole default runs of held-out skins 11–15: 0.9999638 and
#: 99.11 % in the mean to 0.9999778 and 99.48 %, every one ≥ 99.16 %, 106–168 s; orange.png the same 0.9998955
#: (docs/benchmarks.md, "Hinge restarts judged two at a time").
TISSUE_MIN_GAIN = 5e-6
TISSUE_RESTART_PATIENCE = 2
#: The pixel phases end once two checkpoints (40 steps) gained less than :data:`TISSUE_MIN_GAIN`, and the hinge
#: begins: on orange.png the pixel phase's best came at step 40 and its exact score then fell (0.99920 to 0.99880
#: at step 120) while the hinge climbs at once, and 30 s runs on two slow cores ended at steps 133–155, the orange
#: family at 0.99920–0.99965 by whether the hinge had begun; with the patience 0.99962–0.99967. A skin's pixel
#: phase gains ≥ 2.7e−5 over every two checkpoints and runs its length (docs/benchmarks.md, "The tissue pixel
#: phase ends where it stops gaining").
TISSUE_PIXEL_PATIENCE = 2
TISSUE_SCHEDULE = RefineSchedule(phases=(Phase(100, 0.001, 0.02, terms="pixel", patience=TISSUE_PIXEL_PATIENCE),
                                         Phase(40, 0.00025, 0.005, terms="pixel", patience=TISSUE_PIXEL_PATIENCE),
                                         Phase(300, 0.0, 0.0, terms="hinge"),
                                         Phase(150, 0.0, 0.0, terms="hinge", relative_exponent=0.5)),
                                 restarts=(Phase(60, 0.0, 0.0, terms="hinge", relative_exponent=0.5),) * 9,
                                 min_gain=TISSUE_MIN_GAIN, restart_patience=TISSUE_RESTART_PATIENCE)
#: torch's thread count in a fixed-schedule run unless given. The thread
#: count changes no bit of the result (docs/reproducibility.md), only the
#: speed; one thread is never slowed by other processes holding the cores
#: (see host/stage3/refine.py, _ThreadChooser).
FIXED_THREADS = 1
#: Seconds kept back from stage 3 for the last checkpoint write and the
#: report, at most: a write may be under way when stage 3 ends and the best
#: phantom still pending (0.1–0.4 s for 295,000 rows, ``scripts/bench_io.py``),
#: and on a loaded machine a step can take longer than the last one measured
#: (seen here: a 30 s budget overrun by 0.13 s with 1.5 s kept back, while
#: other processes held both cores). A short budget keeps back
#: :data:`FINAL_RESERVE_FRACTION` of itself instead (1.5 s of 10 s).
FINAL_RESERVE_S = 7.0
FINAL_RESERVE_FRACTION = 0.15
#: Factor on what follows stage 3 by this run's measures (:meth:`_Run.after_stage_3_s`): its first write, the
#: ceiling's score still to compute, the tissue figures. Stage 3 keeps back that, with this margin for a
#: loaded machine, and :data:`EXIT_RESERVE_S`, where it is less than :func:`final_reserve_s`: a 30 s tissue run
#: of orange.png kept back 4.5 s and ended at 26.7 s (two first-generation Zen cores), its write taking 0.37 s,
#: the ceiling's score 0.45 s and the figures about 0.4 s after stage 3.
AFTER_STAGE_3_FACTOR = 1.5
#: Seconds before :attr:`_Run.exit_by` below which a run does not import torch on a thread beside stage 1: under a
#: short budget the clock sets stage 1's steps, and the import slowed them (orange.png on two EPYC cores:
#: ``--time-budget 3`` ended at 5.34 and 3.27 s, ``--time-budget 5`` at 5.35 s with its score left out, against
#: 2.76 s and 4.24–4.40 s without the thread).
PREFETCH_TORCH_MIN_S = 20.0
#: Seconds a process needs after :func:`invert` returns: the report, the summary, the interpreter's exit
#: (deadline mode leaves out a ceiling score that would eat into them).
EXIT_RESERVE_S = 0.25
#: Seconds :func:`octcl.tissue.tissue_figures` takes on a 295,000-row phantom (1.0–1.4 s on two cores, ``octcl
#: phantom-stats``), with a margin.
TISSUE_FIGURES_S = 2.0
#: Seconds of a run's first exact score beyond torch's import (:func:`octcl.torch_import.torch_import_s`, which
#: is known per machine), before one has been timed: the LPIPS network and the target's maps and features, one
#: score (0.18 + 0.25 s on orange.png on two cores, ``scripts/bench_aim.py``), with a margin.
SCORER_BUILD_S = 0.6


@dataclass
class InvertResult:
    """Outcome of :func:`invert`.

    Attributes
    ----------
    target : str
        The target's name: its path, or the ``name`` given with an array.
    output : str
        The phantom file written.
    score : float or None
        Mean of the eight exact components of the written phantom's rendering; None where a time budget
        left no time to compute it (deadline mode: stage 3 leaves out a first score that would end past
        its deadline, :meth:`octcl.host.stage3.refine` ``score_input``).
    components : dict or None
        Those eight components (None as ``score``).
    initial_score : float or None
        The exact score after stages 1–2 (None as ``score``).
    scatterers : int
        Rows in the output.
    iterations : int
        Adam steps of stage 3.
    seconds : dict
        Wall time of each stage and ``total``.
    checkpoints : int
        Times the output was written.
    peak_memory_mib : float
        Peak resident memory of the process (ru_maxrss).
    stopped_by_deadline : bool
        Stage 3 was cut short by the time budget.
    stop_reason : str
        What ended stage 3 (:attr:`octcl.host.stage3.refine.RefineResult.stop_reason`):
        ``schedule``, ``converged``, ``target score``, ``ceiling`` or ``deadline``.
    falls : list of int
        Stage-3 steps after which the main run fell and went back to the best
        phantom at lower learning rates
        (:attr:`octcl.host.stage3.refine.RefineSchedule.max_falls`).
    seed : int
    regime : str
        Stages 1–2 (:data:`REGIMES`): ``linear`` or ``physical``.
    field_iterations : int
        Adam steps of stage 1 (in the linear regime, of its first display fit;
        the second has half as many).
    fixed_schedule : bool
        The run followed a fixed schedule (``iterations`` given): no
        decision was taken from the clock.
    threads : int or None
        CPU threads (stage 1's FFTs, stage 3's torch), held for the whole run; None where it was
        chosen by timing (a deadline run without ``threads``).
    reproduce : str
        ``octcl invert`` options that run this schedule again with no
        decision from the clock: ``--seed``, ``--iterations``,
        ``--field-iterations``, ``--threads``.
    reproducible : bool
        No decision of this run came from the clock, so ``reproduce`` gives
        the same file again, byte for byte (same version and device, see
        ``docs/reproducibility.md``): always for a fixed schedule; for a
        deadline run, unless stage 1 fell behind its time share (its
        learning rate then followed the clock) or the deadline ended stage 3.
        The thread count, timed or given, changes no bit (measured at 1 and
        2 threads).
    ceiling : dict
        What the target allows, measured apart from the inversion
        (:class:`octcl.host.stage1.ceiling.Ceiling`): ``writable_share``,
        ``diffused_score``.
    exact_share : float
        Share of pixels the written phantom renders at the target's level.
    avoidable_share : float
        Share of pixels at a writable level of the target that the phantom
        renders at another: what a better phantom could still gain.
    tissue : dict or None
        The tissue regime's phantom as tissue (:func:`octcl.tissue.tissue_figures` against the target: energy
        percentiles, shadow at the bottom of the visible tissue, band densities, median attenuation); None in the
        other regimes, and where a time budget left no time for them (:data:`TISSUE_FIGURES_S`).
    levels : ndarray of uint8, (Nz, Nx)
        The written phantom's rendering, as its score saw it (not in :meth:`as_dict`).
    attenuation_per_mm : ndarray or None, (Nz, Nx)
        The written phantom's attenuation map, µ in mm⁻¹ from its own transmission
        (:func:`octcl.tissue.attenuation_map`), where ``tissue`` is given; None otherwise (not in :meth:`as_dict`).
    """

    target: str
    output: str
    score: float | None
    components: dict | None
    initial_score: float | None
    scatterers: int
    iterations: int
    seconds: dict
    checkpoints: int
    peak_memory_mib: float
    stopped_by_deadline: bool
    stop_reason: str
    falls: list
    seed: int
    regime: str
    field_iterations: int
    fixed_schedule: bool
    threads: int | None
    reproduce: str
    reproducible: bool
    ceiling: dict
    exact_share: float
    avoidable_share: float
    tissue: dict | None = None
    levels: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    attenuation_per_mm: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)

    def as_dict(self) -> dict:
        """The result as JSON takes it: every attribute but the two maps."""
        contents = dataclasses.asdict(dataclasses.replace(self, levels=None, attenuation_per_mm=None))
        return {key: value for key, value in contents.items() if key not in ("levels", "attenuation_per_mm")}


@dataclass(frozen=True)
class InvertProgress:
    """Where an inversion stands: what :func:`invert` tells its ``progress`` callback.

    The run ends at whichever comes first: the end of stage 3's schedule or
    stage 3's deadline (the budget less :func:`final_reserve_s`).
    ``seconds_left`` is the earlier of the two estimates (the schedule's from
    stage 3's measured seconds per iteration, once there is one), so it never
    exceeds the time left in the budget; ``fraction`` is
    elapsed / (elapsed + seconds_left). The last state (stage ``done``) has
    fraction 1 and no time left.

    Attributes
    ----------
    stage : str
        ``field`` (stage 1), ``twin`` (the tissue regime's least-norm field,
        :func:`~octcl.host.stage1.start.least_norm_twin`), ``decode`` (stage 2), ``setup`` (kernels and
        scorer), ``refine`` or ``restart N`` (stage 3), ``done``.
    iteration, iterations : int
        Steps taken and planned in the stage (stage 3: Adam steps, restarts
        included, against the whole schedule).
    fraction : float
        Share of the run done, in [0, 1].
    seconds_left : float
        Estimated seconds until the run ends.
    elapsed_s : float
        Seconds since the run started.
    score : float or None
        The last exact score measured (None before stage 3's first).
    score_elapsed_s : float or None
        ``elapsed_s`` when it was measured.
    """

    stage: str
    iteration: int
    iterations: int
    fraction: float
    seconds_left: float
    elapsed_s: float
    score: float | None = None
    score_elapsed_s: float | None = None


class _ProgressReporter:
    """Turns the stages' callbacks into :class:`InvertProgress` states.

    ``end`` is the ``time.monotonic()`` by which the budget ends the run.
    """

    def __init__(self, callback, started: float, end: float):
        self.callback, self.started, self.end = callback, started, end
        self.score = self.score_time = None
        self._refine_start = None  # (monotonic time, iterations) of stage 3's first report

    def __call__(self, stage: str, iteration: int, iterations: int, seconds_left: float | None = None,
                 done: bool = False) -> None:
        if self.callback is None:
            return
        now = time.monotonic()
        budget_left = max(self.end - now, 0.0)
        seconds_left = 0.0 if done else budget_left if seconds_left is None else min(seconds_left, budget_left)
        elapsed = now - self.started
        self.callback(InvertProgress(
            stage=stage, iteration=iteration, iterations=iterations,
            fraction=1.0 if done else elapsed / (elapsed + seconds_left) if elapsed + seconds_left > 0 else 0.0,
            seconds_left=seconds_left, elapsed_s=elapsed, score=self.score,
            score_elapsed_s=None if self.score_time is None else self.score_time - self.started))

    def refine(self, status: RefineProgress) -> None:
        """Stage 3's report; the schedule's time left from its seconds per iteration so far."""
        self.score, self.score_time = status.score, status.score_time
        now = time.monotonic()
        if self._refine_start is None:
            self._refine_start = (now, status.iterations)
        start_time, start_iterations = self._refine_start
        schedule_left = None
        if status.iterations > start_iterations:
            per_iteration = (now - start_time) / (status.iterations - start_iterations)
            schedule_left = (status.total - status.iterations) * per_iteration
        self(status.stage, status.iterations, status.total, schedule_left)


def peak_memory_mib() -> float:
    """Peak resident memory of this process in MiB.

    POSIX: ``ru_maxrss`` (KiB on Linux, bytes on macOS). Windows, which has
    no ``resource`` module: the peak working set, through psutil.
    """
    if sys.platform == "win32":
        import psutil

        return psutil.Process().memory_info().peak_wset / 2**20
    import resource

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024


class _CheckpointWriter:
    """Writes phantoms to the output in a background thread: validated, atomic, rate-limited.

    Formatting and writing 295,000 rows takes 1.5–3.5 s of Python on this
    machine; in the background it overlaps with the kernels and the loss,
    which release the interpreter lock, instead of stopping the refinement.
    Only the newest offered phantom is kept, and one is written at most every
    ``interval_s`` seconds; :meth:`close` writes what is still pending.
    """

    def __init__(self, path: Path, config: ScannerConfig, interval_s: float):
        self.path, self.config, self.interval_s = path, config, interval_s
        self.writes, self.seconds = 0, 0.0
        self.last_write = None  # time.monotonic() when the last write ended
        self._pending, self._closed, self._error = None, False, None
        self._condition = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="checkpoint-writer", daemon=True)
        self._thread.start()

    def offer(self, phantom: Phantom) -> None:
        """Queue ``phantom`` for writing, replacing any phantom not yet written."""
        with self._condition:
            self._pending = phantom
            self._condition.notify()

    def _run(self) -> None:
        while True:
            with self._condition:
                while True:
                    if self._pending is None:
                        if self._closed:
                            return
                        self._condition.wait()
                        continue
                    wait_s = 0.0 if self.last_write is None else \
                        self.last_write + self.interval_s - time.monotonic()
                    if wait_s <= 0 or self._closed:
                        break
                    self._condition.wait(wait_s)
                phantom, self._pending = self._pending, None
            try:
                self._write(phantom)
            except BaseException as exc:  # re-raised by close() in the caller's thread
                with self._condition:
                    self._error, self._closed, self._pending = exc, True, None
                return

    def _write(self, phantom: Phantom) -> None:
        start = time.monotonic()
        phantom.validate(self.config, y_limit_um=CONTRACT_Y_LIMIT_UM, source=str(self.path))
        phantom.save(self.path)
        self.last_write = time.monotonic()
        self.seconds += self.last_write - start
        self.writes += 1

    def write_now(self, phantom: Phantom) -> None:
        """Write ``phantom`` in the caller's thread, before anything else is offered.

        For stage 2's phantom: in the background its write took twice as
        long (0.8–1.1 s against 0.3–0.6 s), the interpreter lock held by
        what the caller imports next (torch, for stage 3).
        """
        if self.writes or self._pending is not None:
            raise RuntimeError("write_now is for the first phantom only")
        self._write(phantom)

    def close(self) -> None:
        """Write the pending phantom now, stop the thread, and raise its error if it had one."""
        with self._condition:
            self._closed = True
            self._condition.notify()
        self._thread.join()
        if self._error is not None:
            raise self._error


class _LazyExactScore:
    """:class:`octcl.host.stage3.loss.ExactScore` of a target, built at its first use.

    Building it imports torch and loads the LPIPS network (about 2 s on two
    cores); the linear regime writes its first phantom without either, and
    only a run with several stage-1 candidates scores before stage 3. Levels
    equal to a grey target's own score 1 on every component without it:
    the metric then compares identical images (MS-SSIM's terms are x/x
    with the same rounding on both sides, LPIPS' feature differences are
    0; ``tests/pipeline/test_invert.py`` checks :class:`ExactScore` gives exactly
    that), so a scan the scanner rendered, inverted exactly, needs no torch.
    """

    def __init__(self, target, config: ScannerConfig):
        from octcl import scorer

        self.target, self._score = target, None
        scan = target_scan(target)
        self.levels = target_levels(scan, config)
        # The metric reads the Struct map from the target's pixels and the maps from its scan: both must be
        # those of its levels for equal levels to mean identical images.
        self.grey = np.array_equal(target_struct_for_metrics(target), scorer.levels_for_metrics(self.levels)) \
            and np.array_equal(scan, target_scan(self.levels))
        self.perfect = {**dict.fromkeys(scorer.COMPONENTS, 1.0), "mean": 1.0}
        self.scores = {}  # sha256 of the levels → their components: each image is scored once
        self.seconds = 0.0  # what the last computed score took (the network's construction apart)

    def built(self):
        if self._score is None:
            from ..stage3.loss import ExactScore

            self._score = ExactScore(self.target)
        return self._score

    def _key(self, levels) -> bytes:
        return hashlib.sha256(np.ascontiguousarray(levels, dtype=np.uint8).tobytes()).digest()

    def _perfect(self, levels) -> bool:
        """Whether ``levels`` are a grey target's own: they score 1 on every component without torch."""
        return self.grey and np.array_equal(levels, self.levels)

    def cost_s(self, levels) -> float:
        """Seconds a call for ``levels`` would take: 0 for an image scored before (or a grey target's own), the
        last computation's time once one ran, else torch's import where it is still to come and
        :data:`SCORER_BUILD_S` (the network, one score)."""
        if self._perfect(levels) or self._key(levels) in self.scores:
            return 0.0
        return self.seconds if self.scores else torch_import_s() + SCORER_BUILD_S

    def __call__(self, levels):
        if self._perfect(levels):
            return dict(self.perfect)
        # One run asks for the same levels' score more than once: the aim step scores the error-diffused
        # image and each aim it keeps, stage 3 scores its input (the last aim, where the start renders it)
        # and the ceiling the error-diffused image again. The score is a function of the levels alone.
        key = self._key(levels)
        if key not in self.scores:
            score = self.built()
            start = time.monotonic()
            self.scores[key] = score(levels)
            self.seconds = time.monotonic() - start
        return dict(self.scores[key])


def _span(name: str, config: ScannerConfig) -> str:
    return f"{name} {config.depth_pixels}x{config.a_scans}"


def write_reserve_s(regime: str, config: ScannerConfig = DEFAULT_CONFIG) -> float:
    """Seconds stage 1 leaves in the linear and tissue regimes, so that the process ends within its budget: the
    decode and first write, then the close, each the longest of those this machine measured last (:data:`SPANS`;
    :data:`LINEAR_WRITE_RESERVE_S` or :data:`TISSUE_WRITE_RESERVE_S`, and :data:`CLOSE_S`, where it measured
    none), and :data:`EXIT_RESERVE_S`."""
    default = LINEAR_WRITE_RESERVE_S if regime == "linear" else TISSUE_WRITE_RESERVE_S
    return (SPANS.longest(_span(f"{regime} first write", config), default)
            + SPANS.longest(_span("close", config), CLOSE_S) + EXIT_RESERVE_S)


def field_budget_s(regime: str, time_budget_s: float, elapsed_s: float, reserve_s: float | None = None,
                   config: ScannerConfig = DEFAULT_CONFIG) -> float:
    """Stage 1's seconds in deadline mode, ``elapsed_s`` of the budget gone (the process's start, the imports,
    the backend's programs).

    Physical regime: :data:`FIELD_BUDGET_FRACTION` of the budget, at most
    :data:`FIELD_BUDGET_CAP_S`. Linear and tissue regimes: all of it but
    ``reserve_s`` (default :func:`write_reserve_s` on ``config``'s grid: the decode, the
    first write and the close as this machine measured them), so that the process
    ends within the budget; a default run's stage 1 ends at its step counts
    long before. At least :data:`MIN_FIELD_BUDGET_S`: a budget shorter than
    the process's fixed costs still gets a phantom, late.
    """
    if regime in ("linear", "tissue"):
        budget = time_budget_s - elapsed_s - (write_reserve_s(regime, config) if reserve_s is None else reserve_s)
    else:
        budget = min(FIELD_BUDGET_FRACTION * time_budget_s, FIELD_BUDGET_CAP_S) - elapsed_s
    return min(max(budget, MIN_FIELD_BUDGET_S), FIELD_BUDGET_CAP_S)


def twin_budget_s(stage_1_left_s: float | None, exit_left_s: float | None) -> float | None:
    """Seconds of the tissue regime's least-norm twin: what stage 1 left of its budget (``stage_1_left_s``), at
    most :data:`TWIN_SHARE` of the seconds left before the run's exit (``exit_left_s``: the rest is the
    decode's and stage 3's), at least :data:`MIN_FIELD_BUDGET_S`; None on a fixed schedule (both None), where
    the twin's iterations alone bound it."""
    if stage_1_left_s is None or exit_left_s is None:
        return None
    return max(min(stage_1_left_s, TWIN_SHARE * exit_left_s), MIN_FIELD_BUDGET_S)


def final_reserve_s(time_budget_s: float) -> float:
    """Seconds of the budget that stage 3 leaves for the last write (:data:`FINAL_RESERVE_S`, less for a short one)."""
    return min(FINAL_RESERVE_S, FINAL_RESERVE_FRACTION * time_budget_s)


def check_regime(regime) -> None:
    """Raise ValueError unless ``regime`` is one of :data:`REGIMES`."""
    if regime not in REGIMES:
        raise ValueError(f"regime must be one of {', '.join(REGIMES)}, got {regime!r}")


def default_schedule(regime: str) -> RefineSchedule:
    """Stage 3's default schedule in a regime: :data:`LINEAR_SCHEDULE`, ``RefineSchedule()`` (physical) or
    :data:`TISSUE_SCHEDULE`."""
    check_regime(regime)
    return {"linear": LINEAR_SCHEDULE, "tissue": TISSUE_SCHEDULE}.get(regime, RefineSchedule())


@dataclass
class _Start:
    """What stages 1–2 hand to stage 3."""

    phantom: Phantom
    schedule: RefineSchedule     # stage 3's, with the regime's energy floor
    field_iterations: int        # stage 1's Adam steps (linear: the first display fit's, as asked)
    clock_steps: int             # of them, steps whose course the clock set
    threads: int | None          # FFT threads of stage 1
    field_loss: float | None     # stage 1's last loss (physical regime)
    seconds: dict                # {"field": s, "decode": s}, and "twin": s in the tissue regime
    candidates: list | None = None  # the linear regime's stage-1 candidates (LinearStart.candidates)
    aim: np.ndarray | None = None   # the levels stage 1 aimed at (linear regime), for stage 3's stop
    decode: dict | None = None      # what the tissue decode chose (TissueDecode.summary)


def _physical_start(scan, config, schedule, iterations, field_schedule, budget_s, threads, seed, step, tell,
                    exact_score, field_backend, exit_left=None) -> _Start:
    """Stages 1–2 of the published pipeline: :func:`~octcl.host.stage1.display.fit_field`, then
    :func:`~octcl.host.stage2.capped.decode_field` (``exit_left``, the seconds left before the run's exit, is the
    tissue regime's: the other starts take the same arguments)."""
    from ..stage2.capped import decode_field
    from ..stage1.display import fit_field

    fit = fit_field(scan, config, iterations=iterations, time_budget_s=budget_s, threads=threads, progress=step,
                    backend=field_backend)
    tell("decode", 0, 1)
    start = time.monotonic()
    phantom = decode_field(fit.field, config, max_scatterers=TARGET_ROWS, seed=seed)
    return _Start(phantom, schedule, fit.iterations, fit.clock_steps, fit.threads,
                  float(fit.losses[-1]) if fit.losses.size else None,
                  {"field": fit.seconds, "decode": time.monotonic() - start})


def _linear_start(scan, config, schedule, iterations, field_schedule, budget_s, threads, seed, step, tell,
                  exact_score, field_backend, exit_left=None, tissue: bool = False) -> _Start:
    """Stages 1–2 in the linear regime (:mod:`octcl.host.stage1.projections`); draws nothing at random.

    The aim is :func:`~octcl.host.stage1.ceiling.aimed_levels` of the target. Stage 1
    is :func:`~octcl.host.stage1.start.linear_start` of ``field_schedule`` or, by
    default, :func:`~octcl.host.stage1.solve.default_schedules` of
    ``iterations`` display steps (a display fit, projections and the hinge
    fit towards the aimed levels, then the aim's rounds, none in the tissue regime; a half-length candidate
    only where that one falls short); stage 2 :func:`~octcl.host.stage2.exact.decode_exact` or, with
    ``tissue`` (the tissue regime), :func:`~octcl.host.stage2.tissue.decode_tissue` of the field's
    least-norm twin (:func:`_tissue_decode`, within :func:`twin_budget_s` of what stage 1 left of ``budget_s``
    and of ``exit_left()``, the seconds left before the run's exit; None on a fixed schedule). The
    aim goes on to stage 3, which does nothing where the start renders it.
    """
    from ..stage1.solve import DEFAULT_AIM_ROUNDS, default_schedules
    from ..stage1.start import linear_start
    from ..stage2.exact import ENERGY_FLOOR_PCT, decode_exact

    aim = aimed_levels(target_levels(scan, config))
    # The tissue regime's stage 1 has no aim rounds (its aim is the error-diffused one): they gain a few 1e−6
    # of score at the scanner's ceiling, where the tissue regime's stage 3 ends 1e−4 and more below it, and
    # they took 3.3–4.9 s on two first-generation Zen cores. Without them, --regime tissue --time-budget 30
    # scored 0.99853, 0.99474, 0.99588, 0.99547 on orange.png and plain_skin_0–2 against 0.99779, 0.99346,
    # 0.99091, 0.99033, with 51–55 stage-3 steps against 31–41 (docs/benchmarks.md).
    rounds = 0 if tissue else DEFAULT_AIM_ROUNDS
    schedules = default_schedules(iterations, rounds) if field_schedule is None else (field_schedule,)
    found = linear_start(scan, lambda levels: exact_score(levels)["mean"], config, schedules=schedules,
                         time_budget_s=budget_s, threads=threads,
                         progress=lambda taken, planned: step(taken, planned, None), aim=aim, backend=field_backend)
    seconds = {"field": found.seconds}
    # The decode's depth DFTs on the run's threads (the same phantom at any count): 3 per row offset a pass.
    workers = threads or available_cores()
    if tissue:
        twin_s = twin_budget_s(None if budget_s is None else budget_s - found.seconds,
                               None if exit_left is None else exit_left())
        phantom, decode = _tissue_decode(found, config, field_backend, twin_s, tell, seconds, workers)
    else:
        tell("decode", 0, 1)
        start = time.monotonic()
        phantom, decode = decode_exact(found.field, config, workers=workers), None
        seconds["decode"] = time.monotonic() - start
        schedule = dataclasses.replace(schedule,
                                       min_log_energy=min(schedule.min_log_energy, math.log(ENERGY_FLOOR_PCT)))
    # field_iterations: the first candidate's display steps, from which the others follow (the reproduce options).
    return _Start(phantom, schedule, iterations if field_schedule is None else field_schedule.display_iterations,
                  found.clock_steps, found.threads, None, seconds, found.candidates, found.aim, decode)


def _tissue_decode(found, config, backend, twin_s, tell, seconds: dict, workers: int) -> tuple[Phantom, dict]:
    """Stage 2 of the tissue regime: stage 1's field taken to its least-norm twin
    (:func:`~octcl.host.stage1.start.least_norm_twin`, within ``twin_s`` seconds: :func:`twin_budget_s`), then
    :func:`~octcl.host.stage2.tissue.decode_tissue` of it. Returns the phantom and the decode's choices with the
    twin's iterations and share at the aim; ``seconds`` gets ``twin`` and ``decode``; ``workers``: the decode's
    FFT threads."""
    from ..stage1.start import least_norm_twin
    from ..stage2.tissue import decode_tissue

    tell("twin", 0, 1)
    twin = least_norm_twin(found.field, found.aim, backend, time_budget_s=twin_s)
    seconds["twin"] = twin.seconds
    tell("decode", 0, 1)
    start = time.monotonic()
    decoded = decode_tissue(twin.field, config, workers=workers)
    seconds["decode"] = time.monotonic() - start
    return decoded.phantom, dict(decoded.summary(), twin_iterations=twin.iterations, twin_identical=twin.identical)


_STARTS = {"linear": _linear_start, "physical": _physical_start,
           "tissue": functools.partial(_linear_start, tissue=True)}


def invert(target, output_path, time_budget_s: float = 600.0, seed: int = 0, report_path=None,
           progress=None, config: ScannerConfig = DEFAULT_CONFIG,
           schedule: RefineSchedule | None = None, iterations: int | None = None,
           field_iterations: int | None = None, threads: int | None = None,
           name: str | None = None, target_score: float | None = None,
           regime: str = REGIMES[0], started: float | None = None,
           field_schedule=None, backend: str = BACKENDS[0]) -> InvertResult:
    """Invert a target B-scan into a phantom file.

    Parameters
    ----------
    target : str, Path or ndarray of uint8
        The target: an 8-bit (Nz × Nx) grey, RGB or RGBA PNG, read once
        (:func:`octcl.host.pipeline.target.read_target`), or an array in either form
        of :mod:`octcl.host.pipeline.target`: (Nz, Nx) levels of a grey B-scan as the
        scanner saves it, or (Nz, Nx, C) PNG pixels. ``read_target(path)``
        gives the array that inverts exactly as ``path`` does.
    output_path : str or Path
        The phantom text file (``x y z E`` rows, ≤ 295,000 of them, all
        within the task contract: |x| ≤ Xmax/2, |y| ≤ 3 µm, 0 ≤ z ≤ Nz·Δz,
        0 ≤ E ≤ 100).
    time_budget_s : float
        Wall-clock budget in seconds for the whole inversion, from
        ``started``, reading the target and compiling the kernels included:
        the phantom is written within it. Scoring the written phantom for
        the result (and the ceiling's score) may end later, as stage 3
        does nothing after the deadline. Without ``iterations``
        (deadline mode) stage 1 gets min(8 % of it, 45 s), stage 2 runs
        once and stage 3 gets the rest, so how far each stage gets depends
        on the machine's speed and load (linear regime: stage 1 gets all of
        it but what has gone and what the decode, the first write and the
        close took on this machine, :func:`write_reserve_s`). With ``iterations`` it is only a
        ceiling: :class:`TimeBudgetExceeded` if the fixed schedule has not
        ended when stage 3 would have to stop.
    seed : int
        Seed of stage 2's random choices (the scatterers' elevations).
    report_path : str or Path, optional
        JSON report: score trace against wall time per stage, final
        components, settings, seed, timings and peak memory.
    progress : callable, optional
        ``progress(InvertProgress)`` at each step of every stage and once at
        the end (stage ``done``).
    config : ScannerConfig
    schedule : RefineSchedule, optional
        Stage 3's schedule (cut short by the budget in deadline mode);
        default :func:`default_schedule` of the regime.
    iterations : int, optional
        Fixed-schedule mode: stage 1 runs ``field_iterations`` steps and
        stage 3 the first ``iterations`` Adam steps of ``schedule``
        (:meth:`RefineSchedule.truncated`), whatever the clock says, at
        ``threads`` CPU threads (default :data:`FIXED_THREADS`). With the
        same target, seed, iterations, field_iterations, threads, octcl
        version and device the output file is the same, byte for byte
        (``docs/reproducibility.md``). A deadline run's result says how to
        run its schedule this way (:attr:`InvertResult.reproduce`).
    field_iterations : int, optional
        Stage 1's steps (in deadline mode: at most, within its time share);
        default :data:`FIELD_ITERATIONS` of the regime.
    threads : int, optional
        CPU threads for the whole run (stage 1's FFTs, stage 3's torch). In deadline mode it is
        otherwise chosen by timing steps, which follows the machine's load.
    name : str, optional
        The target's name in messages and the result; default: the path, or
        ``"target"`` for an array.
    target_score : float, optional
        End stage 3 as soon as an exact evaluation reaches this score.
    regime : str
        Stages 1–2 (:data:`REGIMES`, module docstring): ``linear`` (default)
        or ``physical``. In the linear regime the seed changes nothing.
    field_schedule : str or FieldSchedule, optional
        The linear regime's stage 1 as named steps
        (:class:`octcl.host.stage1.solve.FieldSchedule`, e.g.
        ``"display:150,project:100,hinge:200"``), one candidate, in place of
        the default candidates of ``field_iterations`` display steps.
    backend : str
        Where stage 1 runs (:data:`BACKENDS`): ``opencl`` (default), its
        steps as kernels on the device that renders (``OCTCL_DEVICE`` or
        octcl's choice, :mod:`octcl.device.runtime`), or ``numpy``, the host
        reference. Stage 3 runs on the device either way.
    started : float, optional
        ``time.monotonic()`` at which the budget began; default: the call.
        ``octcl invert`` passes its process's start, so that the budget
        counts the interpreter's start and the imports too.

    Returns
    -------
    InvertResult

    Raises
    ------
    ImageFormatError
        The target is not a usable B-scan (:func:`octcl.host.pipeline.target.check_target`).
    OutputError
        ``output_path`` or ``report_path`` cannot be written (:func:`octcl._io.check_output_path`),
        checked before the work starts.
    ValueError
        A budget that is not a positive number, iterations beyond the
        schedule, a thread or stage-1 iteration count below 1, a target
        score outside (0, 1].
    TimeBudgetExceeded
        A fixed schedule did not end within the budget; the output then
        holds the best phantom scored so far (or nothing, if the budget ran
        out before stage 2), not the schedule's result.
    """
    started = time.monotonic() if started is None else started
    plan = _Plan.checked(time_budget_s, regime, backend, schedule, iterations, field_iterations, field_schedule,
                         threads, target_score)
    # A bad output path fails now, not after the budget is spent.
    output_path = check_output_path(output_path)
    if report_path is not None:
        check_output_path(report_path)
    if isinstance(target, (str, os.PathLike)):
        name = str(target) if name is None else name
        target = read_target(target, config)
    else:
        name = "target" if name is None else name
        target = check_target(target, config, name)
    run = _Run(plan, target, config, output_path, started, time_budget_s, seed, progress)
    try:
        first = run.start()
        run.write_first(first.phantom)
        result = run.refine(first, target_score)
    except TimeBudgetExceeded as exc:
        holds = f"{output_path} holds the best phantom scored so far, not the schedule's result" \
            if run.writer is not None and run.writer.writes else f"nothing was written to {output_path}"
        raise TimeBudgetExceeded(
            f"{name}: a fixed schedule ({plan.field_iterations} + {plan.schedule.total_iterations} iterations) did "
            f"not fit the time budget of {time_budget_s:g} s ({exc}); give a larger budget. {holds}") from None
    finally:
        if run.writer is not None:
            run.writer.close()  # writes the best phantom if the interval held it back
    outcome, settings = run.outcome(name, first, result)
    if report_path is not None:
        contents = {**outcome.as_dict(), "initial_components": result.initial_components,
                    "settings": {**settings, "config": dataclasses.asdict(config), "target_score": target_score},
                    "refine_timings_s": result.timings_s, "refine_cpu_s": result.cpu_s, "trace": run.trace}
        with atomic_write(report_path, "w") as handle:
            json.dump(contents, handle, indent=1, default=float)
    return outcome


@dataclass(frozen=True)
class _Plan:
    """What :func:`invert` was asked to run, checked and completed with its defaults."""

    regime: str
    backend: str
    schedule: RefineSchedule      # stage 3's, truncated to ``iterations`` in a fixed schedule
    field_iterations: int
    field_schedule: object        # FieldSchedule or None
    threads: int | None
    fixed: bool                   # ``iterations`` given: no decision from the clock

    @classmethod
    def checked(cls, time_budget_s, regime, backend, schedule, iterations, field_iterations, field_schedule, threads,
                target_score) -> "_Plan":
        """Every argument checked before any work (:func:`invert`'s Raises)."""
        if not (isinstance(time_budget_s, (int, float)) and time_budget_s > 0 and math.isfinite(time_budget_s)):
            raise ValueError(f"time_budget_s must be a positive number of seconds, got {time_budget_s!r}")
        for label, count in (("threads", threads), ("field_iterations", field_iterations)):
            if count is not None and not (isinstance(count, int) and count >= 1):
                raise ValueError(f"{label} must be a whole number ≥ 1, got {count!r}")
        check_regime(regime)
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
        if field_schedule is not None:
            from ..stage1.solve import FieldSchedule

            if regime == "physical":
                raise ValueError("a stage-1 schedule of named steps is the linear and tissue regimes'; the physical "
                                 "regime's stage 1 is field_iterations display steps")
            field_schedule = field_schedule if isinstance(field_schedule, FieldSchedule) \
                else FieldSchedule.parse(field_schedule)
        schedule = default_schedule(regime) if schedule is None else schedule
        check_target_score(target_score)
        fixed = iterations is not None
        if fixed:
            schedule = schedule.truncated(iterations)
            threads = FIXED_THREADS if threads is None else threads
        return cls(regime, backend, schedule, FIELD_ITERATIONS[regime] if field_iterations is None else field_iterations,
                   field_schedule, threads, fixed)

    def reproduce(self, seed: int, iterations: int, field_iterations: int) -> str:
        """The options that run this schedule again (:attr:`InvertResult.reproduce`)."""
        return (f"--regime {self.regime} --backend {self.backend} --seed {seed} --iterations {iterations} "
                + (f"--field-iterations {field_iterations} " if self.field_schedule is None
                   else f"--field-schedule {self.field_schedule} ")
                + f"--threads {FIXED_THREADS if self.threads is None else self.threads}")


class _Run:
    """One :func:`invert` run's state: its clock, progress, output, timings and trace, and its stages as steps.

    In a fixed schedule the budget is only a safety ceiling, checked at
    every step; in deadline mode the stages fit themselves inside it.
    """

    def __init__(self, plan: _Plan, target, config: ScannerConfig, output_path, started: float, time_budget_s: float,
                 seed: int, progress):
        self.plan, self.target, self.config, self.output_path = plan, target, config, output_path
        self.started, self.time_budget_s, self.seed = started, time_budget_s, seed
        self.deadline = started + time_budget_s - final_reserve_s(time_budget_s)
        self.tell = _ProgressReporter(progress, started, self.deadline)
        self.field_budget = None  # set where stage 1 begins (start)
        self.first_write_s = None
        self.ceiling = RefineClock(None, self.deadline if plan.fixed else None)
        self.writer, self.seconds, self.trace, self.offset = None, {}, [], 0.0
        self.exact_score = _LazyExactScore(target, config)
        self.scanner = None  # stage 3's kernels, begun on a thread once stage 1's programs are built (start)
        self.prefetch_torch()

    def prefetch_torch(self) -> None:
        """Begin torch's import on a thread beside stage 1 where the run will need it
        (:func:`octcl.torch_import.import_torch_in_background`), unless less than :data:`PREFETCH_TORCH_MIN_S` are
        left before :attr:`exit_by`. A grey scan the scanner could have written, in the linear regime, has nothing
        to aim and is scored without torch (:class:`_LazyExactScore`). Stage 3's scanner kernels are begun beside
        stage 1 as well, once its own programs are built (:meth:`start`).

        Measured on two EPYC cores (``scripts/bench_versions.py``, docs/benchmarks.md): the default run's median
        wall time over orange.png and six plainly quantised skin renderings fell from 6.22 s to 5.56 s, with the
        same scores; the import itself took 1.5–1.6 s beside stage 1 against 1.0–1.2 s alone. On an H200 machine,
        where torch's import takes 2.9–5.3 s, orange.png's median run went from 7.37 s to 6.86 s, and the first
        run on a cold cache no longer compiles the scanner (5.9 s there) after the write.
        """
        exact = self.exact_score
        needed = self.plan.regime != "linear" or not (exact.grey and WRITABLE[exact.levels].all())
        if needed and (self.exit_by is None or time.monotonic() + PREFETCH_TORCH_MIN_S <= self.exit_by):
            import_torch_in_background()

    def elapsed(self) -> float:
        return time.monotonic() - self.started

    def start(self) -> _Start:
        """Stages 1–2 of the plan's regime (:data:`_STARTS`), stage 1 on the plan's backend."""
        from octcl.device.scanner import scanner_in_background

        plan = self.plan

        def field_step(iteration, steps, loss):
            self.ceiling.check_ceiling(f"in stage 1 after {iteration} of {steps} iterations")
            self.tell("field", iteration, steps)

        self.tell("field", 0, 0)
        field_backend = make_backend(plan.backend, self.config, plan.threads)
        # Stage 3's scanner kernels on a thread beside stage 1 (a read of pyopencl's cache, or a machine's first
        # compile), begun after stage 1's own programs: builds are serialised within a process
        # (octcl.device.programs.build), and a first compile begun before them held stage 1's back. On two CPU
        # cores, where the compile and stage 1 share the cores, either order wrote orange.png's phantom at
        # 16.7–17.8 s on a cold cache (docs/benchmarks.md); on a GPU stage 1 no longer waits for the compile.
        self.scanner = scanner_in_background(self.config)
        # After the backend's programs are built: what they took is gone from the budget too.
        self.field_budget = None if plan.fixed else field_budget_s(plan.regime, self.time_budget_s, self.elapsed(),
                                                                   config=self.config)
        first = _STARTS[plan.regime](target_scan(self.target), self.config, plan.schedule, plan.field_iterations,
                                     plan.field_schedule, self.field_budget, plan.threads, self.seed, field_step,
                                     self.tell, self.exact_score, field_backend,
                                     exit_left=None if plan.fixed else lambda: self.exit_by - time.monotonic())
        self.seconds.update(first.seconds)
        self.trace.append({"time_s": self.elapsed(), "stage": "field", "iteration": first.field_iterations,
                           "loss": first.field_loss, "score": None})
        return first

    def write_first(self, phantom) -> None:
        """The first phantom into the output, at once: from here on the output always holds a complete one."""
        self.writer = _CheckpointWriter(self.output_path, self.config, CHECKPOINT_INTERVAL_S)
        self.writer.write_now(phantom)
        self.first_write_s = self.writer.seconds

    def refine(self, first: _Start, target_score):
        """Stage 3 (:func:`octcl.host.stage3.refine.refine`) from the first phantom, each improvement offered to the writer."""
        self.tell("setup", 0, 1)
        start = time.monotonic()
        kernels = self.scanner.result()
        self.seconds["setup"] = time.monotonic() - start
        self.ceiling.check_ceiling("before stage 3")
        self.offset = self.elapsed()
        fixed = self.plan.fixed
        if not fixed:  # what follows stage 3 is measured by now: keep back that, not the budget's share
            self.deadline = max(self.deadline, self.exit_by - AFTER_STAGE_3_FACTOR * self.after_stage_3_s())
            self.tell.end = self.deadline
        return refine(first.phantom, self.target, first.schedule, deadline=None if fixed else self.deadline,
                      kernels=kernels, config=self.config, progress=self.tell.refine, exact_score=self.exact_score,
                      on_improvement=lambda improved, components: self.writer.offer(improved),
                      ceiling=self.ceiling.ceiling if fixed else None, threads=self.plan.threads,
                      target_score=target_score, aim=first.aim,
                      score_by=self.exit_by)

    def after_stage_3_s(self) -> float:
        """Seconds of what follows stage 3, by this run's and this machine's measures: a write (this run's
        first), the ceiling's score where not computed yet (:meth:`_LazyExactScore.cost_s`) and, in the tissue
        regime, the figures (:meth:`tissue_figures_s`)."""
        image = ceiling_image(self.exact_score.levels)
        seconds = self.first_write_s + (0.0 if image is None else self.exact_score.cost_s(image))
        return seconds + (self.tissue_figures_s() if self.plan.regime == "tissue" else 0.0)

    def tissue_figures_s(self) -> float:
        """Seconds :meth:`tissue_figures` is taken to need: the longest this machine measured last (:data:`SPANS`),
        else :data:`TISSUE_FIGURES_S`."""
        return SPANS.longest(_span("tissue figures", self.config), TISSUE_FIGURES_S)

    @property
    def exit_by(self) -> float | None:
        """In deadline mode, the ``time.monotonic()`` by which what follows the last write must end: the budget
        less :data:`EXIT_RESERVE_S` for the report, the summary and the exit (a budget is the process's)."""
        return None if self.plan.fixed else self.started + self.time_budget_s - EXIT_RESERVE_S

    def fits_before_exit(self, seconds: float) -> bool:
        """Whether work of ``seconds`` started now ends by :attr:`exit_by` (always, on a fixed schedule)."""
        return self.exit_by is None or time.monotonic() + seconds <= self.exit_by

    def ceiling_score(self, image) -> float | None:
        """The exact score of one of the ceiling's images; None where it would not end by :attr:`exit_by`."""
        return self.exact_score(image)["mean"] if self.fits_before_exit(self.exact_score.cost_s(image)) else None

    def tissue_figures(self, phantom, levels) -> tuple[dict | None, np.ndarray | None]:
        """:func:`octcl.tissue.tissue_figures` of the written phantom against the target's levels, and its
        attenuation map, from one transmission map; None for both where they would not end by :attr:`exit_by`
        (:meth:`tissue_figures_s`)."""
        from octcl.tissue import attenuation_map, tissue_figures, transmission_map

        if not self.fits_before_exit(self.tissue_figures_s()):
            return None, None
        start = time.monotonic()
        transmission = transmission_map(phantom, self.config)
        figures = (tissue_figures(phantom, levels, self.config, transmission),
                   attenuation_map(transmission, self.config))
        SPANS.record(_span("tissue figures", self.config), time.monotonic() - start)
        return figures

    def record_spans(self, result) -> None:
        """Keep this run's decode and first write, and its close where stage 3 took no step, for the next
        run's clock (:data:`SPANS`, :func:`write_reserve_s`)."""
        SPANS.record(_span(f"{self.plan.regime} first write", self.config),
                     self.seconds.get("decode", 0.0) + self.first_write_s)
        if result.iterations == 0:
            SPANS.record(_span("close", self.config), self.seconds["refine"] - result.timings_s.get("exact_score", 0.0))

    def outcome(self, name: str, first: _Start, result) -> tuple[InvertResult, dict]:
        """The result and the report's settings, after the last write.

        The ceiling of the target (the error-diffused image's exact score:
        none for a target the scanner could have written, and none again
        where the run has scored that image already, as the aim step does)
        and where the phantom stands under it (the levels its score was
        computed from) come after the last write; in deadline mode a ceiling
        score that would end past the budget is left out (None, and the
        summary says so).
        """
        plan, seconds, writer = self.plan, self.seconds, self.writer
        seconds["refine"] = self.elapsed() - self.offset
        seconds["checkpoint_writes"] = writer.seconds
        seconds["written"] = writer.last_write - self.started
        self.trace += [{**entry, "time_s": entry["time_s"] + self.offset} for entry in result.trace]
        seconds["total"] = self.elapsed()
        self.record_spans(result)
        self.tell("done", result.iterations, plan.schedule.total_iterations, done=True)
        levels, rendered = self.exact_score.levels, result.levels
        ceiling = measure_ceiling(levels, self.ceiling_score)
        tissue, attenuation = self.tissue_figures(result.phantom, levels) if plan.regime == "tissue" else (None, None)
        outcome = InvertResult(
            target=name, output=str(self.output_path),
            score=None if result.components is None else result.components["mean"], components=result.components,
            initial_score=None if result.initial_components is None else result.initial_components["mean"],
            scatterers=len(result.phantom), iterations=result.iterations, seconds=seconds,
            checkpoints=writer.writes, peak_memory_mib=peak_memory_mib(),
            stopped_by_deadline=result.stopped_by_deadline, stop_reason=result.stop_reason,
            falls=result.falls, seed=self.seed, field_iterations=first.field_iterations, regime=plan.regime,
            fixed_schedule=plan.fixed, threads=plan.threads,
            reproduce=plan.reproduce(self.seed, result.iterations, first.field_iterations),
            reproducible=first.clock_steps == 0 and not result.stopped_by_deadline,
            ceiling=ceiling.as_dict(), exact_share=float(np.mean(rendered == levels)),
            avoidable_share=float(np.mean(WRITABLE[levels] & (rendered != levels))),
            tissue=tissue, levels=rendered, attenuation_per_mm=attenuation)
        settings = {"time_budget_s": self.time_budget_s, "field_budget_s": self.field_budget,
                    "refine_deadline_s": None if plan.fixed else self.deadline - self.started,
                    "field_iterations_planned": plan.field_iterations, "field_threads": first.threads,
                    "field_backend": plan.backend, "field_clock_steps": first.clock_steps,
                    "field_candidates": first.candidates, "tissue_decode": first.decode,
                    "refine_threads": result.torch_threads,
                    "schedule": dataclasses.asdict(first.schedule), "checkpoint_interval_s": CHECKPOINT_INTERVAL_S}
        return outcome, settings


__all__ = ["BACKENDS", "CHECKPOINT_INTERVAL_S", "FIELD_ITERATIONS", "FIXED_THREADS", "InvertProgress", "InvertResult",
           "LINEAR_SCHEDULE", "REGIMES", "check_regime", "default_schedule",
           "TimeBudgetExceeded", "invert", "peak_memory_mib", "read_target"]
