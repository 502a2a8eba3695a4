"""Stage 3's hinge phase: the levels' hinge on |A|, its unknowns, and L-BFGS iterations within a refinement."""

import time

import numpy as np
import pytest

from octcl.config import DEFAULT_CONFIG
from octcl.host.stage1.levels import INTERVAL_MARGIN, level_magnitude_bounds
from octcl.host.stage3.hinge import HingeUnknowns, LevelHinge
from octcl.host.stage3.refine import Phase, RefineSchedule, refine, saved_precision
from octcl.host.stage3.schedule import HINGE, LossWeights
from octcl.phantom import Phantom
from octcl.render import render


def _levels_and_a_scans(seed=0, shape=(6, 7)):
    rng = np.random.default_rng(seed)
    a_scans = rng.normal(size=shape) + 1j * rng.normal(size=shape)
    levels = rng.integers(1, 255, size=shape).astype(np.uint8)
    levels.flat[0] = 255
    return levels, a_scans


def test_the_hinge_is_anchored_at_the_start_and_zero_inside_every_interval():
    levels, a_scans = _levels_and_a_scans()
    hinge = LevelHinge(levels, a_scans)
    scale = np.abs(a_scans).max()
    lower, upper = level_magnitude_bounds(levels, INTERVAL_MARGIN)
    anchor = np.unravel_index(np.argmax(np.where(levels == 255, np.abs(a_scans), -1)), levels.shape)
    assert hinge.lower[anchor] == hinge.upper[anchor] == scale
    others = np.ones(levels.shape, dtype=bool)
    others[anchor] = False
    np.testing.assert_allclose(hinge.lower[others], scale * lower[others])
    np.testing.assert_allclose(hinge.upper[others], scale * upper[others])
    # A rendering inside every interval: no loss, no gradient, whatever its phases.
    inside = 0.5 * (hinge.lower + hinge.upper) * np.exp(1j * np.angle(a_scans))
    inside[anchor] = scale  # at the anchor's bound exactly (a real number: its magnitude is not rounded)
    loss, a_bar = hinge(inside)
    assert loss == 0 and not a_bar.any()


@pytest.mark.parametrize("anchor_weight, relative_exponent", [(1.0, 0.0), (1000.0, 0.0), (1.0, 0.5), (1.0, 1.0)])
def test_the_hinge_gradient_matches_finite_differences(anchor_weight, relative_exponent):
    levels, a_scans = _levels_and_a_scans(seed=1)
    # Bounds of another rendering: most pixels outside theirs, the anchor too.
    hinge = LevelHinge(levels, a_scans * 1.3, anchor_weight=anchor_weight, relative_exponent=relative_exponent)
    loss, a_bar = hinge(a_scans)
    assert loss > 0
    # The loss is up to 1000 times the anchor's: at 1e−5 the difference's rounding stays below 1e−5. At γ = 1 it
    # is 2e5 (weights up to 1.1e5, a dark pixel 51 dB down): the difference rounds to 3e−5 at 1e−5, 1.3e−5 at 1e−4.
    step = 1e-4 if relative_exponent == 1.0 else 1e-5
    for index in np.ndindex(levels.shape):
        for direction, part in ((1.0, a_bar[index].real), (1j, a_bar[index].imag)):
            moved = a_scans.copy()
            moved[index] += step * direction
            up = hinge(moved)[0]
            moved[index] -= 2 * step * direction
            assert (up - hinge(moved)[0]) / (2 * step) == pytest.approx(part, rel=2e-5, abs=1e-9)


def test_the_anchor_weight_weighs_the_anchor_alone():
    levels, a_scans = _levels_and_a_scans(seed=2)
    plain, weighted = (LevelHinge(levels, a_scans * 1.3, anchor_weight=weight) for weight in (1.0, 1000.0))
    (loss, a_bar), (weighted_loss, weighted_a_bar) = plain(a_scans), weighted(a_scans)
    anchor = plain.lower == plain.upper
    assert anchor.sum() == 1 and a_bar[anchor] != 0
    np.testing.assert_allclose(weighted_a_bar[anchor], 1000.0 * a_bar[anchor])
    np.testing.assert_array_equal(weighted_a_bar[~anchor], a_bar[~anchor])
    anchor_residual = float(np.abs(a_scans[anchor][0]) - plain.upper[anchor][0])  # its interval is one value
    assert weighted_loss - loss == pytest.approx(999.0 * 0.5 * anchor_residual**2)


