"""Stage 3: the scorer-aligned loss, the Adam refinement, its constraints and deadline."""

import dataclasses
import math
import time

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from octcl._io import GREY_LUT, read_png_rgb, read_scan
from octcl._reference import quantise
from octcl.host.stage1.levels import display_interval_of_level
from octcl.host.stage3.loss import LEVEL_MARGIN, QUANTISER_SLOPE, DisplayLoss, ExactScore, LossWeights, scan_of_levels
from octcl.host.stage3.refine import MAX_ENERGY_PCT, Phase, RefineClock, RefineSchedule, refine, saved_precision
from octcl.host.pipeline.target import read_target
from octcl.phantom import CONTRACT_Y_LIMIT_UM, Phantom
from octcl.scorer import COMPONENTS, score

SCAN_SHAPE = (256, 512)
# The terms whose gradient involves no detached normaliser (maps_torch holds
# the OAC display window constant by design), so a finite difference of the
# un-quantised loss is their exact directional derivative.
STRUCT_WEIGHTS = LossWeights(pixel=1.0, sc_l1=0, oac_l1=0, oac_lpips=0, oac_msssim=0,
                             struct_msssim=1.2, struct_lpips=0.01, sc_lpips=0, rsc_lpips=0)


@pytest.fixture(scope="module")
def layers_path(official_data):
    return official_data / "Scan_Exp2_Layers_A.png"


@pytest.fixture(scope="module")
def layers_target(layers_path):
    return read_target(layers_path)


@pytest.fixture(scope="module")
def uniform_levels(official_data):
    return read_png_rgb(official_data / "Scan_Exp1_Uniform_A.png")[..., 0].astype(int)


@pytest.fixture(scope="module")
def stage2_phantom(layers_path):
    """A short stage 1 + 2 of the Layers scan (few scatterers, so kernels are quick)."""
    from octcl.host.stage2.capped import decode_field
    from octcl.host.stage1.display import fit_field

    fit = fit_field(read_scan(layers_path, SCAN_SHAPE), iterations=150, time_budget_s=8.0)
    return decode_field(fit.field, max_scatterers=60_000, seed=0)


def _unquantised_loss(loss: DisplayLoss, display: np.ndarray) -> float:
    """The weighted loss at P = 256·D/255, without the quantiser."""
    with torch.no_grad():
        terms = loss.terms(torch.tensor(QUANTISER_SLOPE * display, dtype=loss.dtype))
    return float(sum(getattr(loss.weights, name) * value for name, value in terms.items()))


def _directional_derivatives(loss, display, count, seed=0, step=1e-5):
    """(central finite differences of the un-quantised loss, straight-through gradient · v)."""
    rng = np.random.default_rng(seed)
    gradient = loss(display).grad_display
    finite, straight = [], []
    for _ in range(count):
        direction = gaussian_filter(rng.normal(size=display.shape), 4)
        direction /= np.abs(direction).max()
        finite.append((_unquantised_loss(loss, display + step * direction)
                       - _unquantised_loss(loss, display - step * direction)) / (2 * step))
        straight.append(float(np.sum(gradient * direction)))
    return np.array(finite), np.array(straight)


def test_loss_forward_is_the_quantised_scan(layers_path, uniform_levels):
    """The forward value is that of the 8-bit scan the scorer reads (levels/255)."""
    target = read_scan(layers_path, SCAN_SHAPE)
    loss = DisplayLoss(target, STRUCT_WEIGHTS, dtype=torch.float64)
    display = (uniform_levels + 0.7) / 256.0  # inside each level's display interval
    levels = GREY_LUT[uniform_levels]
    expected = _unquantised_loss(loss, levels / 255.0 / QUANTISER_SLOPE)
    assert loss(display).loss == pytest.approx(expected, rel=1e-8)


def test_straight_through_gradient_on_the_level_grid(layers_path, uniform_levels):
    """Where D = c/256 (an untruncated colour index), P = 256·D/255 exactly: gradients agree."""
    target = read_scan(layers_path, SCAN_SHAPE)
    loss = DisplayLoss(target, STRUCT_WEIGHTS, dtype=torch.float64)
    index = np.where(GREY_LUT[uniform_levels] == uniform_levels, uniform_levels, uniform_levels + 1)
    assert (GREY_LUT[index] == index).all()
    finite, straight = _directional_derivatives(loss, index / 256.0, count=4)
    np.testing.assert_allclose(straight, finite, rtol=0.02, atol=1e-4 * np.abs(finite).max())


def test_straight_through_gradient_between_levels(layers_path, uniform_levels):
    """Anywhere inside the levels the estimator follows the un-quantised loss roughly."""
    target = read_scan(layers_path, SCAN_SHAPE)
    loss = DisplayLoss(target, STRUCT_WEIGHTS, dtype=torch.float64)
    rng = np.random.default_rng(1)
    display = (uniform_levels + rng.random(uniform_levels.shape)) / 256.0
    finite, straight = _directional_derivatives(loss, display, count=6)
    assert np.linalg.norm(straight - finite) < 0.25 * np.linalg.norm(finite)


