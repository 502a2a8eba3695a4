"""Thin host-side op around ``kernels/scanner.cl``: forward render and adjoint.

The host does what is cheap and must be exact, in float64: it groups the
scatterers into lateral bins and makes, for each bin of A-scans, the list of
its candidate scatterers in the scanner's depth order; it decides each
scatterer's contribution window; it reduces each depth to its carrier phase
φ = −2·k0·z (mod 2π) and its taps on the spreading grid (so float32 kernels
keep the phase of z up to 1536 µm to ~1e−6 rad); and it splits each
amplitude into a float32 mantissa and a binary exponent, so that the float32
kernels work relative to each A-scan's largest amplitude whatever the
phantom's overall energy (``kernels/scanner.cl``, "Scale"). The kernels do
the per-scatterer work.

Two kernel variants compute the same maths (``kernels/scanner.cl``): one
work-item per 8 float32 or 4 float64 A-scans of a bin, one vector lane each
(``"work-item"``, the default on CPU devices) and one work-group per A-scan
(``"work-group"``, the default on GPUs and other accelerators): with 512
A-scans the first launches 64 work-items (float32, 8 A-scans a bin), the
second 512·WG_SIZE (65,536 at the default 128).

During refinement x and y stay fixed while z and E change, so everything that
depends on x and y alone (bins, offsets, contribution windows) is computed
and uploaded once and reused while they are unchanged; device buffers are
kept and refilled.
"""

from __future__ import annotations

import math
import threading
import warnings
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np

from .. import _reference as ref
from .depth_order import depth_order
from .programs import build
from .runtime import context_for, select_device
from ..config import DEFAULT_CONFIG, ScannerConfig

#: The kernel variants (``kernels/scanner.cl``); "auto" picks by device type.
VARIANTS = ("work-item", "work-group")
#: Work-items per work-group of the work-group variant (fewer if the device
#: allows fewer): two grid points and one butterfly pair of the 512-point FFT
#: each, and 128·512 = 65,536 work-items for a B-scan.
WORK_GROUP_SIZE = 128
#: Bytes of the work-item kernels' vectors: LANES reals (8 floats, 4 doubles), the
#: 256 bits of an AVX2 register (``kernels/scanner.cl``, "Vector maths").
VECTOR_BYTES = 32
#: The exponent given to a zero amplitude (a define of ``kernels/scanner.cl``).
NO_AMPLITUDE = -(1 << 20)


@dataclass(frozen=True)
class KernelSettings:
    """Accuracy knobs and variant of the OpenCL scanner (docs/benchmarks.md measures them).

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
    variant : {"auto", "work-item", "work-group"}
        One work-item or one work-group per A-scan; "auto" takes the
        work-group variant on GPUs and accelerators, the work-item variant
        on CPUs.
    """

    spread_width: int = 8
    shadow_radius_sq: float = 20.0
    min_transmission: float = 0.0
    double: bool = False
    variant: str = "auto"

    def __post_init__(self):
        if not 2 <= int(self.spread_width) <= 16:
            raise ValueError(f"spread_width must be in 2…16, got {self.spread_width}")
        if not self.shadow_radius_sq >= ref.CONTRIBUTION_RADIUS_SQ:
            raise ValueError(f"shadow_radius_sq must be ≥ {ref.CONTRIBUTION_RADIUS_SQ:g} "
                             f"(the contribution window), got {self.shadow_radius_sq}")
        if not 0.0 <= self.min_transmission < 1.0:
            raise ValueError(f"min_transmission must be in [0, 1), got {self.min_transmission}")
        if self.variant not in ("auto",) + VARIANTS:
            raise ValueError(f"variant must be 'auto', 'work-item' or 'work-group', got {self.variant!r}")

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


def program_defines(config: ScannerConfig, settings: KernelSettings,
                    work_group_size: int = WORK_GROUP_SIZE) -> tuple[tuple[str, object], ...]:
    """Compile-time constants of ``kernels/scanner.cl`` for a scanner and its settings.

    NZ = Nz, GRID = 2·Nz (the oversampled spreading grid), their base-2
    logarithms, SPREAD_WIDTH = W, WG_SIZE, the work-group size of the
    work-group variant, LANES, the reals in :data:`VECTOR_BYTES` (A-scans per
    work-item of the work-item variant), and :data:`NO_AMPLITUDE`.
    """
    nz = config.depth_pixels
    grid = 2 * nz
    lanes = VECTOR_BYTES // np.dtype(np.float64 if settings.double else np.float32).itemsize
    return (("NZ", nz), ("GRID", grid), ("LOG2_NZ", nz.bit_length() - 1),
            ("LOG2_GRID", grid.bit_length() - 1), ("SPREAD_WIDTH", settings.spread_width),
            ("WG_SIZE", work_group_size), ("LANES", lanes), ("NO_AMPLITUDE", f"({NO_AMPLITUDE})"))