def test_the_relative_exponent_weighs_each_pixel_by_its_upper_bound():
    """w_p = (u_p/u_anchor)^(−2γ): at γ = 1 each pixel's loss is its squared distance relative to its upper
    bound; the anchor's weight stays 1, and a rendering inside every interval still costs nothing."""
    levels, a_scans = _levels_and_a_scans(seed=4)
    levels.flat[1] = 0  # level 0: its upper bound is the display's floor, its lower 0
    plain, relative = (LevelHinge(levels, a_scans * 1.3, relative_exponent=gamma) for gamma in (0.0, 1.0))
    anchor = plain.lower == plain.upper
    scale = plain.upper[anchor][0]
    np.testing.assert_allclose(relative.weight, (plain.upper / scale) ** -2.0)
    assert relative.weight[anchor][0] == 1.0 and relative.weight.flat[1] > 1e4  # the floor is 51 dB down
    magnitude = np.abs(a_scans)
    distance = magnitude - np.clip(magnitude, plain.lower, plain.upper)
    assert relative(a_scans)[0] == pytest.approx(0.5 * float(np.sum((distance * scale / plain.upper) ** 2)))
    inside = 0.5 * (plain.lower + plain.upper) * np.exp(1j * np.angle(a_scans))
    inside[anchor] = scale
    assert relative(inside)[0] == 0
    with pytest.raises(ValueError, match=r"relative_exponent must be in \[0, 1\]"):
        LevelHinge(levels, a_scans, relative_exponent=1.5)


def test_each_hinge_phase_fits_with_its_own_exponent(shadowed_start, monkeypatch):
    """Two hinge phases in a row with different γ are two L-BFGS fits, each weighing the pixels by its own γ;
    the restarts' by theirs."""
    from octcl.host.stage3 import refine as refine_module

    exponents = []

    class Recorded(LevelHinge):
        def __init__(self, *args, relative_exponent=0.0, **kwargs):
            exponents.append(relative_exponent)
            super().__init__(*args, relative_exponent=relative_exponent, **kwargs)

    monkeypatch.setattr(refine_module, "LevelHinge", Recorded)
    start, aim = shadowed_start
    schedule = RefineSchedule(phases=(Phase(2, 0.0, 0.0, terms=HINGE), Phase(2, 0.0, 0.0, terms=HINGE,
                                                                             relative_exponent=0.5)),
                              restarts=(Phase(2, 0.0, 0.0, terms=HINGE, relative_exponent=0.25),),
                              score_every=100, min_gain=None)
    result = refine(start, aim, schedule, aim=aim, threads=1)
    assert exponents == [0.0, 0.5, 0.25] and result.iterations == 6


def test_only_a_hinge_phase_has_a_relative_exponent():
    Phase(5, 0.0, 0.0, terms=HINGE, relative_exponent=0.5)
    with pytest.raises(ValueError, match="a 'pixel' phase has none"):
        Phase(5, 0.001, 0.02, terms="pixel", relative_exponent=0.5)
    with pytest.raises(ValueError, match=r"must be in \[0, 1\]"):
        Phase(5, 0.0, 0.0, terms=HINGE, relative_exponent=-0.1)


def test_the_unknowns_are_log_amplitude_and_carrier_phase():
    rng = np.random.default_rng(2)
    z_um, log_energy = rng.uniform(0, 1536, 9), rng.uniform(-20, 4, 9)
    unknowns = HingeUnknowns(DEFAULT_CONFIG)
    x = unknowns.pack(z_um, log_energy)
    np.testing.assert_allclose(x[:9], log_energy / 2)  # ln a, a = sqrt(E)·const
    np.testing.assert_allclose(x[9:], 2 * DEFAULT_CONFIG.k0_rad_per_um * z_um)  # the carrier's phase
    back_z, back_u = unknowns.unpack(x)
    np.testing.assert_allclose(back_z, z_um, rtol=1e-15)
    np.testing.assert_allclose(back_u, log_energy, rtol=1e-15)
    # The chain rule: f(z, u) = Σ c·z + d·u has ∂f/∂x = (2·d, c/(2·k0)); checked against a difference in x.
    c, d = rng.normal(size=9), rng.normal(size=9)
    gradient = unknowns.gradient(d, c)

    def f(vector):
        z, u = unknowns.unpack(vector)
        return float(c @ z + d @ u)

    direction = rng.normal(size=18)
    assert (f(x + 1e-3 * direction) - f(x - 1e-3 * direction)) / 2e-3 == pytest.approx(gradient @ direction)


def test_a_hinge_phase_takes_no_learning_rates_and_no_loss_weights():
    Phase(5, 0.0, 0.0, terms=HINGE)
    with pytest.raises(ValueError, match="without learning rates"):
        Phase(5, 0.001, 0.0, terms=HINGE)
    with pytest.raises(ValueError, match="no loss weights"):
        LossWeights().for_terms(HINGE)