def test_the_level_term_pulls_each_display_into_the_middle_of_its_level(layers_path):
    """The level term is 0 within f·H of each level's centre, and positive near its edge where the pixel term,
    the level being right, is 0; its gradient is the un-quantised term's and points away from the centre."""
    target = read_scan(layers_path, SCAN_SHAPE)
    levels = np.rint(target * 255).astype(np.intp)
    low, high = display_interval_of_level()
    centre, half = ((low + high) / 2)[levels], ((high - low) / 2)[levels]
    centre[levels == 0], half[levels == 0] = 0.5 / 256, 0.0  # level 0: the quantised difference (D = 0 keeps it 0)
    level_only = LossWeights(**{name: float(name == "level") for name in LossWeights.__dataclass_fields__})
    pixel_only = LossWeights(**{name: float(name == "pixel") for name in LossWeights.__dataclass_fields__})
    loss, pixel = DisplayLoss(target, level_only, dtype=torch.float64), DisplayLoss(target, pixel_only, torch.float64)
    lit = levels > 0
    inside = np.where(lit, centre + 0.5 * LEVEL_MARGIN * half, 0.0)
    at_inside = loss(inside)
    assert at_inside.loss == 0.0 and not at_inside.grad_display.any()
    near_edge = np.where(lit, centre + 0.9 * half, 0.0)
    # The same levels, so the pixel term does not tell them apart (it is the target file's float32 rounding).
    assert (quantise(near_edge) == quantise(inside)).all() and pixel(near_edge).loss == pixel(inside).loss < 1e-8
    at_edge = loss(near_edge)
    assert at_edge.loss > 0 and (at_edge.grad_display[lit] > 0).all() and not at_edge.grad_display[~lit].any()
    finite, straight = _directional_derivatives(loss, near_edge, count=4)
    np.testing.assert_allclose(straight, finite, rtol=0.02, atol=1e-4 * np.abs(finite).max())


def test_loss_weights_skip_terms_and_refuse_bad_values(layers_path):
    target = read_scan(layers_path, SCAN_SHAPE)
    value = DisplayLoss(target, LossWeights().without_lpips())(target.astype(np.float64))
    assert not any("lpips" in name for name in value.terms)
    assert value.grad_display.shape == SCAN_SHAPE and value.grad_display.dtype == np.float64
    with pytest.raises(ValueError, match="pixel"):
        LossWeights(pixel=-1.0)
    with pytest.raises(ValueError, match="positive"):
        LossWeights(**{name: 0.0 for name in LossWeights.__dataclass_fields__})


def test_a_loss_builds_only_what_its_weighted_terms_compare(layers_path, uniform_levels):
    """A loss of the pixel term alone builds no network and no maps, one without LPIPS no network, one of the SC
    map's LPIPS the SC map alone (the aim's proposal); each gives its terms as the published loss does."""
    target = read_scan(layers_path, SCAN_SHAPE)
    display = (uniform_levels + 0.3) / 256.0
    full = DisplayLoss(target, LossWeights(), dtype=torch.float64)(display).terms
    sc_lpips = LossWeights(**{name: float(name == "sc_lpips") for name in dataclasses.asdict(LossWeights())})
    for weights, network, maps in ((LossWeights().for_terms("pixel"), False, set()),
                                   (LossWeights().without_lpips(), False, {"OAC", "SC"}),
                                   (sc_lpips, True, {"SC"}), (LossWeights(), True, {"OAC", "SC", "RSC"})):
        loss = DisplayLoss(target, weights, dtype=torch.float64)
        assert (loss.network is not None) == network and set(loss.target) == {"Struct", *maps}
        value = loss(display)
        assert value.terms == pytest.approx({name: full[name] for name in value.terms}, rel=1e-12)


