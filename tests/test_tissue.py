"""A phantom as tissue (octcl/tissue.py): its transmission, shadow, band densities and attenuation."""

import math

import numpy as np
import pytest

from octcl import _reference as ref
from octcl.config import DEFAULT_CONFIG, ScannerConfig
from octcl.phantom import Phantom
from octcl.tissue import (BAND_UM, VISIBLE_LEVEL, attenuation_map, band_densities, bands_with_signal,
                          scan_attenuation, shadow_db, tissue_figures, transmission_map)

SMALL = ScannerConfig(depth_pixels=32, a_scans=48, xmax_um=288.0)


def test_the_transmission_map_is_the_scanners_product_over_the_scatterers_above():
    """T at the top of each pixel row against the product written out scatterer by scatterer (physics.md §2 step 4),
    over every scatterer: those the map leaves out (beyond the float64 scanner's reach) change T by < 1e-12."""
    rng = np.random.default_rng(3)
    n = 400
    phantom = Phantom(rng.uniform(-140, 140, n), rng.uniform(-4, 4, n), rng.uniform(0, 190, n),
                      rng.uniform(0.01, 20, n))
    got = transmission_map(phantom, SMALL)
    positions = ref.ascan_positions_um(SMALL)
    amplitude_sq = phantom.energy_pct / 100
    for row in (0, 5, 17, 31):
        for line in (0, 7, 24, 47):
            above = phantom.z_um < row * SMALL.pixel_size_um
            beam_sq = ref.beam_weight(positions[line] - phantom.x_um[above], phantom.y_um[above],
                                      SMALL.beam_radius_um) ** 2
            expected = np.prod(1 - np.minimum(beam_sq * amplitude_sq[above], 1))
            assert got[row, line] == pytest.approx(expected, rel=1e-12, abs=1e-300)


def test_a_layer_on_every_line_dims_what_is_below_by_its_lateral_sum():
    """One scatterer of energy E on every A-scan line at 50 µm: below it a line far from the edges keeps
    Π_d (1 − e^{−2(dΔx)²/w0²}·E/100), above it all the light."""
    config = SMALL
    x = ref.ascan_positions_um(config)
    energy = 4.0
    phantom = Phantom(x, np.zeros_like(x), np.full_like(x, 50.0), np.full_like(x, energy))
    transmission = transmission_map(phantom, config)
    d = np.arange(-6, 7)
    expected = np.prod(1 - np.exp(-2 * (d * config.lateral_pitch_um) ** 2 / config.beam_radius_um**2) * energy / 100)
    assert np.all(transmission[:9] == 1.0)
    np.testing.assert_allclose(transmission[9:, 20], expected, rtol=1e-12)


def test_the_shadow_is_read_at_the_deepest_visible_row_of_each_line():
    transmission = np.tile(np.logspace(0, -3, 10)[:, None], (1, 4))  # 0 to −60 dB down each line
    levels = np.zeros((10, 4), np.uint8)
    levels[:3, 0] = levels[:6, 1] = levels[:3, 2] = VISIBLE_LEVEL  # deepest visible rows 2, 5, 2; line 3 none
    levels[8, 2] = VISIBLE_LEVEL - 1                                # not visible
    assert shadow_db(transmission, levels) == pytest.approx(-20 * np.log10(transmission[2, 0]))
    assert shadow_db(transmission, np.zeros_like(levels)) is None


def test_band_densities_sum_what_the_beam_sees_of_each_band():
    config = DEFAULT_CONFIG
    phantom = Phantom(np.array([0.0, 10.0, 1500.0, 1540.0]), np.array([0.0, 5.0, 0.0, 0.0]),
                      np.array([10.0, 191.0, 200.0, 300.0]), np.array([1.0, 2.0, 3.0, 4.0]))
    densities = band_densities(phantom, config)
    assert densities.size == math.ceil(config.depth_range_um / BAND_UM)
    assert densities[0] == pytest.approx(1.0 + 2.0 * math.exp(-2 * 25 / config.beam_radius_um**2))
    assert densities[1] == pytest.approx(3.0)  # x = 1540 µm is outside |x| ≤ Xmax/2
    assert densities[2:].sum() == 0