def _is_cpu(device) -> bool:
    import pyopencl as cl

    return bool(device.type & cl.device_type.CPU)


def sort_device_for(device):
    """The device that runs the scanner's depth order for a scanner on ``device``.

    The classic argsort is a sequential algorithm, one work-item
    (``kernels/depth_order.cl``): on a CPU device that is one core running
    a compiled loop, on a GPU it would be one slow thread holding up the
    whole device. So a CPU scanner sorts on its own device and a GPU scanner
    on the first CPU device (PoCL is installed with octcl); None when there
    is none, and the pure-Python sort is used.
    """
    if _is_cpu(device):
        return device
    from .runtime import OpenCLUnavailableError

    try:
        return select_device("cpu")
    except OpenCLUnavailableError:
        return None


@dataclass
class _LateralLayout:
    """What depends on x and y only: bins and lists (offsets and windows live on the device)."""

    x_um: np.ndarray
    y_um: np.ndarray
    bin: np.ndarray              # int32 bin of each scatterer (shifted by one), −1 outside
    list_start: np.ndarray       # list c's entries are list_start[c] … list_start[c + 1] − 1
    entry_list: np.ndarray       # the list of each entry
    entry_scatterer: np.ndarray | None = None  # each entry's scatterer, in depth order per list

    def matches(self, x_um: np.ndarray, y_um: np.ndarray) -> bool:
        return np.array_equal(self.x_um, x_um) and np.array_equal(self.y_um, y_um)