def test_kept_lpips_gradient_is_reused(layers_path, uniform_levels):
    """``keep`` gives ``compute``'s loss and gradient; ``reuse`` adds the kept LPIPS part to the rest at D."""
    target = read_scan(layers_path, SCAN_SHAPE)
    weights = LossWeights(oac_lpips=0.4, struct_lpips=0.01, sc_lpips=0, rsc_lpips=0)
    loss, without = DisplayLoss(target, weights), DisplayLoss(target, weights.without_lpips())
    with pytest.raises(ValueError, match="earlier call"):
        loss(target.astype(np.float64), lpips="reuse")
    with pytest.raises(ValueError, match="lpips must be"):
        loss(target.astype(np.float64), lpips="sometimes")
    rng = np.random.default_rng(2)
    kept_at = (uniform_levels + rng.random(uniform_levels.shape)) / 256.0
    elsewhere = np.clip(kept_at + rng.normal(0, 0.02, kept_at.shape), 0, 1)
    computed, kept = loss(kept_at), loss(kept_at, lpips="keep")
    # The gradient through the maps' copies (AlexNet with oneDNN) is autograd's through the whole graph.
    d = torch.tensor(kept_at, dtype=loss.dtype, requires_grad=True)
    scan = torch.as_tensor(quantise(kept_at) / 255.0, dtype=loss.dtype) + (QUANTISER_SLOPE * d
                                                                          - (QUANTISER_SLOPE * d).detach())
    sum(getattr(weights, name) * term for name, term in loss.terms(scan).items()).backward()
    np.testing.assert_allclose(computed.grad_display, d.grad.numpy(), atol=1e-5 * np.abs(d.grad.numpy()).max())
    assert kept.loss == pytest.approx(computed.loss, rel=1e-6) and kept.terms == pytest.approx(computed.terms)
    np.testing.assert_allclose(kept.grad_display, computed.grad_display,
                               atol=1e-5 * np.abs(computed.grad_display).max())
    lpips_part = computed.grad_display - without(kept_at).grad_display
    assert np.abs(lpips_part).max() > 0.01 * np.abs(computed.grad_display).max()  # LPIPS matters here
    reused, rest = loss(elsewhere, lpips="reuse"), without(elsewhere)
    np.testing.assert_allclose(reused.grad_display, rest.grad_display + lpips_part,
                               atol=1e-5 * np.abs(computed.grad_display).max())
    lpips_value = sum(getattr(weights, name) * kept.terms[name] for name in ("oac_lpips", "struct_lpips"))
    assert reused.loss == pytest.approx(rest.loss + lpips_value, rel=1e-6)
    assert reused.terms["oac_lpips"] == kept.terms["oac_lpips"]
    # LPIPS-only weights: reusing leaves only the kept part.
    only = DisplayLoss(target, LossWeights(**{**{name: 0.0 for name in LossWeights.__dataclass_fields__},
                                              "struct_lpips": 1.0}))
    first = only(kept_at, lpips="keep")
    np.testing.assert_array_equal(only(elsewhere, lpips="reuse").grad_display, first.grad_display)


@pytest.mark.parametrize("kind", ["official", "grey"])
def test_exact_score_matches_the_scorer_on_saved_files(layers_path, uniform_levels, tmp_path, kind):
    """ExactScore of levels equals octcl.scorer.score of the same levels written as a PNG.

    The target as read from the official grey RGBA file and from a grey
    PNG of the same levels, which the metric reads differently
    (:mod:`octcl.host.pipeline.target`).
    """
    from PIL import Image

    from octcl._io import write_grey_png

    target_file = layers_path
    if kind != "official":
        target_file = tmp_path / f"{kind}.png"
        Image.fromarray(np.asarray(Image.open(layers_path))[..., 0]).save(target_file)
    levels = uniform_levels.astype(np.uint8)
    write_grey_png(tmp_path / "pred.png", levels)
    expected = score(target_file, tmp_path / "pred.png")
    got = ExactScore(read_target(target_file))(levels)
    assert got == pytest.approx(expected, abs=0, rel=0)
    assert set(COMPONENTS) < set(got)
    np.testing.assert_array_equal(scan_of_levels(levels), read_scan(tmp_path / "pred.png"))


def test_short_schedule_improves_on_stage_2(stage2_phantom, layers_target):
    schedule = RefineSchedule(phases=(Phase(12, 0.01, 0.02),), restarts=(), score_every=6)
    improvements, phantoms = [], []

    def on_improvement(phantom, components):
        improvements.append(components["mean"])
        phantoms.append((phantom, phantom.z_um.copy()))

    result = refine(stage2_phantom, layers_target, schedule, on_improvement=on_improvement)
    assert result.iterations == 12
    assert result.components["mean"] > result.initial_components["mean"]
    assert improvements and improvements[-1] == result.components["mean"]
    assert improvements == sorted(improvements)
    # The phantoms handed out are snapshots (a writer thread may still hold
    # them), not views of the iterate that Adam keeps changing.
    assert len(phantoms) >= 2
    for phantom, z_at_callback in phantoms:
        np.testing.assert_array_equal(phantom.z_um, z_at_callback)
    np.testing.assert_array_equal(phantoms[-1][0].z_um, result.phantom.z_um)
    scored = [entry["score"] for entry in result.trace if entry.get("score") is not None]
    assert max(scored) == result.components["mean"]
    # x and y stay, on the file's grid (z and E too, so the score is the file's).
    for column in ("x_um", "y_um"):
        np.testing.assert_array_equal(getattr(result.phantom, column),
                                      saved_precision(getattr(stage2_phantom, column)))
    z_um, energy_pct = result.phantom.z_um, result.phantom.energy_pct
    np.testing.assert_allclose(saved_precision(z_um), z_um, rtol=1e-15)
    # E is kept as u = ln E: exp(fl(ln E)) is within (|ln E|/2 + 1)·ε of E, up
    # to 5.3e-15 at the floor E = 1e-20 (the small energies of a short stage 1).
    np.testing.assert_allclose(saved_precision(energy_pct), energy_pct,
                               rtol=(abs(schedule.min_log_energy) / 2 + 1) * np.finfo(float).eps)