def test_bands_with_signal_count_their_pixels_above_level_zero():
    levels = np.zeros((256, 512), np.uint8)
    levels[:32, :int(0.4 * 512) + 1] = 10
    levels[32:64, :int(0.4 * 512) - 10] = 10
    assert bands_with_signal(levels).tolist()[:3] == [True, False, False]


def test_an_exponential_transmission_has_one_attenuation_coefficient():
    config = DEFAULT_CONFIG
    mu_per_mm = 3.5
    depth_um = np.arange(config.depth_pixels) * config.pixel_size_um
    transmission = np.tile(np.exp(-mu_per_mm * depth_um / 1000)[:, None], (1, config.a_scans))
    np.testing.assert_allclose(attenuation_map(transmission, config), mu_per_mm, rtol=1e-9)


def test_the_scans_own_estimate_of_an_endless_exponential_decay_is_tanh_mu_delta_over_delta():
    """Intensity e^{−2µz} down a line long enough that what is below the last row is negligible: the
    half-pixel depth-resolved estimate is tanh(µΔ)/Δ (Δ in mm) everywhere but the last rows; a line without
    signal has µ = 0."""
    config = ScannerConfig(depth_pixels=400, a_scans=3, xmax_um=18.0)
    delta_mm = config.pixel_size_um / 1000
    mu_per_mm = np.array([4.0, 8.0, 0.0])  # below row 150 and the last: e^{−2·4·1.5} < 1e−5 of the row's left
    depth_mm = np.arange(config.depth_pixels)[:, None] * delta_mm
    magnitude = np.exp(-mu_per_mm * depth_mm) * (mu_per_mm > 0)
    got = scan_attenuation(magnitude, config)
    np.testing.assert_allclose(got[:150, :2], np.tanh(mu_per_mm[:2] * delta_mm) / delta_mm * np.ones((150, 1)),
                               rtol=1e-5)
    assert np.all(got[:, 2] == 0)


def test_the_scans_own_estimate_finds_the_skin_phantoms_attenuation():
    """From the 8-bit scan of a skin phantom (at the scanner's 51 dB), the median µ over the visible tissue is
    within 15 % of the one the phantom's own shadowing makes (seeds 5 and 7: 0.93 and 0.95 of it); the
    figures carry both."""
    from octcl.host.stage1.levels import target_magnitude
    from octcl.render import render

    skin = Phantom.skin(2)
    levels = render(skin).levels
    visible = levels >= VISIBLE_LEVEL
    figures = tissue_figures(skin, levels)
    assert figures["attenuation_per_mm_median"] == pytest.approx(
        np.median(attenuation_map(transmission_map(skin))[visible]))
    assert figures["scan_attenuation_per_mm_median"] == np.median(scan_attenuation(target_magnitude(levels))[visible])
    assert figures["scan_attenuation_per_mm_median"] == pytest.approx(figures["attenuation_per_mm_median"], rel=0.15)


def test_a_tissue_scale_phantom_shadows_and_a_tiny_one_does_not():
    """The skin phantom (median E 0.36 %) loses tens of dB by the bottom of its visible tissue; the same phantom
    with every energy divided by 1e10 renders alike and loses nothing."""
    from octcl.render import render

    skin = Phantom.skin(1)
    levels = render(skin).levels
    tiny = Phantom(skin.x_um, skin.y_um, skin.z_um, skin.energy_pct * 1e-10)
    figures, tiny_figures = tissue_figures(skin, levels), tissue_figures(tiny, levels)
    assert figures["shadow_db"] > 20 and tiny_figures["shadow_db"] < 1e-6
    assert figures["energy_pct"]["p50"] == pytest.approx(1e10 * tiny_figures["energy_pct"]["p50"])
    assert figures["attenuation_per_mm_median"] > 1