class ScannerKernels:
    """The OpenCL Virtual Scanner on one device, for one scanner configuration.

    Use :meth:`set_phantom`, then :meth:`forward` (and :meth:`adjoint` after
    ``forward(for_adjoint=True)``).
    """

    def __init__(self, config: ScannerConfig = DEFAULT_CONFIG,
                 settings: KernelSettings = KernelSettings(), device=None):
        import pyopencl as cl

        self._cl = cl
        self._buffers: dict[str, tuple[object, int]] = {}
        nz = config.depth_pixels
        if nz & (nz - 1):
            raise ValueError(f"the OpenCL scanner needs a power-of-two depth_pixels, got {nz}; "
                             "use the NumPy reference (--backend numpy)")
        self.config, self.settings = config, settings
        self.device = select_device(device) if device is None or isinstance(device, str) else device
        self.context, self.queue = context_for(self.device)
        self.variant = settings.variant if settings.variant != "auto" else (
            "work-item" if _is_cpu(self.device) else "work-group")
        self.work_group_size = min(WORK_GROUP_SIZE, 1 << (self.device.max_work_group_size.bit_length() - 1))
        self.grid = 2 * nz
        self.real = np.float64 if settings.double else np.float32
        self.complex = np.complex128 if settings.double else np.complex64
        program = build(self.context, "scanner", program_defines(config, settings, self.work_group_size),
                        settings.double)
        if self.variant == "work-group":
            self._render_forward = cl.Kernel(program, "render_forward_group")
            self._render_adjoint = cl.Kernel(program, "render_adjoint_group")
        else:
            self._render_forward = cl.Kernel(program, "render_forward")
            self._render_adjoint = cl.Kernel(program, "render_adjoint")
        self._reduce_slots = cl.Kernel(program, "reduce_slots")
        self._gather_entries = cl.Kernel(program, "gather_entries")
        self._ascan_scale = cl.Kernel(program, "ascan_scale")
        size = np.zeros(1, np.int32)
        cl.Kernel(program, "entry_size")(self.queue, (1,), None, self._buffer("entry_size", 4))
        cl.enqueue_copy(self.queue, size, self._buffers["entry_size"][0])
        self.entry_bytes = int(size[0])
        self.sort_device = sort_device_for(self.device)

        w0 = config.beam_radius_um
        reach_um = math.sqrt(settings.shadow_radius_sq) * w0
        self.ascans_per_bin = max(1, math.ceil(reach_um / config.lateral_pitch_um))
        self.bins = (config.a_scans - 1) // self.ascans_per_bin + 3
        wavenumbers = ref.wavenumbers(config)
        self.k0 = config.k0_rad_per_um
        self.dk = wavenumbers[1] - wavenumbers[0]
        s = ref.wavenumber_grid(config)[2]  # each sample's multiple of δk, FFT order
        transfer = ref.hann_window(nz) / (_spreading_kernel_transform(settings, self.grid, s) * nz)
        transfer[nz // 2] = 0.0
        twiddle = np.exp(-2j * np.pi * np.arange(self.grid // 2) / self.grid)
        self._fill("transfer", transfer.astype(self.real))
        self._fill("twiddle", twiddle.astype(self.complex))

        real_name = "f8" if settings.double else "f4"
        self._params = np.zeros((), np.dtype(
            [("a_scans", "i4"), ("ascans_per_bin", "i4"), ("entries", "i4"), ("padding", "i4")]
            + [(name, real_name) for name in (
                "pitch_um", "inv_w0_sq", "shadow_d2", "es_beta", "k0", "dk", "min_transmission")]))
        params = self._params
        params["a_scans"], params["ascans_per_bin"] = config.a_scans, self.ascans_per_bin
        params["pitch_um"] = config.lateral_pitch_um
        params["inv_w0_sq"] = 1 / w0**2
        params["shadow_d2"] = settings.shadow_radius_sq * w0**2
        params["es_beta"], params["k0"], params["dk"] = settings.es_beta, self.k0, self.dk
        params["min_transmission"] = settings.min_transmission
        self._lateral: _LateralLayout | None = None
        self._last_depth_order = None
        self._slots_ready = False
        self.count = self.entries = 0

    # ------------------------------------------------------------ buffers
    def _buffer(self, name: str, nbytes: int):
        """A device buffer of at least ``nbytes`` (≥ 1: OpenCL has no empty buffers), kept between calls."""
        buffer, size = self._buffers.get(name, (None, 0))
        nbytes = max(nbytes, 16)
        if size < nbytes:
            buffer = self._cl.Buffer(self.context, self._cl.mem_flags.READ_WRITE, nbytes)
            self._buffers[name] = (buffer, nbytes)
        return buffer

    def _fill(self, name: str, array: np.ndarray):
        """Copy ``array`` into the device buffer ``name`` (blocking) and return the buffer."""
        array = np.ascontiguousarray(array)
        buffer = self._buffer(name, array.nbytes)
        if array.size:
            self._cl.enqueue_copy(self.queue, buffer, array, is_blocking=True)
        return buffer

    def _scene_arguments(self) -> list:
        return [self._buffers[name][0] for name in ("entries", "list_start", "transfer", "twiddle")]

    # ------------------------------------------------------------ geometry
    def set_phantom(self, x_um, y_um, z_um, log_energy) -> None:
        """Lay out the scatterers for the kernels.

        ``log_energy`` is u = ln E (E in %); the amplitude is a = sqrt(E/100).
        Scatterers out of every A-scan's shadowing reach are left out (they
        change nothing) and get zero gradients.
        """
        x_um, y_um, z_um, log_energy = (np.asarray(v, dtype=np.float64) for v in (x_um, y_um, z_um, log_energy))
        if self._lateral is None or not self._lateral.matches(x_um, y_um):
            self._lateral = self._lay_out_laterally(x_um, y_um)
        lateral = self._lateral
        self.count, self.entries = x_um.size, int(lateral.list_start[-1])
        self._params["entries"] = self.entries

        # Each list holds the scatterers of bins c − 1 … c + 1 in the
        # scanner's depth order. Which scatterers a list holds depends on x
        # alone; their order on z, and between calls that order changes
        # little, so the last one is re-sorted by the new depth ranks (nearly
        # sorted keys: the stable sort's runs make it close to linear).
        by_depth = self._depth_order(z_um)
        if lateral.entry_scatterer is None:
            by_depth = by_depth[lateral.bin[by_depth] >= 0]
            # Each scatterer's three (list, scatterer) pairs, side by side in
            # depth order: a stable sort by list keeps depth order within lists.
            lists = (lateral.bin[by_depth][:, None] + np.arange(-1, 2)).reshape(-1)
            flat = np.flatnonzero((lists >= 1) & (lists <= self.bins - 2))
            # (List numbers fit in int16, for which NumPy's stable sort is a radix sort.)
            by_list = flat[np.argsort(lists[flat].astype(np.int16 if self.bins < 2**15 else np.int64),
                                      kind="stable")]
            lateral.entry_scatterer = by_depth[by_list // 3].astype(np.int32)
        else:
            rank = np.empty(self.count, dtype=np.int64)
            rank[by_depth] = np.arange(self.count)
            key = lateral.entry_list * np.int64(self.count) + rank[lateral.entry_scatterer]
            lateral.entry_scatterer = lateral.entry_scatterer[np.argsort(key, kind="stable")]

        # Spreading taps: p = 2·δk·z·GRID/(2π) grid points (not wrapped, so
        # that taps ascend along a list), first tap ⌈p − W/2⌉.
        position = z_um * (2 * self.dk * self.grid / (2 * np.pi))
        first_tap = np.ceil(position - self.settings.spread_width / 2)
        # The carrier phase φ = −2·k0·z reduced to [−π, π) in float64; the
        # device takes its cosine and sine.
        phase = np.mod(-2 * self.k0 * z_um + np.pi, 2 * np.pi) - np.pi
        # a = sqrt(E/100) as the scanner computes it (for E below 1e−306,
        # E/100 is subnormal and rounds, there as here).
        amplitude = np.sqrt(np.exp(log_energy) / 100.0)
        mantissa, exponent = np.frexp(amplitude)
        exponent[amplitude == 0] = NO_AMPLITUDE

        arrays = {"first_tap": first_tap.astype(np.int32), "tap_offset": (first_tap - position).astype(self.real),
                  "phase": phase.astype(self.real), "mantissa": mantissa.astype(self.real),
                  "exponent": exponent.astype(np.int32), "entry_scatterer": lateral.entry_scatterer}
        for name, array in arrays.items():
            self._fill(name, array)
        entry_index = self._buffer("entry_index", 3 * self.count * 4)
        entries = self._buffer("entries", self.entries * self.entry_bytes)
        if self.entries:
            self._cl.enqueue_fill_buffer(self.queue, entry_index, np.int32(-1), 0, 3 * self.count * 4)
            self._gather_entries(self.queue, (self.entries,), None, self._params,
                                 *(self._buffers[name][0] for name in (
                                     "entry_scatterer", "list_start", "x_offset_um", "y_um", "bin", "window",
                                     "mantissa", "exponent", "first_tap", "tap_offset", "phase")),
                                 entries, entry_index)
        scale_exponent = self._buffer("scale_exponent", self.config.a_scans * 4)
        self._cl.enqueue_fill_buffer(self.queue, scale_exponent, np.int32(NO_AMPLITUDE), 0, self.config.a_scans * 4)
        if self.count:
            self._ascan_scale(self.queue, (self.count,), None, self._buffers["window"][0],
                              self._buffers["exponent"][0], scale_exponent, np.int32(self.count))
        self._slots_ready = False

    def _lay_out_laterally(self, x_um: np.ndarray, y_um: np.ndarray) -> _LateralLayout:
        """Bins, lists, offsets from each bin's first A-scan and contribution windows; uploaded once."""
        config, per_bin = self.config, self.ascans_per_bin
        lateral_index = x_um / config.lateral_pitch_um + config.a_scans / 2
        bin_index = np.floor(lateral_index / per_bin).astype(np.int64) + 1
        bin_index = np.where((bin_index >= 0) & (bin_index < self.bins), bin_index, -1).astype(np.int32)
        ascan_x_um = ref.ascan_positions_um(config)
        x_offset_um = x_um - (ascan_x_um[0] + per_bin * (bin_index - 1) * config.lateral_pitch_um)
        # List c (the A-scans of bin c, 1 ≤ c ≤ bins − 2) holds bins c − 1 … c + 1.
        per_bin_count = np.bincount(bin_index[bin_index >= 0], minlength=self.bins)
        per_list = np.convolve(per_bin_count, np.ones(3, dtype=np.int64), mode="same")
        per_list[[0, -1]] = 0
        list_start = np.concatenate([[0], np.cumsum(per_list)]).astype(np.int32)
        self._fill("x_offset_um", x_offset_um.astype(self.real))
        self._fill("y_um", y_um.astype(self.real))
        self._fill("bin", bin_index)
        self._fill("window", contribution_ranges(x_um, y_um, config))
        self._fill("list_start", list_start)
        entry_list = np.repeat(np.arange(self.bins), per_list)
        return _LateralLayout(x_um.copy(), y_um.copy(), bin_index, list_start, entry_list)

    def _depth_order(self, z_um: np.ndarray) -> np.ndarray:
        """All scatterers in the scanner's depth order, NumPy's classic argsort.

        See :func:`octcl.device.depth_order.depth_order`, run on :attr:`sort_device`
        (:func:`sort_device_for`). During refinement depths move little
        between calls, so the previous order is passed as the guess: the sort
        that looks for ties is then close to linear, and with none found it
        is the answer.
        """
        previous = self._last_depth_order
        guess = previous if previous is not None and previous.size == z_um.size else None
        if self.sort_device is None:
            warnings.warn("no CPU OpenCL device for the scanner's depth order: tied depths are "
                          "ordered by the pure-Python sort (seconds per call)", stacklevel=3)
            order = depth_order(z_um, backend="python", guess=guess)
        else:
            order = depth_order(z_um, backend="opencl", device=self.sort_device, guess=guess)
        self._last_depth_order = order
        return order

    # ------------------------------------------------------------- kernels
    def _launch(self, kernel, *arguments, scratch_points: int = 0) -> None:
        """Launch a scanner kernel: one work-group per A-scan (work-group variant), or one
        work-item per LANES A-scans of a bin (work-item variant, LANES in kernels/scanner.cl:
        8 floats or 4 doubles, 256-bit vectors), whose kernels take one more argument, a
        scratch buffer of ``scratch_points`` complex numbers per A-scan.

        Each of those work-items is a work-group of its own: there are only bins·P/LANES of
        them (64 for 512 A-scans), and PoCL would otherwise pack 16 into one group, one core.
        """
        nx = self.config.a_scans
        if self.variant == "work-group":
            kernel(self.queue, (nx * self.work_group_size,), (self.work_group_size,), *arguments)
        else:
            lanes = VECTOR_BYTES // np.dtype(self.real).itemsize
            work_items = (self.bins - 2) * -(-self.ascans_per_bin // lanes)
            scratch = self._buffer("grid_scratch", nx * scratch_points * np.dtype(self.complex).itemsize)
            kernel(self.queue, (work_items,), (1,), *arguments, scratch)

    def forward(self, for_adjoint: bool = False) -> np.ndarray:
        """Complex A-scans A[n, i], shape (Nz, Nx), complex128.

        With ``for_adjoint`` the per-pair transmissions are kept on the device
        for a following :meth:`adjoint`.
        """
        nz, nx = self.config.shape
        itemsize = np.dtype(self.complex).itemsize
        a_scan = self._buffer("a_scan", nz * nx * itemsize)
        scale_exponent = self._buffers["scale_exponent"][0]
        slot_data = stop_position = None
        if for_adjoint or self.variant == "work-group":  # the work-group variant gathers from the slots
            slot_data = self._buffer("slots", self.ascans_per_bin * self.entries * itemsize)
            stop_position = self._buffer("stop_position", nx * 4)
        self._launch(self._render_forward, self._params, *self._scene_arguments(), a_scan,
                     scale_exponent, slot_data, stop_position, scratch_points=self.grid)
        result = np.empty((nx, nz), dtype=self.complex)
        exponent = np.empty(nx, dtype=np.int32)
        self._cl.enqueue_copy(self.queue, result, a_scan)
        self._cl.enqueue_copy(self.queue, exponent, scale_exponent)
        # The unit of A-scan i is 2^{e_i} (0 for an A-scan with no amplitude).
        self._ascan_unit = np.ldexp(1.0, exponent)
        self._slots_ready = for_adjoint
        return result.T.astype(np.complex128) * self._ascan_unit

    def adjoint(self, a_scan_bar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(∂L/∂u, ∂L/∂z) per scatterer in input order, given Ā = ∂L/∂Re A + i·∂L/∂Im A."""
        cl = self._cl
        if not self._slots_ready:
            raise RuntimeError("adjoint() needs forward(for_adjoint=True) first")
        # The kernels' A-scans are A/2^{e_i}, so their adjoint input is Ā·2^{e_i}.
        a_bar = np.asarray(a_scan_bar) * self._ascan_unit
        self._fill("a_scan_bar", np.ascontiguousarray(a_bar.T, dtype=self.complex))
        self._launch(self._render_adjoint, self._params, *self._scene_arguments(),
                     self._buffers["a_scan_bar"][0], self._buffers["scale_exponent"][0],
                     self._buffers["slots"][0], self._buffers["stop_position"][0],
                     scratch_points=2 * self.grid)
        if not self.count:
            return np.zeros(0), np.zeros(0)
        gradient = self._buffer("gradient", self.count * np.dtype(self.complex).itemsize)
        self._reduce_slots(self.queue, (self.count,), None, self._params, self._buffers["bin"][0],
                           self._buffers["entry_index"][0], self._buffers["slots"][0], gradient,
                           np.int32(self.count))
        reduced = np.empty(self.count, dtype=self.complex)
        cl.enqueue_copy(self.queue, reduced, gradient)
        return reduced.real.astype(np.float64), reduced.imag.astype(np.float64)


def scanner_in_background(config: ScannerConfig = DEFAULT_CONFIG, settings: KernelSettings = KernelSettings()) -> Future:
    """:class:`ScannerKernels` on octcl's device, made on a thread from now: a future of them.

    Making them builds ``kernels/scanner.cl``: a read of pyopencl's binary
    cache once it holds the program (0.02 s on two EPYC cores), a compile
    where it does not, on a machine's first run or after an update (2.3 s
    with Intel's CPU runtime on two EPYC cores, 5.9 s through NVIDIA's
    driver on an H200: docs/benchmarks.md). A run that needs them only
    after stage 1 starts them at its beginning, so that a compile overlaps
    stage 1 (pyopencl releases the interpreter while the compiler runs).
    The device and its context are resolved here, before the thread starts,
    so that the thread and its caller share one context; an error making
    them (no OpenCL device, a failed build) is the future's.
    """
    future: Future = Future()
    try:
        device = select_device(None)
        context_for(device)
    except Exception as exc:  # noqa: BLE001 - the caller meets it where it asks for the kernels
        future.set_exception(exc)
        return future

    def make():
        try:
            future.set_result(ScannerKernels(config, settings, device))
        except BaseException as exc:  # noqa: BLE001 - handed to the caller with its traceback
            future.set_exception(exc)

    threading.Thread(target=make, name="octcl-scanner-build", daemon=True).start()
    return future


def contribution_ranges(x_um: np.ndarray, y_um: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """(first, last) A-scan whose contribution window holds each scatterer; (1, 0) for none.

    Decided in float64 with the reference's own test,
    (x_i − x_j)² + y_j² < 3·w0² (:func:`octcl._reference.in_contribution_window`),
    so the kernels' float32 arithmetic never moves a scatterer at the
    window's edge in or out. The window is an interval of A-scans (d² is
    convex in i) whose ends are ⌈c − h⌉ and ⌊c + h⌋ up to rounding, with
    c = x_j/Δx + Nx/2 and h = sqrt(3·w0² − y_j²)/Δx; the test decides
    among each end's neighbours.
    """
    nx, pitch = config.a_scans, config.lateral_pitch_um
    ascan_x_um = ref.ascan_positions_um(config)
    centre = x_um / pitch + nx / 2
    half = np.sqrt(np.maximum(ref.CONTRIBUTION_RADIUS_SQ * config.beam_radius_um**2 - y_um**2, 0.0)) / pitch

    def inside(candidate):
        index = np.clip(candidate, 0, nx - 1)
        return index, ref.in_contribution_window(ascan_x_um[index] - x_um, y_um, config.beam_radius_um)

    first = np.full(x_um.size, nx, dtype=np.int64)
    last = np.full(x_um.size, -1, dtype=np.int64)
    low, high = np.ceil(centre - half).astype(np.int64), np.floor(centre + half).astype(np.int64)
    for shift in (-1, 0, 1):
        index, hit = inside(low + shift)
        first = np.where(hit, np.minimum(first, index), first)
        index, hit = inside(high + shift)
        last = np.where(hit, np.maximum(last, index), last)
    empty = first > last
    return np.stack([np.where(empty, 1, first), np.where(empty, 0, last)], axis=1).astype(np.int32)
