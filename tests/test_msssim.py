"""MS-SSIM: the exact official value and its differentiable torch twin."""

import numpy as np
import pytest
import torch

from octcl._msssim import MsssimReference, _gaussian_window, _ssim_and_cs, msssim_exact, msssim_torch
from octcl.scorer import MAP_NAMES, _msssim_input

# Both twins compute the same float64 maths; they differ only in the order of
# the rounding steps (separable versus 2-D window, torch versus scipy sums),
# which moves a value near 1 by a few 1e-16 per step.
TWIN_TOLERANCE = 1e-12


def _random_pair(rng, shape, noise):
    ref = rng.integers(0, 256, shape).astype(np.uint8)
    pred = np.clip(ref + rng.normal(0, noise, shape), 0, 255).astype(np.uint8)
    return ref, pred


def test_exact_reproduces_official_values(official_uniform_maps, official_uniform_metrics):
    """All four maps of Uniform_A against Uniform_B, to 1e-12 of the official CSV."""
    ref_maps, pred_maps = official_uniform_maps
    for name in MAP_NAMES:
        value = msssim_exact(_msssim_input(ref_maps[name]), _msssim_input(pred_maps[name]))
        assert value == pytest.approx(official_uniform_metrics[name]["MS-SSIM"], abs=1e-12), name


def test_gaussian_window_is_normalised_and_symmetric():
    window = _gaussian_window()
    assert window.shape == (11, 11)
    assert window.sum() == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_array_equal(window, np.rot90(window, 2))
    assert window.argmax() == 60


def test_identical_images_score_one():
    levels = np.random.default_rng(0).integers(0, 256, (64, 96)).astype(np.uint8)
    assert msssim_exact(levels, levels) == pytest.approx(1.0, abs=1e-15)


def test_a_reference_taken_once_gives_the_same_bits(official_uniform_maps):
    """MsssimReference computed once and reused: each value to the last bit of a call without it, and a
    reference refuses an image of another size."""
    ref_maps, pred_maps = official_uniform_maps
    rng = np.random.default_rng(4)
    for name in MAP_NAMES:
        ref = _msssim_input(ref_maps[name])
        reference = MsssimReference(ref)
        noisy = np.clip(ref + rng.normal(0, 6, ref.shape), 0, 255).astype(np.uint8)
        for pred in (_msssim_input(pred_maps[name]), noisy, ref):
            assert msssim_exact(ref, pred, reference) == msssim_exact(ref, pred), name
    with pytest.raises(ValueError, match="differ in size"):
        msssim_exact(ref, ref[:, :-1], reference)


def test_exact_refuses_non_uint8_and_mismatched_sizes():
    levels = np.zeros((32, 32), np.uint8)
    with pytest.raises(ValueError, match="uint8"):
        msssim_exact(levels.astype(float), levels)
    with pytest.raises(ValueError, match="differ in size"):
        msssim_exact(levels, levels[:, :31])


def test_torch_twin_matches_exact_on_official_maps(official_uniform_maps):
    """Twin on ``levels / 255`` against exact on the levels, to 1e-12.

    The only difference between the two metrics is that the exact one works
    on 8-bit levels (the official uint8 truncation happens before it); fed
    the same levels, they agree to float64 rounding.
    """
    ref_maps, pred_maps = official_uniform_maps
    ref_levels = np.stack([_msssim_input(ref_maps[name]) for name in MAP_NAMES])
    pred_levels = np.stack([_msssim_input(pred_maps[name]) for name in MAP_NAMES])
    twin = msssim_torch(torch.from_numpy(ref_levels / 255.0), torch.from_numpy(pred_levels / 255.0))
    exact = [msssim_exact(ref, pred) for ref, pred in zip(ref_levels, pred_levels)]
    np.testing.assert_allclose(twin.numpy(), exact, rtol=0, atol=TWIN_TOLERANCE)


@pytest.mark.parametrize("shape", [(256, 512), (33, 47), (40, 40)])
def test_torch_twin_matches_exact_on_perturbed_images(shape):
    """Random and noise-perturbed 8-bit images, odd sizes and fewer scales, to 1e-12.

    (40, 40) has room for only two scales; (33, 47) exercises the odd-size
    decimation. As above, fed 8-bit levels the twins differ by rounding only.
    """
    rng = np.random.default_rng(sum(shape))
    pairs = [_random_pair(rng, shape, noise) for noise in (5.0, 40.0)]
    pairs.append((pairs[0][0], 255 - pairs[0][0]))  # anti-correlated: negative cs terms
    ref = torch.from_numpy(np.stack([ref for ref, _ in pairs]) / 255.0)
    pred = torch.from_numpy(np.stack([pred for _, pred in pairs]) / 255.0)
    twin = msssim_torch(ref, pred)
    assert twin.shape == (len(pairs),)
    exact = [msssim_exact(ref_levels, pred_levels) for ref_levels, pred_levels in pairs]
    np.testing.assert_allclose(twin.numpy(), exact, rtol=0, atol=TWIN_TOLERANCE)
    anti_ref, anti_pred = (image.astype(float) for image in pairs[2])
    assert _ssim_and_cs(anti_ref, anti_pred, _gaussian_window())[1] < 0


def test_torch_twin_in_float32_is_close():
    """float32 input is computed in float32: agreement to 1e-5 on a 256×512 pair."""
    ref_levels, pred_levels = _random_pair(np.random.default_rng(3), (256, 512), 20.0)
    twin = msssim_torch(torch.from_numpy(ref_levels / np.float32(255)), torch.from_numpy(pred_levels / np.float32(255)))
    assert twin.dtype == torch.float32
    assert twin.item() == pytest.approx(msssim_exact(ref_levels, pred_levels), abs=1e-5)


@pytest.mark.parametrize(
    "ref_kind, pred_kind",
    [("grey", "grey"), ("black", "black"), ("white", "white"), ("black", "white"),
     ("grey", "noise"), ("black", "noise"), ("white", "noise"), ("noise", "inverted")],
)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_torch_twin_gradients_are_finite(ref_kind, pred_kind, dtype):
    rng = np.random.default_rng(7)
    noise = rng.random((64, 96))
    images = {"grey": np.full((64, 96), 0.5), "black": np.zeros((64, 96)), "white": np.ones((64, 96)),
              "noise": noise, "inverted": 1 - noise}
    ref = torch.tensor(images[ref_kind], dtype=dtype, requires_grad=True)
    pred = torch.tensor(images[pred_kind], dtype=dtype, requires_grad=True)
    value = msssim_torch(ref, pred)
    value.backward()
    assert torch.isfinite(value)
    assert torch.isfinite(ref.grad).all() and torch.isfinite(pred.grad).all()