def test_constraints_hold_after_steps(stage2_phantom, layers_target):
    """Huge steps from a phantom at the bounds stay inside 0 ≤ z ≤ 1536, E_floor ≤ E ≤ 100."""
    rng = np.random.default_rng(0)
    count = len(stage2_phantom)
    z = np.where(rng.random(count) < 0.5, 0.0, 1536.0)
    energy = np.where(rng.random(count) < 0.5, MAX_ENERGY_PCT, 0.0)
    start = Phantom(stage2_phantom.x_um, stage2_phantom.y_um, z, energy)
    schedule = RefineSchedule(phases=(Phase(3, 50.0, 30.0),), restarts=(Phase(2, 50.0, 30.0),),
                              score_every=1)
    result = refine(start, layers_target, schedule)
    assert result.iterations == 5
    phantom = result.phantom
    phantom.validate(y_limit_um=CONTRACT_Y_LIMIT_UM)
    assert phantom.z_um.min() >= 0 and phantom.z_um.max() <= 1536.0
    assert phantom.energy_pct.max() <= MAX_ENERGY_PCT
    assert phantom.energy_pct.min() >= math.exp(schedule.min_log_energy) * (1 - 1e-12)


@pytest.mark.clock
def test_deadline_is_respected(stage2_phantom, layers_target):
    schedule = RefineSchedule(phases=(Phase(10_000, 0.01, 0.02),), restarts=(), score_every=5)
    start = time.monotonic()
    result = refine(stage2_phantom, layers_target, schedule, deadline=start + 6.0)
    elapsed = time.monotonic() - start
    assert result.stopped_by_deadline
    assert 0 < result.iterations < 10_000
    # One initial evaluation always runs; everything else must fit the deadline.
    assert elapsed < 6.0 + 3.0
    assert result.components["mean"] >= result.initial_components["mean"]


def test_lpips_gradient_is_computed_every_k_steps_of_a_run(stage2_phantom, layers_target, monkeypatch):
    """``lpips_every`` 2: kept on a run's first step, every second after, and after a step without LPIPS."""
    calls = []
    original = DisplayLoss.__call__

    def spy(self, display, lpips="compute"):
        calls.append(lpips if any(name.endswith("lpips") and weight > 0 for name, weight in
                                  vars(self.weights).items()) else "none")
        return original(self, display, lpips)

    monkeypatch.setattr(DisplayLoss, "__call__", spy)
    schedule = RefineSchedule(phases=(Phase(3, 0.001, 0.01), Phase(1, 0.001, 0.01, terms="no_lpips"),
                                      Phase(1, 0.001, 0.01)), restarts=(Phase(1, 0.001, 0.01),),
                              loss_weights=STRUCT_WEIGHTS, lpips_every=2, min_gain=None)
    result = refine(stage2_phantom, layers_target, schedule, threads=2)
    assert result.iterations == 6
    assert calls == ["keep", "reuse", "keep", "none", "keep", "keep"]


def test_a_phase_computes_only_its_terms(stage2_phantom, layers_target, monkeypatch):
    """A ``pixel`` phase's loss has the pixel term alone, a ``no_lpips`` one every weighted term but LPIPS, an
    ``all`` one every weighted term; the pixel phase moves the phantom towards its target."""
    seen = []
    original = DisplayLoss.__call__

    def spy(self, display, lpips="compute"):
        value = original(self, display, lpips)
        seen.append(sorted(value.terms))
        return value

    monkeypatch.setattr(DisplayLoss, "__call__", spy)
    weights = LossWeights()
    schedule = RefineSchedule(phases=(Phase(4, 0.001, 0.02, terms="pixel"), Phase(1, 0.001, 0.01, terms="no_lpips"),
                                      Phase(1, 0.001, 0.01)), restarts=(), loss_weights=weights, min_gain=None)
    result = refine(stage2_phantom, layers_target, schedule, threads=2)
    weighted = sorted(name for name, weight in vars(weights).items() if weight > 0)
    assert seen == [["pixel"]] * 4 + [[name for name in weighted if "lpips" not in name], weighted]
    pixel_losses = [entry["loss"] for entry in result.trace if entry["loss"] is not None][:4]
    assert pixel_losses[-1] < pixel_losses[0]


