"""octcl.render: the public render keeps one OpenCL scanner per (config, settings, device)."""

import numpy as np

from octcl import Phantom, render
from octcl.device.runtime import select_device
from octcl.device.scanner import KernelSettings, ScannerKernels
from octcl.config import DEFAULT_CONFIG
from octcl.render import _scanner_kernels


def small_phantom(seed, count=3000):
    rng = np.random.default_rng(seed)
    return Phantom(rng.uniform(-1536, 1536, count), rng.uniform(-3, 3, count),
                   rng.uniform(0, 1536, count), rng.uniform(0.01, 5, count))


def test_renders_reuse_one_scanner_and_leave_nothing_behind():
    first, second = small_phantom(0), small_phantom(1, count=500)
    fresh = ScannerKernels(device=select_device())
    with np.errstate(divide="ignore"):
        fresh.set_phantom(first.x_um, first.y_um, first.z_um, np.log(first.energy_pct))
    expected = fresh.forward()

    _scanner_kernels.cache_clear()
    render(first)
    render(second)  # another phantom in between
    again = render(first)
    info = _scanner_kernels.cache_info()
    assert (info.misses, info.hits) == (1, 2)
    np.testing.assert_array_equal(again.a_scans, expected)


def test_scanner_is_kept_per_settings_and_device():
    _scanner_kernels.cache_clear()
    phantom = small_phantom(2, count=200)
    device = select_device()
    render(phantom)
    render(phantom, device=device)  # the default device, named: the same scanner
    render(phantom, settings=KernelSettings(spread_width=6))
    assert _scanner_kernels.cache_info().misses == 2
    kernels, _ = _scanner_kernels(DEFAULT_CONFIG, KernelSettings(), device)
    assert _scanner_kernels.cache_info().misses == 2
    assert kernels.settings == KernelSettings() and kernels.device == device
