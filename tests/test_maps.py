"""Tests of octcl.maps: exact official maps, their torch twins and writing them."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

import octcl._io
from octcl import maps
from octcl._io import GREY_LUT, read_png_rgb, read_scan

OFFICIAL_SCANS = ("Scan_Exp1_Uniform_A", "Scan_Exp1_Uniform_B", "Scan_Exp2_Layers_A")

# Twin vs exact, on the official scans (float32 input). The twin computes the
# same maths in torch with another summation order (separable box means,
# torch's cumsum), measured at most 1e-6 from the exact normalised map; we
# allow 5x that. A pixel within that distance of one of the 256 quantisation
# steps can land on the other side, expected for about 2 * 1e-6 * 256 = 0.05 %
# of pixels at most; measured: at least 99.994 % identical levels, all within
# one colour-table step. One step is 2 levels where the 'gray' table
# truncates (24 of its 256 entries), hence the maximum difference of 2.
TWIN_MAX_VALUE_ERROR = 5e-6
TWIN_MIN_IDENTICAL_LEVELS = 0.9995
TWIN_MIN_WITHIN_ONE_LEVEL = 0.9999
TWIN_MAX_LEVEL_DIFFERENCE = 2


@pytest.fixture(scope="module")
def official(official_data):
    """Per official scan: (scan path, float32 scan, {map: official uint8 levels})."""
    cases = {}
    for stem in OFFICIAL_SCANS:
        official_levels = {}
        for name in maps.MAP_NAMES:
            rgb = read_png_rgb(official_data / f"{stem}_{name}.png")
            assert (rgb == rgb[..., :1]).all(), f"{stem}_{name}.png is not grey"
            official_levels[name] = rgb[..., 0]
        path = official_data / f"{stem}.png"
        cases[stem] = (path, read_scan(path), official_levels)
    return cases


def _exact_display_values(values: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Exact maps normalised as imsave shows them, before the 8-bit quantisation."""
    shown = {}
    for name, value in values.items():
        clipped = maps.display_normalise(value, *maps.display_window(name, value))
        low, high = clipped.min(), clipped.max()
        shown[name] = (clipped - low) / (high - low) if high > low else np.zeros_like(clipped)
    return shown


# --- exact maps --------------------------------------------------------------


@pytest.mark.parametrize("stem", OFFICIAL_SCANS)
def test_map_levels_identical_to_official_pngs(official, stem):
    _, scan, official_levels = official[stem]
    levels = maps.map_levels(scan)
    assert set(levels) == set(maps.MAP_NAMES)
    for name in maps.MAP_NAMES:
        assert levels[name].dtype == np.uint8 and levels[name].shape == scan.shape
        mismatched = np.count_nonzero(levels[name] != official_levels[name])
        assert mismatched == 0, f"{stem} {name}: {mismatched} pixels differ"


def test_maps_keep_the_scan_float32_arithmetic(official):
    _, scan, _ = official[OFFICIAL_SCANS[0]]
    for value in maps.map_values(scan).values():
        assert value.dtype == np.float32


def test_linear_intensity_spans_four_decades():
    scan = np.array([[0.0, 0.5, 1.0]] * 2, dtype=np.float32)
    intensity = maps.linear_intensity(scan)
    np.testing.assert_allclose(intensity[0], [1.0, 100.0, 1e4], rtol=1e-6)
    # A 0..255 array is rescaled as the processor does.
    np.testing.assert_array_equal(maps.linear_intensity(scan * np.float32(255)), intensity)


def test_oac_follows_the_depth_resolved_formula():
    scan = np.random.default_rng(3).random((30, 4))
    intensity = 10.0 ** (4 * scan)
    below = np.array([intensity[row + 1 :].sum(axis=0) for row in range(30)])
    expected = intensity / (2 * maps.PIXEL_SIZE_UM * (below + 0.5 * intensity))
    np.testing.assert_allclose(maps.oac(scan), expected, rtol=1e-9)
    # The bottom pixel sees only itself (half weight): mu = 1/h per um.
    np.testing.assert_allclose(maps.oac(scan)[-1], 1 / maps.PIXEL_SIZE_UM, rtol=1e-9)


def test_speckle_contrast_is_std_over_mean_in_a_reflected_box():
    values = np.random.default_rng(4).random((31, 27)) + 0.1
    half = maps.SPECKLE_WINDOW // 2
    padded = np.pad(values, (half, half - 1), mode="symmetric")
    windows = np.lib.stride_tricks.sliding_window_view(padded, (maps.SPECKLE_WINDOW,) * 2)
    contrast = windows.std(axis=(-2, -1)) / windows.mean(axis=(-2, -1))
    border = maps.SPECKLE_BORDER
    expected = np.pad(contrast[border:-border, border:-border], border, mode="edge")
    np.testing.assert_allclose(maps.speckle_contrast(values), expected, rtol=1e-9)


def test_grey_lut_truncates_like_matplotlib():
    table = GREY_LUT
    assert table[0] == 0 and table[-1] == 255
    assert len(np.unique(table)) == 232
    assert table[33] == 32 and table[34] == 34


