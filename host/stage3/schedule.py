"""What stage 3 runs, as data: its phases, restarts, stopping rule and loss weights.

:class:`RefineSchedule` is read by :func:`octcl.host.stage3.refine.refine`, which
runs it; the schedule itself imports no torch, so that choosing one
(``octcl invert``'s options, :mod:`octcl.host.pipeline.invert`'s defaults) costs
nothing until a run needs the loss.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from .hinge import check_relative_exponent

#: Largest energy of the task contract, in % (u ≤ ln 100).
MAX_ENERGY_PCT = 100.0
#: The default :attr:`RefineSchedule.min_gain`: the smallest gain of exact score that counts as progress.
MIN_GAIN = 1e-5
#: Stopping rules by name (:meth:`RefineSchedule.with_stop_rule`), the default first.
STOP_RULES = ("restarts", "stall", "none")
#: What a fall of the main run (:attr:`RefineSchedule.max_falls`) multiplies its learning rates by.
FALL_LR_FACTOR = 0.5
#: Maps each LPIPS term compares (the key of :class:`LossWeights` → map name).
LPIPS_TERMS = {"struct_lpips": "Struct", "oac_lpips": "OAC", "sc_lpips": "SC", "rsc_lpips": "RSC"}
#: What a phase's loss computes (:attr:`Phase.terms`): every weighted term; all but the LPIPS ones (about a third
#: of the cost); the pixel term alone (no maps, no network: a step of the tissue regime took 0.13–0.14 s where the
#: full loss's took 0.50–0.56 s, docs/benchmarks.md "Stage 3 in the tissue regime"); the level term alone (as
#: cheap; :mod:`octcl.host.stage3.loss`); or no loss of :mod:`~octcl.host.stage3.loss` at all but the hinge of each
#: pixel's magnitude on its aimed level's interval, by L-BFGS instead of Adam (:data:`HINGE`).
PHASE_TERMS = ("all", "no_lpips", "pixel", "level", "hinge")
#: The terms of a phase of L-BFGS iterations on the levels' hinge (:mod:`octcl.host.stage3.hinge`): its steps have
#: no learning rates (both 0) and compare the rendering with the aimed levels.
HINGE = "hinge"
#: The phases whose loss is one term alone, compared with the aimed levels (:meth:`LossWeights.for_terms`).
SINGLE_TERM_PHASES = ("pixel", "level")


def _check_terms(terms) -> None:
    if terms not in PHASE_TERMS:
        raise ValueError(f"terms must be one of {', '.join(PHASE_TERMS)}, got {terms!r}")


@dataclass(frozen=True)
class LossWeights:
    """Weights of the loss terms (see the module docstring); 0 skips a term.

    The defaults are the published method's weights; ``level`` (0 unless
    set) is octcl's, the term of a ``level`` phase (:meth:`for_terms`). LPIPS is most of the
    loss's time (one 256×512 image through AlexNet and back per term):
    0.69–0.89 s a refinement step for the full loss on two cores, 0.32–0.36 s
    with OAC's LPIPS only and 0.16–0.20 s without LPIPS (before AlexNet ran
    with oneDNN, :class:`DisplayLoss`); the cheaper losses
    reached lower scores per second on three of four scans
    (``scripts/bench_refine.py``, docs/benchmarks.md).
    """

    pixel: float = 1.0
    level: float = 0.0
    sc_l1: float = 0.1
    oac_l1: float = 1.0
    oac_lpips: float = 0.4
    oac_msssim: float = 1.0
    struct_msssim: float = 1.2
    struct_lpips: float = 0.01
    sc_lpips: float = 0.05
    rsc_lpips: float = 0.05

    def __post_init__(self):
        for weight in dataclasses.fields(self):
            value = getattr(self, weight.name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"loss weight {weight.name} must be finite and ≥ 0, got {value!r}")
        if not any(dataclasses.astuple(self)):
            raise ValueError("at least one loss weight must be positive")

    def without_lpips(self) -> "LossWeights":
        """The same weights with every LPIPS term off (the cheap loss)."""
        return dataclasses.replace(self, **{name: 0.0 for name in LPIPS_TERMS})

    def for_terms(self, terms: str) -> "LossWeights":
        """The weights a phase of :attr:`Phase.terms` ``terms`` uses: these, :meth:`without_lpips`, or the pixel
        or the level term alone at weight 1 (alone, its weight only scales the gradient, which Adam's steps
        ignore)."""
        _check_terms(terms)
        if terms == HINGE:
            raise ValueError("a hinge phase has no loss weights: it fits the levels (octcl.host.stage3.hinge)")
        if terms in SINGLE_TERM_PHASES:
            return LossWeights(**{weight.name: float(weight.name == terms) for weight in dataclasses.fields(self)})
        return self if terms == "all" else self.without_lpips()


@dataclass(frozen=True)
class Phase:
    """A run of Adam iterations at fixed learning rates, or of L-BFGS iterations on the levels' hinge.

    Attributes
    ----------
    iterations : int
        Adam steps (L-BFGS iterations in a :data:`HINGE` phase).
    lr_z_um : float
        Step length of the depths, in µm.
    lr_u : float
        Step length of u = ln E (dimensionless).
    terms : str
        Which of the loss's terms it computes (:data:`PHASE_TERMS`, :meth:`LossWeights.for_terms`): ``all``,
        ``no_lpips``, ``pixel`` or ``level``; ``hinge``: L-BFGS on the levels' hinge (:data:`HINGE`), both rates 0.
    relative_exponent : float
        A hinge phase's γ in [0, 1]: its loss weighs each pixel's distance from its interval divided by
        the interval's upper bound to the power γ (:class:`octcl.host.stage3.hinge.LevelHinge`): 0 in absolute
        magnitude, 1 relative to the pixel's own. 0 for the other phases.
    patience : int or None
        An Adam phase ends early at a checkpoint where the best exact score has gained less than the
        schedule's ``min_gain`` over the last ``patience`` checkpoints (of its run, this phase's or the ones
        before), and its run (the main run, or a restart) goes on with its next phase from where it is (from
        the best phantom where that checkpoint fell). None: the phase runs its length. Off without adaptive
        stopping (``min_gain`` None); a hinge phase has its own end.
    """

    iterations: int
    lr_z_um: float
    lr_u: float
    terms: str = "all"
    relative_exponent: float = 0.0
    patience: int | None = None

    def __post_init__(self):
        if self.iterations < 0:
            raise ValueError(f"iterations must be ≥ 0, got {self.iterations}")
        _check_terms(self.terms)
        if not (self.lr_z_um >= 0 and self.lr_u >= 0):
            raise ValueError(f"learning rates must be ≥ 0, got {self.lr_z_um}, {self.lr_u}")
        if self.terms == HINGE and (self.lr_z_um or self.lr_u):
            raise ValueError(f"a hinge phase takes L-BFGS steps, without learning rates: give 0 and 0, got "
                             f"{self.lr_z_um}, {self.lr_u}")
        check_relative_exponent(self.relative_exponent)
        if self.patience is not None and not (isinstance(self.patience, int) and self.patience >= 1):
            raise ValueError(f"a phase's patience must be a whole number ≥ 1 or None, got {self.patience!r}")
        if self.patience is not None and self.terms == HINGE:
            raise ValueError("a hinge phase ends where L-BFGS does: it takes no patience")
        if self.relative_exponent and self.terms != HINGE:
            raise ValueError(f"relative_exponent weighs a hinge phase's pixels; a {self.terms!r} phase has none, got "
                             f"{self.relative_exponent}")

    @property
    def lpips(self) -> bool:
        """Whether the phase's loss has its LPIPS terms."""
        return self.terms == "all"