def test_a_stalled_run_stops(stage2_phantom, layers_target):
    """Zero learning rates never gain: the main run ends at its first checkpoint, then one restart.

    With ``patience`` 1 the main run ends at its checkpoint at step 2, where
    the best has gained nothing, and the restarts begin from the best
    phantom; the first stalls the same way at its half-way checkpoint and
    has gained nothing over its parent, so the second is skipped. Without
    adaptive stopping every step runs.
    """
    still = Phase(6, 0.0, 0.0, terms="no_lpips")
    schedule = RefineSchedule(phases=(still,), restarts=(Phase(4, 0.0, 0.0, terms="no_lpips"), still),
                              score_every=2, patience=1)
    result = refine(stage2_phantom, layers_target, schedule, threads=2)
    assert result.iterations == 2 + 2 and result.stop_reason == "converged"
    scored = [(entry["stage"], entry["iteration"]) for entry in result.trace if entry["score"] is not None]
    assert scored == [("initial", 0), ("refine", 2), ("restart 1", 2)]
    assert result.components == result.initial_components
    whole = refine(stage2_phantom, layers_target, schedule.fixed_length().truncated(6 + 2), threads=2)
    assert whole.iterations == 6 + 2 and whole.stop_reason == "schedule"
    assert max(entry["iteration"] for entry in whole.trace if entry["stage"] == "refine") == 6
    # Restarts that gain are repeated until the iterations the stalled main
    # run left are spent.
    gaining = RefineSchedule(phases=(still,), restarts=(Phase(2, 0.01, 0.02, terms="no_lpips"),), score_every=2,
                             patience=1, min_gain=1e-12)
    repeated = refine(stage2_phantom, layers_target, gaining, threads=2)
    assert repeated.iterations == 2 + 3 * 2 == gaining.total_iterations and repeated.stop_reason == "schedule"
    assert {entry["stage"] for entry in repeated.trace} == {"initial", "refine", "restart 1", "restart 2", "restart 3"}
    assert repeated.components["mean"] > repeated.initial_components["mean"]


def test_restarts_are_judged_together_over_restart_patience(stage2_phantom, layers_target):
    """``restart_patience`` 2: a restart that gains nothing is followed by one more, and the refinement ends once
    the two together gained less than ``min_gain``; restarts that gain are judged over the last two."""
    still = Phase(6, 0.0, 0.0, terms="no_lpips")
    schedule = RefineSchedule(phases=(still,), restarts=(Phase(4, 0.0, 0.0, terms="no_lpips"), still),
                              score_every=2, patience=1, restart_patience=2)
    result = refine(stage2_phantom, layers_target, schedule, threads=2)
    assert result.stop_reason == "converged" and result.iterations == 2 + 2 + 3
    scored = [(entry["stage"], entry["iteration"]) for entry in result.trace if entry["score"] is not None]
    assert scored == [("initial", 0), ("refine", 2), ("restart 1", 2), ("restart 2", 3)]
    gaining = RefineSchedule(phases=(still,), restarts=(Phase(2, 0.01, 0.02, terms="no_lpips"),), score_every=2,
                             patience=1, min_gain=1e-12, restart_patience=2)
    repeated = refine(stage2_phantom, layers_target, gaining, threads=2)
    assert repeated.iterations == gaining.total_iterations and repeated.stop_reason == "schedule"


def test_a_phase_out_of_patience_hands_over_to_the_next(stage2_phantom, layers_target):
    """A phase of zero rates with ``patience`` 1 never gains: it ends at its first checkpoint without a step
    there, and the next phase goes on from that iterate and step count, its checkpoints unchanged and that
    iterate not scored twice. Without adaptive stopping the phase runs its length."""
    schedule = RefineSchedule(phases=(Phase(6, 0.0, 0.0, terms="pixel", patience=1),
                                      Phase(4, 0.001, 0.02, terms="pixel")), restarts=(), score_every=2)
    result = refine(stage2_phantom, layers_target, schedule, threads=2)
    assert result.iterations == 2 + 4 and result.stop_reason == "schedule"
    scored = [entry["iteration"] for entry in result.trace if entry["stage"] == "refine" and entry["score"] is not None]
    assert scored == [2, 8, 10]
    whole = refine(stage2_phantom, layers_target, schedule.fixed_length(), threads=2)
    assert whole.iterations == 6 + 4


def test_a_phase_that_fell_and_ran_out_of_patience_hands_over_its_best(stage2_phantom, layers_target, monkeypatch):
    """Steps far too long fall at the first checkpoint, which also ends the phase: the next phase begins from
    the best phantom (the input) with fresh moments, at the halved rates of a fall."""
    from octcl.host.stage3.refine import FALL_LR_FACTOR, _Refiner

    steps = []
    original = _Refiner.step

    def spy(self, adam, params, grads, lrs):
        steps.append((params[0].copy(), lrs, adam.steps))
        return original(self, adam, params, grads, lrs)

    monkeypatch.setattr(_Refiner, "step", spy)
    schedule = RefineSchedule(phases=(Phase(6, 2.0, 2.0, terms="no_lpips", patience=1),
                                      Phase(2, 0.001, 0.01, terms="no_lpips")), restarts=(), score_every=2)
    result = refine(stage2_phantom, layers_target, schedule, threads=1)
    assert result.falls == [2] and result.iterations == 2 + 2
    assert [lr for _, lr, _ in steps] == [(2.0, 2.0)] * 2 + [(0.001 * FALL_LR_FACTOR, 0.01 * FALL_LR_FACTOR)] * 2
    np.testing.assert_array_equal(steps[2][0], steps[0][0])
    assert steps[2][2] == 0