@pytest.fixture(scope="module")
def shadowed_start():
    """A phantom with real shadowing, its rendering's levels as the aim, and the phantom moved off them: each
    scatterer's energy by a random ±20 % and its depth by up to ±0.02 µm (a carrier turn of ±0.19 rad)."""
    rng = np.random.default_rng(3)
    count = 20_000
    x_um = rng.uniform(-1536, 1536, count)
    z_um = rng.uniform(40, 900, count)
    energy = rng.uniform(0.01, 0.2, count)
    truth = Phantom(x_um, np.zeros(count), z_um, energy)
    aim = render(truth).levels
    moved = Phantom(x_um, np.zeros(count), z_um + rng.uniform(-0.02, 0.02, count),
                    energy * rng.uniform(0.8, 1.2, count))
    return Phantom(*(saved_precision(getattr(moved, name)) for name in ("x_um", "y_um", "z_um", "energy_pct"))), aim


def test_a_hinge_phase_puts_pixels_back_at_their_levels(shadowed_start):
    """From a phantom moved off its rendering's levels, the hinge phase's L-BFGS iterations put more pixels at
    their level and score higher; each iteration counts as a step, the last is scored, z and E stay in bounds."""
    start, aim = shadowed_start
    at_start = np.mean(render(start).levels == aim)
    schedule = RefineSchedule(phases=(Phase(15, 0.0, 0.0, terms=HINGE),), restarts=(), score_every=5)
    result = refine(start, aim, schedule, aim=aim, threads=1)
    assert result.iterations == 15
    assert [entry["iteration"] for entry in result.trace if entry["score"] is not None] == [0, 5, 10, 15]
    assert result.components["mean"] > result.initial_components["mean"]
    at_end = np.mean(render(result.phantom).levels == aim)
    assert at_end > at_start + 0.1, (at_start, at_end)
    assert result.phantom.energy_pct.max() <= 100 and result.phantom.z_um.min() >= 0


def test_adam_phases_go_on_after_a_hinge_phase(shadowed_start):
    """A hinge phase between Adam phases: the steps add up, and the Adam phase after it takes its steps."""
    start, aim = shadowed_start
    schedule = RefineSchedule(phases=(Phase(2, 0.001, 0.02, terms="pixel"), Phase(3, 0.0, 0.0, terms=HINGE),
                                      Phase(2, 0.001, 0.02, terms="pixel")), restarts=(), score_every=100)
    result = refine(start, aim, schedule, aim=aim, threads=1)
    assert result.iterations == 7
    assert [entry["iteration"] for entry in result.trace][-1] == 7
    losses = [entry["loss"] for entry in result.trace if entry["loss"] is not None]
    assert len(losses) == 4  # the Adam steps' losses; the hinge's iterations log none


def test_the_iterate_a_hinge_phase_starts_from_is_scored_at_a_checkpoint(shadowed_start):
    """Checkpoints every 2 steps: the pixel phase's last iterate (step 4), where the hinge begins, is scored
    before the hinge moves it, as the hinge's own at 6 and the last at 7."""
    start, aim = shadowed_start
    schedule = RefineSchedule(phases=(Phase(4, 0.001, 0.02, terms="pixel"), Phase(3, 0.0, 0.0, terms=HINGE)),
                              restarts=(), score_every=2, min_gain=None)
    result = refine(start, aim, schedule, aim=aim, threads=1)
    assert result.iterations == 7
    assert [entry["iteration"] for entry in result.trace if entry["score"] is not None] == [0, 2, 4, 6, 7]


@pytest.mark.clock
def test_a_hinge_phase_keeps_the_deadline(shadowed_start):
    """Its iterations stop where the next one and a score would end past the deadline; the last is scored."""
    start, aim = shadowed_start
    schedule = RefineSchedule(phases=(Phase(10_000, 0.0, 0.0, terms=HINGE),), restarts=(), score_every=10_000)
    began = time.monotonic()
    result = refine(start, aim, schedule, aim=aim, threads=1, deadline=began + 4.0)
    elapsed = time.monotonic() - began
    assert result.stopped_by_deadline and 0 < result.iterations < 10_000
    assert elapsed < 4.0 + 1.0
    scored = [entry["iteration"] for entry in result.trace if entry["score"] is not None]
    assert scored == [0, result.iterations]


def test_a_hinge_phase_from_a_dark_rendering_is_skipped():
    """Scatterers that no A-scan sees render nothing: the phase has no pixel to anchor the levels at, and the
    schedule goes on past it (the Adam phase after it runs) instead of failing."""
    count = 50
    dark = Phantom(np.full(count, 5000.0), np.zeros(count), np.linspace(100, 900, count), np.full(count, 1.0))
    aim = np.zeros((256, 512), dtype=np.uint8)
    aim[100, 200] = 255
    schedule = RefineSchedule(phases=(Phase(4, 0.0, 0.0, terms=HINGE), Phase(2, 0.001, 0.02, terms="pixel")),
                              restarts=(), score_every=100)
    result = refine(dark, aim, schedule, aim=aim, threads=1)
    assert result.iterations == 2
    assert [entry["iteration"] for entry in result.trace][-1] == 6
