"""scripts/kernel_resources.py: offline GPU builds of every kernel and their resource reports."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from octcl.config import DEFAULT_CONFIG
from octcl.device import depth_order
from octcl.device.programs import PRELUDE, build_options
from octcl.device.scanner import WORK_GROUP_SIZE, KernelSettings, program_defines
from octcl.host.optim import lbfgs_device
from octcl.host.stage1 import display_device, levels_device, operator_device as field_kernels
from octcl.host.stage1.operator import FieldOperator, padded_column_count

from conftest import load_script

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "scripts" / "kernel_resources.py"
#: The field operator's lateral reach R at the default scanner, as FieldKernels takes it.
FIELD_REACH = (FieldOperator(DEFAULT_CONFIG).taps.size - 1) // 2

kr = load_script("kernel_resources")


def run_script(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, cwd=REPO)


def kernel_dir_with(tmp_path: Path, name: str, source: str) -> Path:
    """``tmp_path`` as a kernel folder: octcl's prelude and ``<name>.cl`` holding ``source``."""
    (tmp_path / f"{PRELUDE}.cl").write_text((REPO / "kernels" / f"{PRELUDE}.cl").read_text())
    (tmp_path / f"{name}.cl").write_text(source)
    return tmp_path


@pytest.fixture(scope="module")
def compilers():
    """Skips when clang-14 / libclc are missing (scripts/check_kernels.sh installs them in CI)."""
    try:
        return kr.find_tools(os.environ.get("CLANG", "clang-14"),
                             Path(os.environ.get("LIBCLC_DIR", "/usr/lib/clc")), os.environ.get("PTXAS", "ptxas"))
    except kr.ToolMissingError as exc:
        pytest.skip(f"no offline GPU compiler: {exc}")


def test_builds_are_octcls_builds_for_every_knob_and_precision():
    builds = kr.enumerate_builds(REPO / "kernels", {"spread_width": (8, 16, 8)})
    scanner = {(b.precision, b.knobs): b.options for b in builds if b.file == "scanner"}
    for width in (8, 16):
        for precision in ("float32", "float64"):
            double = precision == "float64"
            defines = program_defines(DEFAULT_CONFIG, KernelSettings(spread_width=width, double=double))
            assert scanner[(precision, (("spread_width", width),))] == tuple(build_options(defines, double))
    assert len(scanner) == 4  # the repeated 8 is built once
    # The depth order does not depend on the knobs: one integer build, no knob reported.
    assert [(b.precision, b.knobs, b.options) for b in builds if b.file == "depth_order"] == [
        ("integer", (), tuple(build_options(depth_order.program_defines(), double=False)))]
    # Nor do the stage-1 files: their ops' defines at the default scanner, float32 and float64.
    no_knob = {"field_operator": field_kernels.program_defines(DEFAULT_CONFIG, FIELD_REACH),
               "display_loss": display_device.program_defines(DEFAULT_CONFIG, 0.1, cpu=False),
               "adam": display_device.program_defines(DEFAULT_CONFIG, 0.1, cpu=False),
               "level_fit": levels_device.program_defines(),
               "lbfgs": lbfgs_device.program_defines()}
    for name, defines in no_knob.items():
        assert [(b.precision, b.knobs, b.options) for b in builds if b.file == name] == [
            (precision, (), tuple(build_options(defines, double=precision == "float64")))
            for precision in ("float32", "float64")], name
    # The prelude is in every build, not a build of its own.
    assert {b.file for b in builds} == {path.stem for path in (REPO / "kernels").glob("*.cl")} - {PRELUDE}


def test_an_unregistered_kernel_file_fails_the_run(tmp_path):
    kernel_dir_with(tmp_path, "depth_order", (REPO / "kernels" / "depth_order.cl").read_text())
    (tmp_path / "scanner_tiles.cl").write_text("__kernel void k(__global int *a) { a[0] = 1; }\n")
    with pytest.raises(kr.RegistryError, match="scanner_tiles.cl: no build registered"):
        kr.enumerate_builds(tmp_path, kr.KNOBS)
    result = run_script("--kernel-dir", str(tmp_path))
    assert result.returncode == 2
    assert "KERNEL_FILES" in result.stderr


def test_a_kernel_folder_without_the_prelude_fails_the_run(tmp_path):
    (tmp_path / "depth_order.cl").write_text((REPO / "kernels" / "depth_order.cl").read_text())
    with pytest.raises(kr.RegistryError, match="prelude.cl does not exist"):
        kr.enumerate_builds(tmp_path, kr.KNOBS)


def test_only_libclcs_own_triple_warning_is_ignored():
    libclc = ("warning: linking module '/usr/lib/clc/amdgcn--amdhsa.bc': Linking two modules of different "
              "target triples: '/usr/lib/clc/amdgcn--amdhsa.bc' is 'amdgcn-unknown-amdhsa' whereas "
              "'kernels/scanner.cl' is '{ours}'\n [-Wlinker-warnings]\n1 warning generated.\n")
    assert kr._unexpected_diagnostics(libclc.format(ours="amdgcn-amd-amdhsa")) == ""
    assert "different target triples" in kr._unexpected_diagnostics(libclc.format(ours="nvptx64-nvidia-nvcl"))
    other = "kernels/scanner.cl:3:5: warning: unused variable 'x' [-Wunused-variable]\n"
    assert kr._unexpected_diagnostics(libclc.format(ours="amdgcn-amd-amdhsa") + other) == other.strip()