def test_a_fallen_main_run_goes_back_to_its_best(stage2_phantom, layers_target, monkeypatch):
    """Steps far too long make the checkpoints fall below the start: back to the best, at half the rates.

    With ``max_falls`` 2 the run falls after steps 2 and 4; each time the
    next step starts from the best phantom (the input, since nothing
    gains) with fresh moments, and the learning rates are halved. A third
    fall is not acted on.
    """
    from octcl.host.stage3.refine import FALL_LR_FACTOR, _Refiner

    steps = []
    original = _Refiner.step

    def spy(self, adam, params, grads, lrs):
        steps.append((params[0].copy(), params[1].copy(), lrs, adam.steps))
        return original(self, adam, params, grads, lrs)

    monkeypatch.setattr(_Refiner, "step", spy)
    wild = Phase(8, 2.0, 2.0, terms="no_lpips")
    schedule = RefineSchedule(phases=(wild,), restarts=(), score_every=2, max_falls=2)
    result = refine(stage2_phantom, layers_target, schedule, threads=1)
    assert result.falls == [2, 4] and result.iterations == 8
    scored = [entry["score"] for entry in result.trace if entry["score"] is not None]
    assert all(score < scored[0] for score in scored[1:])  # every checkpoint fell
    assert result.components == result.initial_components
    lrs = [lr for _, _, lr, _ in steps]
    assert lrs == [(2.0, 2.0)] * 2 + [(2.0 * FALL_LR_FACTOR,) * 2] * 2 + [(2.0 * FALL_LR_FACTOR**2,) * 2] * 4
    for after_fall in (2, 4):  # the input phantom again, and Adam from zero moments
        np.testing.assert_array_equal(steps[after_fall][0], steps[0][0])
        np.testing.assert_array_equal(steps[after_fall][1], steps[0][1])
        assert steps[after_fall][3] == 0
    assert not np.array_equal(steps[6][0], steps[0][0])  # the third fall (after step 6) is let be

    # A run that gains never falls, and the guard changes none of its bits.
    steps.clear()
    gaining = RefineSchedule(phases=(Phase(6, 0.002, 0.02, terms="no_lpips"),), restarts=(), score_every=2)
    guarded = refine(stage2_phantom, layers_target, gaining, threads=1)
    unguarded = refine(stage2_phantom, layers_target, dataclasses.replace(gaining, max_falls=0), threads=1)
    assert guarded.falls == unguarded.falls == []
    assert guarded.components["mean"] > guarded.initial_components["mean"]
    np.testing.assert_array_equal(guarded.phantom.z_um, unguarded.phantom.z_um)
    np.testing.assert_array_equal(guarded.phantom.energy_pct, unguarded.phantom.energy_pct)


def test_target_score_stops_the_refinement(stage2_phantom, layers_target):
    schedule = RefineSchedule(phases=(Phase(30, 0.01, 0.02, terms="no_lpips"),), restarts=(), score_every=2)
    reached = refine(stage2_phantom, layers_target, schedule, threads=1, target_score=0.01)
    assert reached.iterations == 0 and reached.stop_reason == "target score"
    # A target just above the start: the first checkpoint that reaches it ends the run.
    first = refine(stage2_phantom, layers_target, schedule.truncated(2), threads=1)
    assert first.components["mean"] > first.initial_components["mean"]
    target = (first.initial_components["mean"] + first.components["mean"]) / 2
    result = refine(stage2_phantom, layers_target, schedule, threads=1, target_score=target)
    assert result.iterations == 2 and result.stop_reason == "target score"
    assert result.components == first.components
    for bad in (0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="target_score"):
            refine(stage2_phantom, layers_target, schedule, target_score=bad)


def test_a_start_at_its_aimed_levels_is_not_refined(stage2_phantom, layers_target):
    """``aim``: a start that renders every aimed level stops at once (``ceiling``); one pixel off, it runs."""
    from octcl.render import render

    schedule = RefineSchedule(phases=(Phase(2, 0.01, 0.02, terms="no_lpips"),), restarts=(), score_every=2)
    rendered = render(Phantom(saved_precision(stage2_phantom.x_um), saved_precision(stage2_phantom.y_um),
                              saved_precision(stage2_phantom.z_um), saved_precision(stage2_phantom.energy_pct))).levels
    at_aim = refine(stage2_phantom, layers_target, schedule, threads=1, aim=rendered)
    assert at_aim.iterations == 0 and at_aim.stop_reason == "ceiling"
    assert at_aim.components == at_aim.initial_components
    off = rendered.copy()
    off[0, 0] = GREY_LUT[255] if off[0, 0] != GREY_LUT[255] else GREY_LUT[0]
    runs = refine(stage2_phantom, layers_target, schedule, threads=1, aim=off)
    assert runs.iterations == 2 and runs.stop_reason == "schedule"


