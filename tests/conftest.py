"""Shared pytest fixtures and options."""

import importlib.util
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from octcl import _reference as ref
from octcl.config import ScannerConfig
from octcl.phantom import Phantom
from octcl.render import Rendering

# Oclgrind reads its checks from the environment when its platform starts, at the first platform
# query of the process: data races and OpenCL API misuse on, every report to a log the kernel tests
# read (oclgrind_reports; tests/device/test_scanner.py and tests/stage1/test_operator_device.py, "Under Oclgrind").
# Out-of-bounds accesses are always checked.
OCLGRIND_LOG = Path(tempfile.mkdtemp(prefix="octcl-oclgrind-")) / "oclgrind.log"
os.environ.update(OCLGRIND_DATA_RACES="1", OCLGRIND_CHECK_API="1", OCLGRIND_LOG=str(OCLGRIND_LOG))

#: The repository's scripts/ folder, whose files are programs rather than a package (:func:`load_script`).
SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def load_script(name: str):
    """scripts/NAME.py executed afresh as the module NAME (also put in ``sys.modules``, where dataclasses and
    pickling look for it), for tests of a script's functions."""
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = sys.modules[name] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


#: How to get each OpenCL implementation the kernel tests run on, for the reason of a skip.
IMPLEMENTATION_SOURCES = {
    "pocl": "pip install pocl-binary-distribution (installed with octcl; on CPUs its LLVM 14 does not know, "
            "such as AMD Zen 5, apt-get install pocl-opencl-icd)",
    "intel": "pip install 'octcl[intel]' (x86-64 Linux; scripts/setup.sh installs it)",
    "oclgrind": "apt-get install oclgrind (Debian, Ubuntu)",
}


def pytest_terminal_summary(terminalreporter):
    """One line of the kernel tests run on each OpenCL implementation (the test id names it), so
    that a CI log shows which implementations the kernels were proven on."""
    import re

    counts = {name: {} for name in dict.fromkeys((*IMPLEMENTATION_SOURCES, *KERNEL_IMPLEMENTATIONS))}
    for outcome in ("passed", "failed", "skipped"):
        for report in terminalreporter.stats.get(outcome, []):
            for name, tally in counts.items():
                if re.search(rf"[\[-]{name}[\]-]", report.nodeid) and (outcome != "passed" or report.when == "call"):
                    tally[outcome] = tally.get(outcome, 0) + 1
    if any(counts.values()):
        terminalreporter.write_line("kernel tests per OpenCL implementation: " + "; ".join(
            f"{name} " + (", ".join(f"{n} {outcome}" for outcome, n in tally.items()) or "none")
            for name, tally in counts.items()))


def oclgrind_reports(text: str) -> list[str]:
    """Oclgrind's reports in ``text``: its log (OCLGRIND_LOG), which gets those about kernels,
    and standard error, which gets those about API calls made outside a context.

    One report is left out: pyopencl asks every device for NVIDIA's compute
    capability (CL_DEVICE_COMPUTE_CAPABILITY_MAJOR_NV, a vendor extension) in
    a try block before a kernel's first launch, and Oclgrind's API check
    reports the CL_INVALID_VALUE it answers. The call is pyopencl's and legal.
    """
    reports = [block.strip() for block in text.split("\n\n") if "Oclgrind" in block or "Kernel:" in block]
    vendor_query = ["Oclgrind - OpenCL runtime error detected", "Function: clGetDeviceInfo",
                    "Error:    CL_INVALID_VALUE", "For argument 'param_name'"]
    return [report for report in reports if [line.strip() for line in report.splitlines()] != vendor_query]


#: Where a GPU implementation's skip reason points.
GPU_SOURCE = "the GPU vendor's OpenCL driver (octcl devices lists what it finds)"
#: Variable naming more implementations for the kernel tests, comma-separated (``OCTCL_TEST_IMPLEMENTATIONS=nvidia``
#: on a machine whose GPU the listing below would miss); GPUs that are present are added without it.
TEST_IMPLEMENTATIONS_ENV = "OCTCL_TEST_IMPLEMENTATIONS"


def gpu_implementations() -> tuple[str, ...]:
    """The implementations of the GPUs present (``nvidia``, ``amd``, ``intel-gpu``, ``apple``, ...), and those
    :data:`TEST_IMPLEMENTATIONS_ENV` names: the kernel tests run on each, beside the CPUs'."""
    from octcl.device.runtime import SIMULATORS, implementation, list_devices, pyopencl_module

    gpu = pyopencl_module().device_type.GPU
    found = [implementation(device) for _, device in list_devices()
             if device.type & gpu and implementation(device) not in SIMULATORS]
    named = [name.strip() for name in os.environ.get(TEST_IMPLEMENTATIONS_ENV, "").split(",") if name.strip()]
    return tuple(dict.fromkeys(found + named))


#: The implementations the kernel tests compare with the float64 twins: the CPU runtimes octcl installs and
#: every GPU present. Oclgrind, the simulator, runs its own (smaller) cases.
KERNEL_IMPLEMENTATIONS = ("pocl", "intel", *gpu_implementations())