@dataclass(frozen=True)
class RefineSchedule:
    """What stage 3 runs, in order, until its iterations or the deadline run out.

    Attributes
    ----------
    phases : tuple of Phase
        The main run: one Adam optimiser whose learning rates and loss change
        from phase to phase (its moments carry over). The default, 20
        iterations at (lr_z_um, lr_u) = (0.002, 0.05), 140 at (0.002, 0.02),
        120 at (0.0005, 0.005), then two restarts of 60, follows the
        measurements in the module docstring; on two CPU cores a 600 s
        inversion reaches 300–600 iterations depending on the load.
    restarts : tuple of Phase
        Each restarts Adam (zero moments) from the best phantom so far and
        keeps the best of that parent and its checkpoints at half its
        iterations and at its end.
    score_every : int
        Iterations between exact evaluations in the main run (its last
        iterate is always evaluated).
    beta1, beta2, epsilon : float
        Adam's moment decay rates and the guard of its denominator.
        Gradients of dim scatterers reach 1e−14 (the loss is a mean over
        131,072 pixels and ∂|A|/∂u ∝ a_j), so ε is far below them, leaving
        every scatterer its full step. On orange.png the choice mattered
        little: 0.99847 with ε = 1e−8 and 0.99838 with 1e−20 after 40
        iterations at lr 0.01 / 0.02 (one run each).
    min_log_energy : float
        Floor of u = ln E, so E never reaches 0 (u = −∞) and a dimmed
        scatterer keeps a gradient (∂/∂u ∝ a_j). Stage 2 scales its phantom
        so that shadowing is negligible, which puts the median E near 1e−4 %
        and the dimmest decoded scatterers near 1e−11 %; the default 1e−20 %
        (a = 1e−11, 100 dB below them and far above float32's smallest
        normal number) changes no rendering.
    loss_weights : LossWeights
        Weights of the loss terms (the LPIPS ones apply in ``lpips`` phases).
    max_iterations : int, optional
        Stop after this many Adam steps, restarts included (:meth:`truncated`).
    min_gain : float or None
        Adaptive stopping: refinement ends once a restart has gained less
        than ``min_gain`` over its parent (the best score before it), and
        while each gains, the last restart is repeated until the schedule's
        iterations are spent. None: every restart runs, once
        (:meth:`fixed_length`, the schedule before adaptive stopping).
    restart_patience : int
        With ``min_gain``, how many restarts in a row are judged together:
        the refinement ends once the last ``restart_patience`` restarts
        together gained less than ``min_gain`` over the best score before the
        first of them. 1 (the default): the first restart that gains less
        ends it.
    patience : int or None
        With ``min_gain``, the main run also ends (skipping the rest of its
        phases; the restarts begin from the best phantom) once the best
        exact score has gained less than ``min_gain`` over its last
        ``patience`` checkpoints. Off by default: on the development set it
        cost up to 2.3e−4 of score (module docstring).
    lpips_every : int
        In ``lpips`` phases, the LPIPS terms' gradient is computed on every
        ``lpips_every``-th step of a run (and its first, and the first after
        a phase without LPIPS) and reused on the steps between
        (:class:`octcl.host.stage3.loss.DisplayLoss`, ``lpips="keep"``/``"reuse"``);
        the other terms are computed on every step. 1: LPIPS on every step,
        the default: with 2 or 3, the score fell on every reusing step and
        ended lower on every scan of the development set, early and late in
        the schedule, for 0.2–0.6 s less a step (``scripts/bench_refine.py``,
        docs/benchmarks.md).
    max_falls : int
        The main run goes back when it falls: a checkpoint scoring below
        max(s₀, s_best − ``fall_tolerance``), s₀ the score the run started
        from and s_best the best so far, puts the best phantom back as the
        iterate, with fresh Adam moments and the learning rates of the rest
        of the main run times :data:`FALL_LR_FACTOR`; at most ``max_falls``
        times, then the run goes on from where it is (0: never). Restarts
        already begin from the best phantom and keep it, so only the main
        run is guarded. On a run that gains, nothing changes: its
        checkpoints stay above s₀ and within the tolerance of its best.
    fall_tolerance : float
        How far below the best a checkpoint may score before the main run
        has fallen. Along the main run the iterate's exact score moves by
        ±1e−4 to ±4e−4 between checkpoints while its best keeps rising (module
        docstring), so the default 1e−3 is 2.5 times the largest such move.
    hinge_anchor_weight : float
        The anchor pixel's weight in ``hinge`` phases' loss
        (:class:`octcl.host.stage3.hinge.LevelHinge`), every other pixel's
        being 1. A weight of 1000 took away the fall of the exact score
        that a hinge phase begins with on a skin and slowed orange.png
        (docs/benchmarks.md, "Where the hinge loses time"). The default,
        1, is the tissue regime's too: at 100 its 30 s runs scored higher
        and its default runs on skins lower.

    These decisions follow the exact scores alone, never the clock, so
    fixed-schedule runs stay reproducible.
    """

    phases: tuple[Phase, ...] = (Phase(20, 0.002, 0.05), Phase(140, 0.002, 0.02),
                                 Phase(120, 0.0005, 0.005))
    restarts: tuple[Phase, ...] = (Phase(60, 0.0005, 0.005), Phase(60, 0.00025, 0.0025))
    score_every: int = 20
    beta1: float = 0.9
    beta2: float = 0.999
    epsilon: float = 1e-20
    min_log_energy: float = math.log(1e-20)
    loss_weights: LossWeights = field(default_factory=LossWeights)
    max_iterations: int | None = None
    patience: int | None = None
    min_gain: float | None = MIN_GAIN
    restart_patience: int = 1
    lpips_every: int = 1
    max_falls: int = 2
    fall_tolerance: float = 1e-3
    hinge_anchor_weight: float = 1.0

    def __post_init__(self):
        if self.score_every < 1:
            raise ValueError(f"score_every must be ≥ 1, got {self.score_every}")
        if not (0 <= self.beta1 < 1 and 0 <= self.beta2 < 1 and self.epsilon > 0):
            raise ValueError("need 0 ≤ beta1, beta2 < 1 and epsilon > 0")
        if not self.min_log_energy < math.log(MAX_ENERGY_PCT):
            raise ValueError(f"min_log_energy must be below ln 100, got {self.min_log_energy}")
        if self.max_iterations is not None and self.max_iterations < 0:
            raise ValueError(f"max_iterations must be ≥ 0, got {self.max_iterations}")
        if self.patience is not None and not (isinstance(self.patience, int) and self.patience >= 1):
            raise ValueError(f"patience must be a whole number ≥ 1 or None, got {self.patience!r}")
        if self.min_gain is not None and not self.min_gain >= 0:
            raise ValueError(f"min_gain must be ≥ 0 or None, got {self.min_gain}")
        if not (isinstance(self.restart_patience, int) and self.restart_patience >= 1):
            raise ValueError(f"restart_patience must be a whole number ≥ 1, got {self.restart_patience!r}")
        if self.patience is not None and self.min_gain is None:
            raise ValueError("patience needs a min_gain")
        if not (isinstance(self.lpips_every, int) and self.lpips_every >= 1):
            raise ValueError(f"lpips_every must be a whole number ≥ 1, got {self.lpips_every!r}")
        if not (isinstance(self.max_falls, int) and self.max_falls >= 0):
            raise ValueError(f"max_falls must be a whole number ≥ 0, got {self.max_falls!r}")
        if not self.fall_tolerance >= 0:
            raise ValueError(f"fall_tolerance must be ≥ 0, got {self.fall_tolerance}")
        if not self.hinge_anchor_weight > 0:
            raise ValueError(f"hinge_anchor_weight must be > 0, got {self.hinge_anchor_weight}")

    def fixed_length(self) -> "RefineSchedule":
        """This schedule without adaptive stopping: every phase and restart runs its whole length."""
        return dataclasses.replace(self, patience=None, min_gain=None)

    def with_stop_rule(self, rule: str) -> "RefineSchedule":
        """This schedule with one of the stopping rules of :data:`STOP_RULES` (``octcl invert --stop-rule``).

        ``restarts``: the schedule's own ``min_gain`` and ``restart_patience``
        (:data:`MIN_GAIN` where it has none), no ``patience`` (the default);
        ``stall``: the same and ``patience`` 2 (about half the time on the
        development set, not yet shown to keep every scan's score: module
        docstring); ``none``: :meth:`fixed_length`.
        """
        if rule not in STOP_RULES:
            raise ValueError(f"stop rule must be one of {', '.join(STOP_RULES)}, got {rule!r}")
        if rule == "none":
            return self.fixed_length()
        return dataclasses.replace(self, min_gain=MIN_GAIN if self.min_gain is None else self.min_gain,
                                   patience=2 if rule == "stall" else None)

    @classmethod
    def published(cls) -> "RefineSchedule":
        """The seed paper's schedule: 800 + 200 iterations, four 100-iteration restarts.

        The restarts' learning rates 0.002, 0.002, 0.001, 0.0005 are taken
        as depth steps in µm, with 10× that for u (the ratio of the best
        rates measured here, module docstring); the main run's rates are not
        published and are the default's. At about 1 s an iteration on two
        CPU cores this takes some 25 minutes: it is for faster machines.
        """
        return cls(phases=(Phase(800, 0.002, 0.02), Phase(200, 0.0005, 0.005)),
                   restarts=tuple(Phase(100, lr, 10 * lr) for lr in (0.002, 0.002, 0.001, 0.0005)),
                   score_every=50, min_gain=None)

    @property
    def total_iterations(self) -> int:
        """Adam steps the schedule runs: its phases and restarts, or ``max_iterations`` if fewer."""
        planned = sum(p.iterations for p in self.phases + self.restarts)
        return planned if self.max_iterations is None else min(planned, self.max_iterations)

    def truncated(self, iterations: int) -> "RefineSchedule":
        """The schedule stopped after its first ``iterations`` Adam steps (:attr:`max_iterations`).

        It runs what a deadline run that stopped after that many steps ran:
        phases and then restarts in order, with their exact evaluations on
        the same steps as in the whole schedule, plus one of the last iterate.

        Raises
        ------
        ValueError
            ``iterations`` negative or beyond the schedule's Adam steps.
        """
        planned = sum(p.iterations for p in self.phases + self.restarts)
        if not (isinstance(iterations, int) and 0 <= iterations <= planned):
            raise ValueError(f"iterations must be a whole number in [0, {planned}] (the schedule's Adam "
                             f"steps), got {iterations!r}")
        return dataclasses.replace(self, max_iterations=iterations)


__all__ = ["FALL_LR_FACTOR", "HINGE", "LPIPS_TERMS", "LossWeights", "MAX_ENERGY_PCT", "MIN_GAIN", "PHASE_TERMS", "Phase",
           "RefineSchedule", "SINGLE_TERM_PHASES", "STOP_RULES"]