def test_matplotlib_grey_levels_rescale_to_the_array_range():
    ramp = np.linspace(0, 1, 257, dtype=np.float32)[None]
    table = GREY_LUT
    expected = table[np.minimum(np.arange(257), 255)]
    np.testing.assert_array_equal(maps.matplotlib_grey_levels(ramp)[0], expected)
    # imsave stretches an array that does not reach 0 and 1 to its own range.
    squeezed = np.float32(0.25) + ramp * np.float32(0.5)
    np.testing.assert_array_equal(
        maps.matplotlib_grey_levels(squeezed), maps.matplotlib_grey_levels(ramp)
    )
    # A constant array is black, whatever its value (Normalize with vmin == vmax).
    constant = np.full((3, 4), 0.7, dtype=np.float32)
    np.testing.assert_array_equal(maps.matplotlib_grey_levels(constant), 0)


def test_flat_scan_gives_black_speckle_maps():
    levels = maps.map_levels(np.full((40, 50), 0.5, dtype=np.float32))
    np.testing.assert_array_equal(levels["SC"], 0)
    # OAC still varies with depth: a flat scan is a uniformly attenuating medium.
    assert levels["OAC"].min() == 0 and levels["OAC"].max() == 255


def test_map_levels_rejects_non_images():
    with pytest.raises(ValueError):
        maps.map_levels(np.zeros((4, 30, 30), dtype=np.float32))
    with pytest.raises(ValueError):
        maps.map_levels(np.zeros((30, 30), dtype=np.uint8))
    with pytest.raises(ValueError, match="border"):
        maps.map_levels(np.zeros((30, 20), dtype=np.float32))


# --- torch twins -------------------------------------------------------------


@pytest.mark.parametrize("stem", OFFICIAL_SCANS)
def test_twin_matches_exact_maps(official, stem):
    _, scan, _ = official[stem]
    exact_shown = _exact_display_values(maps.map_values(scan))
    exact_levels = maps.map_levels(scan)
    with torch.no_grad():
        twin = maps.maps_torch(torch.from_numpy(scan))
    for name in maps.MAP_NAMES:
        value = twin[name].numpy()
        assert value.shape == scan.shape
        assert np.abs(value - exact_shown[name]).max() <= TWIN_MAX_VALUE_ERROR, name
        difference = np.abs(maps.matplotlib_grey_levels(value).astype(int) - exact_levels[name])
        assert np.mean(difference == 0) >= TWIN_MIN_IDENTICAL_LEVELS, name
        assert np.mean(difference <= 1) >= TWIN_MIN_WITHIN_ONE_LEVEL, name
        assert difference.max() <= TWIN_MAX_LEVEL_DIFFERENCE, name
        # The continuous value sits within the quantisation of the saved level.
        offset = exact_levels[name] / 255 - value
        assert offset.min() > -2 / 255 and offset.max() <= 1 / 255 + 1e-6, name


@pytest.mark.parametrize(
    "scan",
    [
        pytest.param(torch.full((64, 80), 0.5), id="flat"),
        pytest.param(torch.zeros(64, 80), id="black"),
        pytest.param(torch.ones(64, 80), id="white"),
        pytest.param(torch.rand(64, 80, generator=torch.Generator().manual_seed(0)), id="random"),
    ],
)
def test_twin_gradients_are_finite(scan):
    scan = scan.clone().requires_grad_(True)
    twin = maps.maps_torch(scan)
    weights = torch.rand(scan.shape, generator=torch.Generator().manual_seed(1))
    for name in maps.MAP_NAMES:
        assert torch.isfinite(twin[name]).all(), name
        assert 0 <= twin[name].min() and twin[name].max() <= 1, name
        (gradient,) = torch.autograd.grad((twin[name] * weights).sum(), scan, retain_graph=True)
        assert torch.isfinite(gradient).all(), name
    # OAC changes with every pixel, so its gradient reaches every pixel.
    (gradient,) = torch.autograd.grad((twin["OAC"] * weights).sum(), scan)
    assert (gradient != 0).all()


def test_twin_accepts_batches():
    generator = torch.Generator().manual_seed(2)
    batch = torch.rand(3, 48, 40, generator=generator, dtype=torch.float64)
    together = maps.maps_torch(batch)
    for index in range(3):
        alone = maps.maps_torch(batch[index])
        for name in maps.MAP_NAMES:
            assert together[name].shape == batch.shape
            torch.testing.assert_close(together[name][index], alone[name])


def test_twin_computes_the_maps_asked_for():
    generator = torch.Generator().manual_seed(3)
    scan = torch.rand(48, 40, generator=generator, dtype=torch.float64)
    every = maps.maps_torch(scan)
    for names in (["SC"], ["RSC"], ["OAC"], ["RSC", "SC"]):
        some = maps.maps_torch(scan, names)
        assert list(some) == [name for name in maps.MAP_NAMES if name in names]
        for name in names:
            torch.testing.assert_close(some[name], every[name], rtol=0, atol=0)