def implementation_device(name: str, double: bool = False):
    """The first device of the OpenCL implementation ``name`` that builds (PyPI's PoCL and the
    distribution's may both be there, and only one build on a given CPU); skips, with the reason,
    where none is installed, none can build on this machine, or ``double`` is asked of a device
    without float64 (Apple's GPUs)."""
    from octcl.device.runtime import has_fp64, implementation, list_devices, probe

    devices = [device for _, device in list_devices() if implementation(device) == name]
    if not devices:
        pytest.skip(f"no {name} device found: {IMPLEMENTATION_SOURCES.get(name, GPU_SOURCE)}")
    building = [device for device in devices if probe(device).builds]
    if not building:
        pytest.skip(f"{name} cannot build on this machine: {probe(devices[0]).error}")
    if double and not has_fp64(building[0]):
        pytest.skip(f"{name} has no float64 (cl_khr_fp64)")
    return building[0]

#: Factor by which ``--fuzz-long`` alone multiplies the fuzz tests' example budgets.
FUZZ_LONG_FACTOR = 50


def pytest_addoption(parser):
    parser.addoption(
        "--fuzz-long", type=int, nargs="?", const=FUZZ_LONG_FACTOR, default=1, metavar="FACTOR",
        help=f"run the fuzz tests (tests/test_fuzz_inputs.py) with FACTOR times their example budget "
             f"(default {FUZZ_LONG_FACTOR}) and new random inputs each run")


@pytest.fixture(scope="session")
def fuzz_settings(request):
    """``fuzz_settings(examples)``: Hypothesis settings for a fuzz test of that many examples.

    Without ``--fuzz-long`` the examples are derandomized (the same inputs
    every run, so CI cannot flake); with it their number is multiplied and
    they are drawn anew. No deadline: the machine is shared and its timing
    noisy; hangs are caught by the tests' own alarm.
    """
    from hypothesis import HealthCheck, settings

    factor = request.config.getoption("fuzz_long")
    return lambda examples: settings(
        max_examples=examples * factor, deadline=None, database=None, derandomize=factor == 1,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.large_base_example,
                               HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="session")
def official_data() -> Path:
    """The official SynthOCT scans, maps and metrics in the repository's ``data/official/``.

    See ``data/README.md`` for their provenance and licence.
    """
    path = Path(__file__).resolve().parents[1] / "data" / "official"
    assert path.is_dir(), f"reference data folder missing: {path}"
    return path


@pytest.fixture
def real_like_target(official_data, tmp_path) -> Path:
    """A real-like target: the official Layers_A scan's levels (``.npy``) with every level above 60 moved to
    one the scanner never writes (:data:`octcl.host.stage1.ceiling.WRITABLE`), so that a run has something
    to aim and needs torch for its score."""
    from octcl.host.pipeline.target import read_target, target_scan
    from octcl.host.stage1.ceiling import WRITABLE
    from octcl.host.stage1.levels import target_levels

    levels = target_levels(target_scan(read_target(official_data / "Scan_Exp2_Layers_A.png")))
    unwritable = np.flatnonzero(~WRITABLE)
    bright = levels > 60
    levels[bright] = unwritable[np.searchsorted(unwritable, levels[bright]) % unwritable.size]
    path = tmp_path / "real_like.npy"
    np.save(path, levels)
    return path


def cache_with_built_programs(folder: Path) -> Path:
    """A fresh octcl cache folder (``OCTCL_CACHE_DIR``) holding a copy of this machine's compiled programs and
    device probes, where there are any: a test of what a run keeps in its cache (torch's import times, the
    spans) then runs a process on its own cache without compiling every kernel first, which is not what it
    tests (with the copy, the torch-import tests took 40.8 and 11.3 s instead of 48.5 and 17.0 s on two
    first-generation Zen cores)."""
    import shutil

    from octcl.device.runtime import cache_dir

    folder.mkdir(parents=True, exist_ok=True)
    for name in ("programs", "probes"):
        if (cache_dir() / name).is_dir():
            shutil.copytree(cache_dir() / name, folder / name, dirs_exist_ok=True)
    return folder


@pytest.fixture(scope="session")
def lpips_weights() -> Path:
    """The cached LPIPS weights; fails (not skips) with the fetch hint when missing."""
    from octcl._lpips import WeightsMissingError, check_weights

    try:
        return check_weights()
    except WeightsMissingError as exc:
        pytest.fail(str(exc), pytrace=False)


@pytest.fixture(scope="session")
def official_uniform_metrics(official_data) -> dict:
    """Official MS-SSIM and LPIPS of Uniform_A against Uniform_B: {map: {metric: value}}."""
    import csv

    with open(official_data / "metrics_exp1_uniform.csv", newline="") as handle:
        return {
            row["Map_Type"]: {"MS-SSIM": float(row["MS-SSIM"]), "LPIPS": float(row["LPIPS"])}
            for row in csv.DictReader(handle)
        }