@pytest.mark.parametrize("registers, shared_bytes, block_size, warps", [
    (32, 0, 256, 64),       # 1024 registers a warp: 16 warps per sub-partition, 64 per SM
    (40, 0, 256, 48),       # 1280 a warp: 12 per sub-partition → 48 warps, 6 blocks of 8
    (64, 0, 256, 32),       # 2048 a warp: 8 per sub-partition → 32 warps (50 %)
    (255, 0, 32, 8),        # 8160 → 8192 a warp: 2 per sub-partition
    (256, 0, 32, 0),        # over 255 registers a thread: no launch
    (32, 49152, 128, 12),   # (48 KiB + 1 KiB reserved) per block: 3 blocks in 164 KiB
    (16, 0, 32, 32),        # one-warp blocks stop at 32 blocks per SM
])
def test_nvidia_occupancy_follows_the_cuda_occupancy_rules(registers, shared_bytes, block_size, warps):
    assert kr.nvidia_occupancy(registers, shared_bytes, block_size) == warps


def test_every_kernel_compiles_and_reports_its_private_arrays(compilers):
    """Every build for sm_80 (a second or so each) and the depth order for every target."""
    nvidia = run_script("--json", "--targets", "sm_80")
    amd = run_script("--json", "--kernels", "depth_order", "--targets", "gfx906,gfx90a")
    for result in (nvidia, amd):
        assert result.returncode == 0, result.stderr
    records = [json.loads(line) for line in (nvidia.stdout + amd.stdout).splitlines()]
    for record in records:
        assert {"kernel", "target", "precision", "private_bytes", "registers", "occupancy"} <= record.keys()
        assert record["registers"] is None or 0 < record["occupancy"] <= record["occupancy_max"]
    found = {(r["kernel"], r["target"], r["precision"], r["spread_width"]): r for r in records}
    assert {key[:3] for key in found} >= {("introsort_argsort", t, "integer") for t in ("gfx906", "gfx90a", "sm_80")}
    # The sort keeps three stacks of 32 pending ints in private memory.
    for target in ("gfx906", "gfx90a", "sm_80"):
        assert found[("introsort_argsort", target, "integer", None)]["private_bytes"] >= 3 * 32 * 4
    # One private grid of 2·Nz complex values forwards, two in the adjoint.
    grid = 2 * DEFAULT_CONFIG.depth_pixels
    for precision, complex_bytes in (("float32", 8), ("float64", 16)):
        for width in kr.KNOBS["spread_width"]:
            assert found[("render_forward", "sm_80", precision, width)]["private_bytes"] >= grid * complex_bytes
            assert found[("render_adjoint", "sm_80", precision, width)]["private_bytes"] >= 2 * grid * complex_bytes
            assert found[("reduce_slots", "sm_80", precision, width)]["private_bytes"] == 0
            # The work-group variant keeps its grids in local memory: nothing
            # private, the grid (and the adjoint's second grid) in shared memory,
            # and blocks of the kernel's required work-group size.
            for kernel, grids in (("render_forward_group", 1), ("render_adjoint_group", 2)):
                record = found[(kernel, "sm_80", precision, width)]
                assert record["private_bytes"] == 0
                assert record["shared_bytes"] >= grids * grid * complex_bytes
                assert record["block_size"] == WORK_GROUP_SIZE
        # The field operator's transforms ping-pong between two local arrays of Nz (depth) or P
        # (columns) complex values: nothing private, blocks of its required work-group size.
        padded = padded_column_count(DEFAULT_CONFIG, FIELD_REACH)
        for kernel, length in (("depth_convolve", DEFAULT_CONFIG.depth_pixels),
                               ("depth_fft", DEFAULT_CONFIG.depth_pixels), ("lateral_filter", padded)):
            record = found[(kernel, "sm_80", precision, None)]
            assert record["private_bytes"] == 0
            assert record["shared_bytes"] >= 2 * length * complex_bytes
            assert record["block_size"] == field_kernels.WORK_GROUP_SIZE
        assert found[("lateral_convolve", "sm_80", precision, None)]["private_bytes"] == 0


BROKEN_KERNELS = {
    # The message names the line of the file itself, not of the prelude before it.
    "syntax": ("__kernel void introsort_argsort(__global long *key) { key[0] = 1 }\n",
               "depth_order.cl:1:65: error: expected ';'"),
    "undefined function": ("long helper(long x);\n"
                           "__kernel void introsort_argsort(__global long *key) { key[0] = helper(key[1]); }\n",
                           "helper"),
}


@pytest.mark.parametrize("target", ["gfx906", "sm_80"])
@pytest.mark.parametrize("problem", sorted(BROKEN_KERNELS))
def test_a_broken_kernel_fails_the_run_with_the_compilers_message(compilers, tmp_path, target, problem):
    source, message = BROKEN_KERNELS[problem]
    kernel_dir_with(tmp_path, "depth_order", source)
    result = run_script("--kernel-dir", str(tmp_path), "--targets", target)
    assert result.returncode == 1
    assert f"FAILED kernels/depth_order.cl integer for {target}" in result.stderr
    assert message in result.stderr


def test_without_ptxas_the_ptx_gives_private_bytes_and_catches_undefined_functions(compilers, tmp_path):
    result = run_script("--json", "--kernels", "depth_order", "--targets", "sm_80", "--ptxas", "")
    assert result.returncode == 0, result.stderr
    (record,) = [json.loads(line) for line in result.stdout.splitlines()]
    assert record["private_bytes"] >= 3 * 32 * 4
    assert record["registers"] is None and record["occupancy"] is None
    assert "no ptxas" in record["reported_by"]
    kernel_dir_with(tmp_path, "depth_order", BROKEN_KERNELS["undefined function"][0])
    result = run_script("--kernel-dir", str(tmp_path), "--targets", "sm_80", "--ptxas", "")
    assert result.returncode == 1
    assert "undefined functions helper" in result.stderr