def test_the_pixel_and_level_phases_compare_with_the_aimed_levels(stage2_phantom, layers_target):
    """With ``aim``, the pixel term alone and the level term alone compare the rendering with the aimed levels
    (a level the scanner never writes cannot be reached); without, with the target. At zero learning rates the
    first step's loss is the term at the start: mean|P − P*| + mean((P − P*)²), P* the aim's scan or the
    target's; and mean e + mean e², e = max(|P̃ − C| − f·H, 0), C and H the centre and half-width of each
    compared level's interval (e = |P − P*| at level 0)."""
    from octcl.render import render

    start = Phantom(*(saved_precision(getattr(stage2_phantom, name)) for name in ("x_um", "y_um", "z_um",
                                                                                  "energy_pct")))
    rendering = render(start)
    aim = rendering.levels.copy()
    aim[::7, ::5] = np.where(aim[::7, ::5] > 128, GREY_LUT[0], GREY_LUT[255])  # far from the start somewhere
    scan, unquantised = scan_of_levels(rendering.levels).astype(np.float64), QUANTISER_SLOPE * rendering.display
    low, high = display_interval_of_level()
    centre, half = QUANTISER_SLOPE * (low + high) / 2, QUANTISER_SLOPE * (high - low) / 2
    for levels_compared, given in ((aim, aim), (np.asarray(layers_target), None)):
        difference = scan - scan_of_levels(levels_compared).astype(np.float64)
        excess = np.where(levels_compared == 0, np.abs(difference),
                          np.maximum(np.abs(unquantised - centre[levels_compared])
                                     - LEVEL_MARGIN * half[levels_compared], 0.0))
        for terms, error in (("pixel", difference), ("level", excess)):
            schedule = RefineSchedule(phases=(Phase(1, 0.0, 0.0, terms=terms),), restarts=(), min_gain=None)
            result = refine(start, layers_target, schedule, threads=1, aim=given)
            loss = next(entry["loss"] for entry in result.trace if entry["loss"] is not None)
            assert loss == pytest.approx(np.abs(error).mean() + (error**2).mean(), rel=1e-5), terms


class _CostlyScore:
    """An exact score that says a call costs ``seconds``; it answers with ``score`` (without one it fails)."""

    def __init__(self, seconds, score=None):
        self.seconds, self.score = seconds, score

    def cost_s(self, levels):
        return self.seconds

    def __call__(self, levels):
        if self.score is None:
            raise AssertionError("a score left out was computed")
        return self.score(levels)


@pytest.mark.clock
def test_a_score_that_would_end_past_score_by_is_left_out(stage2_phantom, layers_target):
    """``score_by``: where the scorer's own cost ends past it, nothing is scored, nothing refined, and the
    result says so (components None); at its aim the reason is ``ceiling``, elsewhere ``deadline``."""
    from octcl.render import render

    schedule = RefineSchedule(phases=(Phase(2, 0.01, 0.02, terms="no_lpips"),), restarts=(), score_every=2)
    rendered = render(Phantom(saved_precision(stage2_phantom.x_um), saved_precision(stage2_phantom.y_um),
                              saved_precision(stage2_phantom.z_um), saved_precision(stage2_phantom.energy_pct))).levels
    for aim, reason in ((rendered, "ceiling"), (None, "deadline")):
        result = refine(stage2_phantom, layers_target, schedule, threads=1, aim=aim, exact_score=_CostlyScore(5.0),
                        deadline=time.monotonic() + 600, score_by=time.monotonic() + 1.0)
        assert result.components is None and result.initial_components is None
        assert result.stop_reason == reason and result.iterations == 0
        np.testing.assert_array_equal(result.levels, rendered)
        np.testing.assert_array_equal(result.phantom.z_um, saved_precision(stage2_phantom.z_um))
    # The same cost within score_by is computed.
    scored = refine(stage2_phantom, layers_target, schedule, threads=1, aim=rendered,
                    exact_score=_CostlyScore(5.0, ExactScore(layers_target)),
                    deadline=time.monotonic() + 600, score_by=time.monotonic() + 600)
    assert scored.components is not None and scored.stop_reason == "ceiling"