@pytest.fixture(scope="session")
def official_uniform_maps(official_data) -> tuple[dict, dict]:
    """The official Struct/OAC/SC/RSC map PNGs of Uniform_A and Uniform_B as the metric reads them."""
    from octcl.scorer import _read_map_for_metrics

    def maps(scan):
        suffixes = {"Struct": "", "OAC": "_OAC", "SC": "_SC", "RSC": "_RSC"}
        return {
            name: _read_map_for_metrics(official_data / f"Scan_{scan}{suffix}.png")
            for name, suffix in suffixes.items()
        }

    return maps("Exp1_Uniform_A"), maps("Exp1_Uniform_B")


@pytest.fixture(scope="session")
def official_reference():
    """``rendering(kind, seed)``: float64 reference rendering of a baseline phantom, made once per session."""
    from octcl.phantom import Phantom
    from octcl.render import render

    cache = {}

    def rendering(kind, seed):
        if (kind, seed) not in cache:
            cache[kind, seed] = render(Phantom.baseline(kind, seed), backend="numpy")
        return cache[kind, seed]

    return rendering


@pytest.fixture(scope="session")
def report_table():
    """``report_table(html_text)``: the scans table of a batch's report.html as {column: cell} rows.

    A cell is its ``data-value`` as a float (None where empty) for number
    columns, else its text.
    """
    from html.parser import HTMLParser

    class Table(HTMLParser):
        def __init__(self):
            super().__init__()
            self.inside, self.header, self.rows, self.cell = False, [], [], None

        def handle_starttag(self, tag, attrs):
            attrs = dict(attrs)
            if tag == "table" and attrs.get("id") == "scans":
                self.inside = True
            elif self.inside and tag == "tr":
                self.rows.append([])
            elif self.inside and tag in ("td", "th"):
                value = attrs.get("data-value")
                self.cell = {"value": None if value in (None, "") else float(value), "numeric": value is not None,
                             "text": "", "header": tag == "th"}

        def handle_data(self, data):
            if self.cell is not None:
                self.cell["text"] += data

        def handle_endtag(self, tag):
            if tag == "table":
                self.inside = False
            elif self.inside and tag in ("td", "th") and self.cell is not None:
                self.rows[-1].append(self.cell)
                self.cell = None

    def parse(text: str) -> list[dict]:
        table = Table()
        table.feed(text)
        header, *rows = table.rows
        names = [cell["text"] for cell in header]
        return [{name: cell["value"] if cell["numeric"] else (cell["text"] or None)
                 for name, cell in zip(names, row)} for row in rows]

    return parse


@pytest.fixture
def slow_clock(monkeypatch):
    """``slow_clock(module)``: the module's ``time`` jumps 1000 s at every reading.

    A run that takes no decision from the clock gives the same result under
    it as under the real one; a run that does stops or changes course.
    """
    import itertools
    import time
    import types

    def install(module):
        readings = itertools.count()
        start = time.monotonic()

        def reading():
            return start + 1000.0 * next(readings)

        monkeypatch.setattr(module, "time", types.SimpleNamespace(monotonic=reading, perf_counter=reading,
                                                                  process_time=reading))

    return install


# ------------------------------------------------ the float64 reference scanner's renders, for the stage tests
#: A small scanner (32 rows, 16 A-scans of 6 µm) for the float64 reference's renders.
SMALL_SCANNER = ScannerConfig(depth_pixels=32, a_scans=16, xmax_um=96.0)


def random_field(config: ScannerConfig, seed: int) -> np.ndarray:
    """A speckle-like field: complex Gaussian, brighter near the top."""
    rng = np.random.default_rng(seed)
    nz, nx = config.shape
    decay = np.exp(-np.arange(nz) / (nz / 3))[:, None]
    return decay * (rng.normal(size=(nz, nx)) + 1j * rng.normal(size=(nz, nx)))


def reference_a_scans(phantom: Phantom, config: ScannerConfig, shadowing: bool = True) -> np.ndarray:
    """Complex A-scans of the float64 reference scanner, as octcl.render builds them."""
    spectra = ref.render_spectra(phantom, config, shadowing=shadowing)
    return np.fft.ifft(spectra * ref.hann_window(config.depth_pixels)[:, None], axis=0)


def reference_rendering(phantom: Phantom, config: ScannerConfig, shadowing: bool = True):
    """:func:`reference_a_scans` and their Rendering."""
    a_scans = reference_a_scans(phantom, config, shadowing)
    return a_scans, Rendering.from_a_scans(a_scans)


def scanner_made_target(seed: int) -> np.ndarray:
    """Levels of the reference scanner's rendering of a random phantom on the full grid (a feasible target)."""
    rng = np.random.default_rng(seed)
    n = 40_000
    phantom = Phantom(rng.uniform(-1536, 1530, n), rng.uniform(-3, 3, n), rng.uniform(0, 1536, n),
                      rng.lognormal(-6, 1.5, n) * np.exp(-rng.uniform(0, 1536, n) / 500))
    return ref.render_reference(phantom).levels