def test_twin_rejects_other_inputs():
    with pytest.raises(ValueError):
        maps.maps_torch(torch.zeros(30, 30, dtype=torch.int64))
    with pytest.raises(ValueError):
        maps.maps_torch(torch.zeros(30))
    with pytest.raises(ValueError, match="unknown maps.*Struct"):
        maps.maps_torch(torch.zeros(30, 30), ["Struct", "SC"])


# --- writing -----------------------------------------------------------------


def test_write_maps_writes_three_opaque_grey_pngs(official, tmp_path):
    path, scan, official_levels = official[OFFICIAL_SCANS[2]]
    written = maps.write_maps(path, out_dir=tmp_path)
    assert {name: p.name for name, p in written.items()} == {
        name: f"{path.stem}_{name}.png" for name in maps.MAP_NAMES
    }
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in written.values())
    for name, written_path in written.items():
        with Image.open(written_path) as image:
            assert image.mode == "RGBA" and image.size == (scan.shape[1], scan.shape[0])
            rgba = np.asarray(image)
        assert (rgba[..., 3] == 255).all()
        assert (rgba[..., :3] == official_levels[name][..., None]).all()


def test_write_maps_defaults_to_the_scan_folder(official, tmp_path):
    source, _, _ = official[OFFICIAL_SCANS[0]]
    scan_path = tmp_path / "target.png"
    scan_path.write_bytes(source.read_bytes())
    written = maps.write_maps(scan_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "target.png", "target_OAC.png", "target_RSC.png", "target_SC.png"
    ]
    assert all(p.parent == tmp_path for p in written.values())


@pytest.mark.parametrize("stem", OFFICIAL_SCANS)
def test_write_maps_of_a_npy_writes_the_png_maps_byte_for_byte(official, tmp_path, stem):
    """``scan.npy`` of a scan's grey levels: the same three files as ``scan.png``, beside it or in ``out_dir``."""
    path, _, official_levels = official[stem]
    rgb = read_png_rgb(path)
    for kind in ("png", "npy"):
        (tmp_path / kind).mkdir()
    (tmp_path / "png" / "scan.png").write_bytes(path.read_bytes())
    np.save(tmp_path / "npy" / "scan.npy", rgb[..., 0])
    from_png = maps.write_maps(tmp_path / "png" / "scan.png")
    from_npy = maps.write_maps(tmp_path / "npy" / "scan.npy")
    assert sorted(p.name for p in (tmp_path / "npy").iterdir()) == [
        "scan.npy", "scan_OAC.png", "scan_RSC.png", "scan_SC.png"
    ]
    for name in maps.MAP_NAMES:
        assert from_npy[name].read_bytes() == from_png[name].read_bytes(), name
        np.testing.assert_array_equal(read_png_rgb(from_npy[name])[..., 0], official_levels[name])
    elsewhere = maps.write_maps(tmp_path / "npy" / "scan.npy", out_dir=tmp_path / "maps")
    assert all(elsewhere[name].read_bytes() == from_png[name].read_bytes() for name in maps.MAP_NAMES)


@pytest.mark.parametrize("shape, dtype, message", [
    ((255, 512), np.uint8, "array is 255x512 (rows x columns), expected 256x512"),
    ((256, 512), np.float64, "float64 array; a B-scan is a 2-D uint8 array"),
    ((256, 512, 3), np.uint8, "3-D array of shape (256, 512, 3)"),
])
def test_write_maps_of_a_npy_that_is_not_a_scan_writes_nothing(tmp_path, shape, dtype, message):
    """A .npy must be a SynthOCT scan (256x512 uint8), though a PNG of any size has maps."""
    np.save(tmp_path / "scan.npy", np.zeros(shape, dtype))
    with pytest.raises(octcl._io.ImageFormatError) as caught:
        maps.write_maps(tmp_path / "scan.npy")
    assert str(caught.value).startswith(f"{tmp_path / 'scan.npy'}: {message}")
    assert [p.name for p in tmp_path.iterdir()] == ["scan.npy"]


def test_write_maps_replaces_existing_files_atomically(official, tmp_path, monkeypatch):
    path, _, official_levels = official[OFFICIAL_SCANS[1]]
    destination = tmp_path / f"{path.stem}_SC.png"
    destination.write_bytes(b"old map")
    with open(destination, "rb") as reader_of_old_file:
        maps.write_maps(path, out_dir=tmp_path)
        # The new file was renamed over the old one, never written into it.
        assert reader_of_old_file.read() == b"old map"
    np.testing.assert_array_equal(read_png_rgb(destination)[..., 0], official_levels["SC"])
    assert len(list(tmp_path.iterdir())) == 3

    # A write that fails leaves the previous file whole and no temporary file.
    previous = destination.read_bytes()

    def failing_sync(fd):  # the data could not all reach the disk
        raise OSError("disk full")

    monkeypatch.setattr(octcl._io.os, "fsync", failing_sync)
    with pytest.raises(OSError, match="disk full"):
        maps.write_maps(path, out_dir=tmp_path)
    assert destination.read_bytes() == previous
    assert len(list(tmp_path.iterdir())) == 3