def test_schedule_checks():
    with pytest.raises(ValueError, match="iterations"):
        Phase(-1, 0.01, 0.01)
    with pytest.raises(ValueError, match="score_every"):
        RefineSchedule(score_every=0)
    for bad in (0, 1.5):
        with pytest.raises(ValueError, match="patience"):
            RefineSchedule(patience=bad)
    with pytest.raises(ValueError, match="min_gain"):
        RefineSchedule(min_gain=float("nan"))
    for bad in (0, 2.0):
        with pytest.raises(ValueError, match="lpips_every"):
            RefineSchedule(lpips_every=bad)
    for bad in (-1, 1.0):
        with pytest.raises(ValueError, match="max_falls"):
            RefineSchedule(max_falls=bad)
    with pytest.raises(ValueError, match="fall_tolerance"):
        RefineSchedule(fall_tolerance=float("nan"))
    with pytest.raises(ValueError, match="terms"):
        Phase(1, 0.01, 0.01, terms="lpips")
    with pytest.raises(ValueError, match="terms"):
        LossWeights().for_terms("struct")
    for bad in (0, 1.5):
        with pytest.raises(ValueError, match="patience"):
            Phase(1, 0.01, 0.01, patience=bad)
    with pytest.raises(ValueError, match="hinge"):
        Phase(1, 0.0, 0.0, terms="hinge", patience=2)
    for bad in (0, 1.5):
        with pytest.raises(ValueError, match="restart_patience"):
            RefineSchedule(restart_patience=bad)
    own = RefineSchedule(min_gain=3e-6, restart_patience=2)
    assert own.with_stop_rule("restarts") == own and own.fixed_length().with_stop_rule("restarts").min_gain == 1e-5
    rules = {rule: RefineSchedule().with_stop_rule(rule) for rule in ("restarts", "stall", "none")}
    assert rules["restarts"] == RefineSchedule() and rules["none"] == RefineSchedule().fixed_length()
    assert (rules["stall"].patience, rules["stall"].min_gain) == (2, RefineSchedule().min_gain)
    with pytest.raises(ValueError, match="stop rule"):
        RefineSchedule().with_stop_rule("never")
    published = RefineSchedule.published()
    assert published.total_iterations == 1400
    assert [restart.lr_z_um for restart in published.restarts] == [0.002, 0.002, 0.001, 0.0005]


def test_truncated_schedule_runs_by_counts_alone(stage2_phantom, layers_target, slow_clock):
    """The first 5 steps of a 2 + 4 schedule: exact scores where the whole schedule has them, no clock.

    The restart's evaluation stays half-way through its whole length (step
    2), not half-way through what is left of it (3), and a clock 1000× slower
    changes nothing when neither a deadline nor a time-chosen thread count
    is involved.
    """
    import octcl.host.stage3.refine as refine_module

    whole = RefineSchedule(phases=(Phase(2, 0.01, 0.02, terms="no_lpips"),),
                           restarts=(Phase(4, 0.005, 0.01, terms="no_lpips"),), score_every=2)
    schedule = whole.truncated(5)
    assert schedule.total_iterations == 5 and whole.total_iterations == 6
    results = [refine(stage2_phantom, layers_target, schedule, threads=1)]
    slow_clock(refine_module)
    results.append(refine(stage2_phantom, layers_target, schedule, threads=1))
    for result in results:
        assert result.iterations == 5 and not result.stopped_by_deadline and result.torch_threads == 1
        scored = [(entry["stage"], entry["iteration"]) for entry in result.trace if entry["score"] is not None]
        assert scored == [("initial", 0), ("refine", 2), ("restart 1", 2), ("restart 1", 3)]
    np.testing.assert_array_equal(results[0].phantom.z_um, results[1].phantom.z_um)
    np.testing.assert_array_equal(results[0].phantom.energy_pct, results[1].phantom.energy_pct)
    assert results[0].components == results[1].components
    for bad in (-1, 7, 2.5):
        with pytest.raises(ValueError, match="iterations must be a whole number in \\[0, 6\\]"):
            whole.truncated(bad)


def test_ceiling_fails_loudly(stage2_phantom, layers_target):
    from octcl.host.stage3.refine import TimeBudgetExceeded

    schedule = RefineSchedule(phases=(Phase(5, 0.01, 0.02, terms="no_lpips"),), restarts=())
    with pytest.raises(TimeBudgetExceeded, match="in stage 3 \\(refine\\) after 0 of 5 iterations"):
        refine(stage2_phantom, layers_target, schedule, ceiling=time.monotonic(), threads=1)


def test_the_loss_is_the_same_whatever_thread_count_built_it(layers_target):
    """Stage 3 builds its loss at its first use, at the loss's thread count: the target's LPIPS
    features must not depend on it (without oneDNN, AlexNet's layers 2–5 differ between 1 and 2
    threads, which changed a fixed schedule's file with ``--threads``)."""
    from octcl.host.pipeline.target import target_scan

    scan = target_scan(layers_target)
    display = np.clip(scan.astype(np.float64) + 0.01 * np.random.default_rng(0).standard_normal(scan.shape), 0, 1)
    previous = torch.get_num_threads()
    values = {}
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            loss = DisplayLoss(scan)
            torch.set_num_threads(1)  # the same thread count for the evaluation itself
            values[threads] = loss(display)
    finally:
        torch.set_num_threads(previous)
    assert values[1].loss == values[2].loss
    np.testing.assert_array_equal(values[1].grad_display, values[2].grad_display)


def test_the_clock_keeps_the_last_duration_or_the_longest():
    """An operation of steady cost is timed by its last call; one whose cost varies (a hinge iteration, one
    evaluation or several) by its longest, so that what must follow it (the last iterate's score) still fits."""
    clock = RefineClock(time.monotonic() + 10.0)
    for seconds in (0.3, 0.1):
        clock.record("render", seconds)
        clock.record("hinge", seconds, longest=True)
    assert clock.durations == {"render": 0.1, "hinge": 0.3}
    assert clock.fits("hinge") and not clock.fits(*["hinge"] * 40)
