"""Thin host-side op around ``kernels/scanner.cl``: forward render and adjoint.

The host does what is cheap and must be exact: it sorts the scatterers into
lateral bins in depth order, reduces each depth to its carrier phase
φ = −2·k0·z (mod 2π) and its position on the spreading grid in float64 (so
float32 kernels keep the phase of z up to 1536 µm to ~1e−6 rad), and turns
the complex A-scans into the display. The kernels do the per-scatterer work.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import _reference as ref
from ._depth_order import depth_order
from ._runtime import build, context_for, select_device
from .config import DEFAULT_CONFIG, ScannerConfig


@dataclass(frozen=True)
class KernelSettings:
    """Accuracy knobs of the OpenCL scanner (docs/benchmarks.md measures them).

    Attributes
    ----------
    spread_width : int
        W, grid points of the "exponential of semicircle" spreading kernel
        (2 … 16). Error falls roughly as exp(−2.3·W); W = 8 matches the
        float64 direct DFT to ~1e−6 of the display.
    shadow_radius_sq : float
        R²: shadowing counts scatterers with (x_i − x_j)² + y_j² < R²·w0²
        (≥ 3, the contribution window). R² = 20 is exact in float64: beyond
        it 1 − (B·a)² rounds to 1.
    min_transmission : float
        An A-scan stops once its transmission T falls to this value: deeper
        scatterers then change no pixel by more than T relative to the
        shallow ones. 0 stops only behind a mirror (exact).
    double : bool
        Run the kernels in float64 (needs cl_khr_fp64).
    """

    spread_width: int = 8
    shadow_radius_sq: float = 20.0
    min_transmission: float = 0.0
    double: bool = False

    def __post_init__(self):
        if not 2 <= int(self.spread_width) <= 16:
            raise ValueError(f"spread_width must be in 2…16, got {self.spread_width}")
        if not self.shadow_radius_sq >= ref.CONTRIBUTION_RADIUS_SQ:
            raise ValueError(f"shadow_radius_sq must be ≥ {ref.CONTRIBUTION_RADIUS_SQ:g} "
                             f"(the contribution window), got {self.shadow_radius_sq}")
        if not 0.0 <= self.min_transmission < 1.0:
            raise ValueError(f"min_transmission must be in [0, 1), got {self.min_transmission}")

    @property
    def es_beta(self) -> float:
        """β = 2.30·W, the shape of ψ(t) = exp(β·(sqrt(1 − t²) − 1))."""
        return 2.30 * self.spread_width


def _spreading_kernel_transform(settings: KernelSettings, grid: int, s: np.ndarray) -> np.ndarray:
    """ψ̂(s) = (1/h)·∫ ψ(2u/(W·h))·e^{−isu} du, h = 2π/grid, by Gauss–Legendre quadrature."""
    width = settings.spread_width
    nodes, weights = np.polynomial.legendre.leggauss(200)
    psi = np.exp(settings.es_beta * (np.sqrt(1.0 - nodes**2) - 1.0))
    h = 2 * np.pi / grid
    return (width / 2) * (np.cos(np.outer(s, nodes) * width * h / 2) @ (weights * psi))


def program_defines(config: ScannerConfig, settings: KernelSettings) -> tuple[tuple[str, object], ...]:
    """Compile-time constants of ``kernels/scanner.cl`` for a scanner and its settings.

    NZ = Nz, GRID = 2·Nz (the oversampled spreading grid), their base-2
    logarithms, and SPREAD_WIDTH = W.
    """
    nz = config.depth_pixels
    grid = 2 * nz
    return (("NZ", nz), ("GRID", grid), ("LOG2_NZ", nz.bit_length() - 1),
            ("LOG2_GRID", grid.bit_length() - 1), ("SPREAD_WIDTH", settings.spread_width))


class ScannerKernels:
    """The OpenCL Virtual Scanner on one device, for one scanner configuration.

    Use :meth:`set_phantom`, then :meth:`forward` (and :meth:`adjoint` after
    ``forward(for_adjoint=True)``).
    """

    def __init__(self, config: ScannerConfig = DEFAULT_CONFIG,
                 settings: KernelSettings = KernelSettings(), device=None):
        import pyopencl as cl

        self._cl = cl
        nz = config.depth_pixels
        if nz & (nz - 1):
            raise ValueError(f"the OpenCL scanner needs a power-of-two depth_pixels, got {nz}; "
                             "use the NumPy reference (--backend numpy)")
        self.config, self.settings = config, settings
        self.device = select_device(device) if device is None or isinstance(device, str) else device
        self.context, self.queue = context_for(self.device)
        self.grid = 2 * nz
        self.real = np.float64 if settings.double else np.float32
        self.complex = np.complex128 if settings.double else np.complex64
        program = build(self.context, "scanner", program_defines(config, settings), settings.double)
        self._render_forward = cl.Kernel(program, "render_forward")
        self._render_adjoint = cl.Kernel(program, "render_adjoint")
        self._reduce_slots = cl.Kernel(program, "reduce_slots")

        w0 = config.beam_radius_um
        reach_um = math.sqrt(settings.shadow_radius_sq) * w0
        self.ascans_per_bin = max(1, math.ceil(reach_um / config.lateral_pitch_um))
        self.bins = (config.a_scans - 1) // self.ascans_per_bin + 3
        wavenumbers = ref.wavenumbers(config)
        self.k0 = 2 * np.pi / config.wavelength_um
        self.dk = wavenumbers[1] - wavenumbers[0]
        q = np.arange(nz)
        s = np.where(q <= nz // 2, q, q - nz)
        transfer = ref.hann_window(nz) / (_spreading_kernel_transform(settings, self.grid, s) * nz)
        transfer[nz // 2] = 0.0
        twiddle = np.exp(-2j * np.pi * np.arange(self.grid // 2) / self.grid)
        self._transfer = self._upload(transfer.astype(self.real))
        self._twiddle = self._upload(twiddle.astype(self.complex))

        real_name = "f8" if settings.double else "f4"
        self._params_dtype = np.dtype(
            [("a_scans", "i4"), ("ascans_per_bin", "i4"), ("bins", "i4"), ("slots", "i4")]
            + [(name, real_name) for name in (
                "pitch_um", "inv_w0_sq", "shadow_d2", "es_beta",
                "k0", "dk", "min_transmission")])
        params = np.zeros((), self._params_dtype)
        params["a_scans"], params["ascans_per_bin"] = config.a_scans, self.ascans_per_bin
        params["bins"], params["slots"] = self.bins, 3 * self.ascans_per_bin
        params["pitch_um"] = config.lateral_pitch_um
        params["inv_w0_sq"] = 1 / w0**2
        params["shadow_d2"] = settings.shadow_radius_sq * w0**2
        params["es_beta"], params["k0"], params["dk"] = settings.es_beta, self.k0, self.dk
        params["min_transmission"] = settings.min_transmission
        self._params = params
        self.count = 0

    def _upload(self, array: np.ndarray):
        """A read-only device copy; an empty array becomes one zero element (OpenCL has no empty buffers)."""
        mf = self._cl.mem_flags
        array = np.ascontiguousarray(array) if array.size else np.zeros(1, array.dtype)
        return self._cl.Buffer(self.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=array)

    # ------------------------------------------------------------ geometry
    def set_phantom(self, x_um, y_um, z_um, log_energy) -> None:
        """Lay out the scatterers for the kernels.

        ``log_energy`` is u = ln E (E in %); the amplitude is a = e^{u/2}/10.
        Scatterers out of every A-scan's shadowing reach are left out (they
        change nothing) and get zero gradients.
        """
        config, per_bin = self.config, self.ascans_per_bin
        x_um, y_um, z_um, log_energy = (np.asarray(v, dtype=np.float64) for v in (x_um, y_um, z_um, log_energy))
        lateral_index = x_um / config.lateral_pitch_um + config.a_scans / 2
        bin_index = np.floor(lateral_index / per_bin).astype(np.int64) + 1
        in_bins = (bin_index >= 0) & (bin_index < self.bins)
        # Depth rank in the scanner's order, then group by bin keeping that
        # order: the kernel merges bins by rank. The order of tied depths
        # depends on every depth, so all scatterers are sorted, then filtered.
        by_depth = self._depth_order(z_um)
        by_depth = by_depth[in_bins[by_depth]]
        # Bin numbers fit in int16, for which NumPy's stable sort is a radix sort.
        order = by_depth[np.argsort(bin_index[by_depth].astype(np.int16), kind="stable")]
        rank = np.empty(len(x_um), dtype=np.int32)
        rank[by_depth] = np.arange(by_depth.size, dtype=np.int32)
        bins = bin_index[order].astype(np.int32)
        self.order, self.count, self.total = order, order.size, len(x_um)

        span = 2 * self.dk * z_um[order]                    # x_j = 2·δk·z_j
        grid_pos = np.mod(span * (self.grid / (2 * np.pi)), self.grid)
        carrier = np.exp(-2j * self.k0 * z_um[order])       # e^{iφ}, φ = −2·k0·z
        amplitude = np.exp(0.5 * log_energy[order]) / 10.0  # sqrt(E/100)
        ascan_x_um = ref.ascan_positions_um(config)
        x_offset_um = x_um[order] - (ascan_x_um[0] + per_bin * (bins - 1) * config.lateral_pitch_um)
        self._geometry = [self._upload(a.astype(self.real)) for a in (x_offset_um, y_um[order], amplitude, grid_pos)]
        self._geometry += [self._upload(carrier.astype(self.complex)), self._upload(rank[order]),
                           self._upload(bins),
                           self._upload(np.searchsorted(bins, np.arange(self.bins + 1)).astype(np.int32)),
                           self._upload(self._contribution_ranges(x_um[order], y_um[order], lateral_index[order]))]

    def _contribution_ranges(self, x_um, y_um, lateral_index) -> np.ndarray:
        """(first, last) A-scan whose contribution window holds each scatterer.

        Decided in float64 with the reference's own test,
        (x_i − x_j)² + y_j² < 3·w0², so the kernels' float32 arithmetic never
        moves a scatterer at the window's edge in or out. The window is an
        interval of A-scans (d² is convex in i); an empty one is (1, 0).
        """
        config = self.config
        reach = math.ceil(math.sqrt(ref.CONTRIBUTION_RADIUS_SQ) * config.beam_radius_um
                          / config.lateral_pitch_um) + 1
        candidates = np.rint(lateral_index)[:, None].astype(np.int64) + np.arange(-reach, reach + 1)
        ascan_x_um = ref.ascan_positions_um(config)
        inside = (candidates >= 0) & (candidates < config.a_scans)
        inside &= ref.in_contribution_window(ascan_x_um[np.clip(candidates, 0, config.a_scans - 1)]
                                             - x_um[:, None], y_um[:, None], config.beam_radius_um)
        first = np.where(inside.any(axis=1), np.where(inside, candidates, np.iinfo(np.int64).max).min(axis=1), 1)
        last = np.where(inside.any(axis=1), np.where(inside, candidates, -1).max(axis=1), 0)
        return np.stack([first, last], axis=1).astype(np.int32)

    def _depth_order(self, z_um: np.ndarray) -> np.ndarray:
        """All scatterers in the scanner's depth order, NumPy's classic argsort.

        See :func:`octcl._depth_order.depth_order`, run on this device. During
        refinement depths move little between calls and have no ties, so the
        previous order is passed as the guess: the sort that looks for ties
        is then close to linear, and with none found it is the answer.
        """
        previous = getattr(self, "_last_depth_order", None)
        guess = previous if previous is not None and previous.size == z_um.size else None
        self._last_depth_order = depth_order(z_um, backend="opencl", device=self.device, guess=guess)
        return self._last_depth_order

    # ------------------------------------------------------------- kernels
    def forward(self, for_adjoint: bool = False) -> np.ndarray:
        """Complex A-scans A[n, i], shape (Nz, Nx), complex128.

        With ``for_adjoint`` the per-pair transmissions are kept on the device
        for a following :meth:`adjoint`.
        """
        cl, config = self._cl, self.config
        nz, nx = config.depth_pixels, config.a_scans
        itemsize = np.dtype(self.complex).itemsize
        a_scan = cl.Buffer(self.context, cl.mem_flags.WRITE_ONLY, nz * nx * itemsize)
        slot_data = stop_cursor = None
        if for_adjoint:
            slots = max(1, self.count) * 3 * self.ascans_per_bin
            slot_data = cl.Buffer(self.context, cl.mem_flags.READ_WRITE, slots * itemsize)
            cl.enqueue_fill_buffer(self.queue, slot_data, np.zeros(1, self.complex), 0, slots * itemsize)
            stop_cursor = cl.Buffer(self.context, cl.mem_flags.READ_WRITE, 3 * nx * 4)
        self._render_forward(self.queue, (nx,), None, self._params, *self._geometry,
                                    self._transfer, self._twiddle, a_scan, slot_data, stop_cursor)
        result = np.empty((nx, nz), dtype=self.complex)
        cl.enqueue_copy(self.queue, result, a_scan)
        self._slot_data, self._stop_cursor = slot_data, stop_cursor
        return result.T.astype(np.complex128)

    def adjoint(self, a_scan_bar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(∂L/∂u, ∂L/∂z) per scatterer in input order, given Ā = ∂L/∂Re A + i·∂L/∂Im A."""
        cl, config = self._cl, self.config
        if self._slot_data is None:
            raise RuntimeError("adjoint() needs forward(for_adjoint=True) first")
        a_bar = self._upload(np.ascontiguousarray(np.asarray(a_scan_bar).T, dtype=self.complex))
        self._render_adjoint(self.queue, (config.a_scans,), None, self._params, *self._geometry,
                                    self._transfer, self._twiddle, a_bar, self._slot_data,
                                    self._stop_cursor)
        grad_u = np.zeros(self.total)
        grad_z = np.zeros(self.total)
        if self.count:
            gradient = cl.Buffer(self.context, cl.mem_flags.WRITE_ONLY,
                                 self.count * np.dtype(self.complex).itemsize)
            self._reduce_slots(self.queue, (self.count,), None, self._params, self._geometry[6],
                                      self._slot_data, gradient, np.int32(self.count))
            reduced = np.empty(self.count, dtype=self.complex)
            cl.enqueue_copy(self.queue, reduced, gradient)
            grad_u[self.order], grad_z[self.order] = reduced.real, reduced.imag
        return grad_u, grad_z
