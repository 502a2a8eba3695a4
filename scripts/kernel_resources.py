#!/usr/bin/env python
"""Compile every OpenCL kernel offline for GPU targets and report its resources.

Every build octcl makes (each ``kernels/*.cl`` with the ``-D`` defines of each
compile-time knob setting, in float32 and, where the kernel has one, float64)
is compiled with clang and libclc for

- AMD GCN/CDNA, ``amdgcn-amd-amdhsa``: gfx906 (Vega 20, MI50/MI60) and
  gfx90a (CDNA2, MI200), to assembly, whose "Kernel info" comments state the
  registers, scratch and occupancy; the assembly is then assembled and every
  symbol must be defined (a call to a function libclc lacks compiles silently
  otherwise, with a guessed 16 KiB stack);
- NVIDIA, ``nvptx64-nvidia-nvcl``: sm_80 (Ampere, A100), to PTX, then
  ``ptxas -arch=sm_80 -v`` (CUDA), which states registers, stack frame and
  spills; without ptxas only the PTX's ``__local_depot`` size is read
  (``reported_by`` says which) and registers/occupancy are left empty, since
  PTX registers are virtual.

Any compiler error or warning fails the run (exit status 1, the compiler's
output printed), with one exception: linking libclc's bitcode warns that its
triple (``amdgcn-unknown-amdhsa``, ``nvptx64-unknown-nvidiacl``) differs from
the kernel's in vendor and OS; that is how Debian's libclc is built and is
ignored when the architectures agree. The kernels compile warning-free today,
so any other warning is new and worth a look.

Build recipe: the source is ``octcl.device.programs.kernel_source`` (the
prelude ``kernels/prelude.cl``, ``#line 1``, then the kernel file: what octcl
builds; with ``--kernel-dir`` both files come from that folder) and the
options ``octcl.device.programs.build_options`` of each op's own
``program_defines`` (``octcl.device.scanner``, ``octcl.device.depth_order``,
``octcl.host.stage1.operator_device``, ``octcl.host.stage1.display_device``,
``octcl.host.stage1.levels_device``, ``octcl.host.optim.lbfgs_device``: the
functions octcl's own builds use), at the default scanner configuration
(Nz = 256, Nx = 512; work-groups of 64 for the field operator and the
reductions, as on any device that allows them); the language is OpenCL C 1.2
at -O3, as an OpenCL driver compiles it. libclc provides the builtins
(``-mlink-builtin-bitcode``: only the functions used are linked and they take
the target's features).

Fields reported per kernel (``--json``: one object a line):

``private_bytes``
    Private memory per work-item that lives outside registers: AMD
    ``ScratchSize`` (per lane, callees included), NVIDIA ptxas "cumulative
    stack size" (per thread; the stack frame when there are no calls).
``registers``
    Per work-item registers: AMD VGPRs (``TotalNumVgprs``: VGPRs + AGPRs on
    gfx90a), NVIDIA 32-bit registers; ``sgprs`` adds AMD's scalar registers.
``occupancy``, ``occupancy_max``, ``occupancy_unit``
    AMD: waves per SIMD as the compiler states it (``Occupancy``), out of 10
    on gfx906 and 8 on gfx90a (LLVM's ``AMDGPU::IsaInfo::getMaxWavesPerEU``).
    NVIDIA: resident warps per SM out of 64, computed below.
``shared_bytes``
    Local (LDS/shared) memory per work-group.
``sgpr_spills``, ``vgpr_spills`` (AMD, registers) / ``spill_store_bytes``, ``spill_load_bytes`` (NVIDIA)
    Registers spilled to scratch / local memory.

NVIDIA occupancy, the rules of ``cuda_occupancy.h`` (CUDA Toolkit, the
occupancy calculator's source) and the CUDA C++ Programming Guide's table of
compute capability 8.0: for a block of B threads (the kernel's
``reqd_work_group_size`` where it has one, as the work-group variant's
kernels do; otherwise ``--block-size``, 256 by default, since octcl leaves
the work-group size to the driver) and r registers,
s bytes of shared memory per thread block,

    warps per block   w = ⌈B / 32⌉
    registers/warp    R = ⌈32·r / 256⌉·256            (allocation unit 256)
    blocks by regs    ⌊⌊(65536 / 4) / R⌋·4 / w⌋       (4 sub-partitions; 0 if r > 255)
    blocks by warps   ⌊64 / w⌋
    blocks by shared  ⌊167936 / ⌈(s + 1024) / 128⌉·128⌋  (164 KiB, 1 KiB reserved per block)
    blocks            min(the three, 32)
    occupancy         blocks·w warps per SM, out of 64.

Local memory (``private_bytes``) lives in device memory and limits no
occupancy on either vendor; AMD's stated occupancy counts VGPRs, SGPRs and
LDS.

Registry: ``KERNEL_FILES`` names how each kernel file is built and ``KNOBS``
the compile-time knob values compiled. Kernel names are read from the
compiler's output; a ``kernels/*.cl`` that is not registered (other than the
prelude, which is part of every build) fails the run.

Measured (docs/benchmarks.md): the default builds (3 kernel files, W ∈ {8,
16}, 3 targets) take about 70 s of CPU, about 40 s on two cores; almost all
of it is LLVM's AMDGPU instruction scheduler on the float32 scanner (13 s per
build, against 3 s for float64 and under 1 s for PTX); the field operator's
two builds for the 3 targets take under 2 s (``--kernels field_operator``).
All of W = 2 … 16 is ``--knob spread_width=2..16``.

    python scripts/kernel_resources.py                 # table
    python scripts/kernel_resources.py --markdown      # table for docs
    python scripts/kernel_resources.py --json          # one JSON object a line
    python scripts/kernel_resources.py --kernels depth_order --targets sm_80
"""

from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import itertools
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from octcl.config import DEFAULT_CONFIG  # noqa: E402
from octcl.device import depth_order
from octcl.device.programs import PRELUDE, build_options, kernel_source
from octcl.device.scanner import KernelSettings, program_defines
from octcl.host.optim import lbfgs_device
from octcl.host.stage1 import display_device, levels_device, operator_device
from octcl.host.stage1.operator import lateral_taps


# ------------------------------------------------------------------ registry
@dataclasses.dataclass(frozen=True)
class KernelFile:
    """How octcl builds ``kernels/<name>.cl``.

    ``defines`` maps a :class:`KernelSettings` (its ``double`` that of the
    build) to the file's ``-D`` defines (the function octcl's own build uses);
    ``precisions`` are the builds made of each: "float32", "float64"
    (``-DOCTCL_DOUBLE``), or "integer" for a file without floating point,
    compiled once.
    """

    name: str
    defines: Callable[[KernelSettings], tuple]
    precisions: tuple[str, ...]


def _scanner_defines(settings: KernelSettings) -> tuple:
    return program_defines(DEFAULT_CONFIG, settings)


def _depth_order_defines(settings: KernelSettings) -> tuple:
    return depth_order.program_defines()


def _field_operator_defines(settings: KernelSettings) -> tuple:
    """The field operator's defines: R = 2 taps either side, P = 1024 padded columns (no knob)."""
    return operator_device.program_defines(DEFAULT_CONFIG, lateral_taps(DEFAULT_CONFIG).size // 2)


def _display_fit_defines(settings: KernelSettings) -> tuple:
    """The display fit's defines (``display_loss.cl``, ``adam.cl``) as a GPU gets them: λ_E = 0.1, a work-group
    per 8·64 pixels of a pass (no knob)."""
    return display_device.program_defines(DEFAULT_CONFIG, 0.1, cpu=False)


def _level_fit_defines(settings: KernelSettings) -> tuple:
    """``level_fit.cl``'s defines: reductions in work-groups of 64 (no knob)."""
    return levels_device.program_defines()


def _lbfgs_defines(settings: KernelSettings) -> tuple:
    """``lbfgs.cl``'s defines: reductions in work-groups of 64 (no knob)."""
    return lbfgs_device.program_defines()


#: Every kernel file octcl builds; a new ``kernels/<name>.cl`` is one line here.
KERNEL_FILES = (
    KernelFile("scanner", _scanner_defines, ("float32", "float64")),
    KernelFile("depth_order", _depth_order_defines, ("integer",)),
    KernelFile("field_operator", _field_operator_defines, ("float32", "float64")),
    KernelFile("display_loss", _display_fit_defines, ("float32", "float64")),
    KernelFile("adam", _display_fit_defines, ("float32", "float64")),
    KernelFile("level_fit", _level_fit_defines, ("float32", "float64")),
    KernelFile("lbfgs", _lbfgs_defines, ("float32", "float64")),
)

#: Compile-time knobs (fields of KernelSettings) and the values compiled. Every
#: combination is built; combinations that give a file the same defines are
#: built once. W ≤ 8 and W > 8 take 8- and 16-lane vectors: 8 and 16 are the
#: default and the largest of each. A new compile-time knob is one line here.
KNOBS = {"spread_width": (8, 16)}


@dataclasses.dataclass(frozen=True)
class Build:
    """One program as octcl builds it: kernel file, precision, knob values, compiler options."""

    file: str
    precision: str
    knobs: tuple[tuple[str, object], ...]
    options: tuple[str, ...]

    def stem(self) -> str:
        """A file name for the build: ``scanner-float32-spread_width8``."""
        return "-".join([self.file, self.precision] + [f"{key}{value}" for key, value in self.knobs])

    def label(self) -> str:
        knobs = " ".join(f"{key}={value}" for key, value in self.knobs)
        return f"kernels/{self.file}.cl {self.precision}" + (f" {knobs}" if knobs else "")


class RegistryError(ValueError):
    """A kernel file without a registry entry, or a registry entry without a file."""


def enumerate_builds(kernel_dir: Path, knobs: dict, only: list[str] | None = None) -> list[Build]:
    """Every build of the kernel files in ``kernel_dir`` for every combination of ``knobs``.

    Each file's knob settings are grouped by the defines they give it; a
    group's reported knobs are those constant within it (the knobs that
    change the file's code).
    """
    registered = {entry.name: entry for entry in KERNEL_FILES}
    if not (kernel_dir / f"{PRELUDE}.cl").exists():
        raise RegistryError(f"{kernel_dir / PRELUDE}.cl does not exist: every build starts with it")
    present = sorted(path.stem for path in kernel_dir.glob("*.cl") if path.stem != PRELUDE)
    unregistered = [name for name in present if name not in registered]
    if unregistered:
        raise RegistryError(
            f"{', '.join(f'{kernel_dir / name}.cl' for name in unregistered)}: no build registered; "
            f"add a KernelFile line to KERNEL_FILES in {Path(__file__).name}")
    wanted = only if only is not None else present
    for name in wanted:
        if name not in present:
            raise RegistryError(f"{kernel_dir / name}.cl does not exist")
    combinations = [dict(zip(knobs, values)) for values in itertools.product(*knobs.values())]
    builds = []
    for name in wanted:
        entry = registered[name]
        for precision in entry.precisions:
            double = precision == "float64"
            groups: dict[tuple, list[dict]] = {}
            for combination in combinations:
                settings = KernelSettings(**combination, double=double)
                groups.setdefault(tuple(entry.defines(settings)), []).append(combination)
            for defines, members in groups.items():
                varying = len(groups) > 1
                constant = tuple((key, members[0][key]) for key in knobs
                                 if varying and all(member[key] == members[0][key] for member in members))
                builds.append(Build(name, precision, constant, tuple(build_options(defines, double))))
    return builds


# ------------------------------------------------------------------- targets
@dataclasses.dataclass(frozen=True)
class Target:
    """A GPU the kernels are compiled for."""

    name: str
    vendor: str          # "amd" or "nvidia"
    triple: str
    libclc: str          # libclc bitcode file
    occupancy_max: int
    occupancy_unit: str

    @property
    def arch(self) -> str:
        return self.triple.split("-")[0]


TARGETS = {
    "gfx906": Target("gfx906", "amd", "amdgcn-amd-amdhsa", "amdgcn--amdhsa.bc", 10, "waves/SIMD"),
    "gfx90a": Target("gfx90a", "amd", "amdgcn-amd-amdhsa", "amdgcn--amdhsa.bc", 8, "waves/SIMD"),
    "sm_80": Target("sm_80", "nvidia", "nvptx64-nvidia-nvcl", "nvptx64--nvidiacl.bc", 64, "warps/SM"),
}


@dataclasses.dataclass(frozen=True)
class NvidiaLimits:
    """Per-SM limits of a compute capability (cuda_occupancy.h; CUDA C++ Programming Guide, Table 'Technical Specifications per Compute Capability')."""

    max_warps: int = 64
    max_blocks: int = 32
    registers: int = 65536
    max_registers_per_thread: int = 255
    register_unit: int = 256
    sub_partitions: int = 4
    shared_bytes: int = 167936          # 164 KiB on compute capability 8.0
    shared_unit: int = 128
    shared_reserved_per_block: int = 1024


NVIDIA_LIMITS = {"sm_80": NvidiaLimits()}


def nvidia_occupancy(registers: int, shared_bytes: int, block_size: int,
                     limits: NvidiaLimits = NVIDIA_LIMITS["sm_80"]) -> int:
    """Resident warps per SM for ``block_size`` threads (the module docstring's formulas)."""
    warps_per_block = math.ceil(block_size / 32)
    if registers > limits.max_registers_per_thread:
        return 0
    registers_per_warp = math.ceil(32 * registers / limits.register_unit) * limits.register_unit
    by_registers = (limits.registers // limits.sub_partitions // max(registers_per_warp, 1)
                    * limits.sub_partitions // warps_per_block)
    by_warps = limits.max_warps // warps_per_block
    shared_per_block = math.ceil((shared_bytes + limits.shared_reserved_per_block) / limits.shared_unit) * limits.shared_unit
    by_shared = limits.shared_bytes // shared_per_block
    return min(by_registers, by_warps, by_shared, limits.max_blocks) * warps_per_block


# --------------------------------------------------------------------- tools
@dataclasses.dataclass(frozen=True)
class Tools:
    clang: str
    llvm_nm: str
    libclc_dir: Path
    ptxas: str | None
    clang_version: str
    ptxas_version: str | None


class ToolMissingError(RuntimeError):
    """clang, llvm-nm or libclc is not installed; the message says how to get them."""


def find_tools(clang: str, libclc_dir: Path, ptxas: str | None) -> Tools:
    """Locate the compilers; llvm-nm is taken from clang's own directory."""
    hint = "install them with `apt-get install clang-14 libclc-14` (scripts/check_kernels.sh does)"
    clang_path = shutil.which(clang)
    if clang_path is None:
        raise ToolMissingError(f"{clang} not found; {hint}")
    llvm_nm = Path(clang_path).resolve().parent / "llvm-nm"
    if not llvm_nm.exists():
        raise ToolMissingError(f"llvm-nm not found next to {Path(clang_path).resolve()}; {hint}")
    for bitcode in {target.libclc for target in TARGETS.values()}:
        if not (libclc_dir / bitcode).exists():
            raise ToolMissingError(f"libclc bitcode {libclc_dir / bitcode} not found; {hint}")
    clang_version = subprocess.run([clang_path, "--version"], capture_output=True, text=True).stdout.splitlines()[0]
    ptxas_path = shutil.which(ptxas) if ptxas else None
    ptxas_version = None
    if ptxas_path:
        text = subprocess.run([ptxas_path, "--version"], capture_output=True, text=True).stdout
        found = re.search(r"release \S+ (V[\d.]+)", text)
        ptxas_version = f"ptxas {found.group(1) if found else '(unknown version)'}"
    return Tools(clang_path, str(llvm_nm), libclc_dir, ptxas_path, clang_version, ptxas_version)


# ------------------------------------------------------------------ compiling
class CompileError(RuntimeError):
    """A build failed or warned; the message holds the command and the compiler's output."""


_LIBCLC_TRIPLE_WARNING = re.compile(
    r"warning: linking module '[^']*': Linking two modules of different target triples: "
    r"'[^']*' is '(?P<theirs>[^']*)' whereas '[^']*' is '(?P<ours>[^']*)'\n\s*\[-Wlinker-warnings\]\n")


def _unexpected_diagnostics(stderr: str) -> str:
    """The compiler's output less the expected libclc triple warning (see the module docstring)."""
    def drop(match):
        same_arch = match["theirs"].split("-")[0] == match["ours"].split("-")[0]
        return "" if same_arch else match.group(0)

    text = _LIBCLC_TRIPLE_WARNING.sub(drop, stderr)
    text = re.sub(r"^\d+ warnings? generated\.\n", "", text, flags=re.M)
    return text.strip()


def _run(command: list[str], what: str) -> subprocess.CompletedProcess:
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0:
        raise CompileError(f"{what}: exit status {result.returncode}\n$ {' '.join(command)}\n"
                           f"{result.stdout}{result.stderr}".rstrip())
    return result


def _clang(build: Build, target: Target, tools: Tools, source: Path, output: Path) -> None:
    cpu = ["-mcpu=" + target.name] if target.vendor == "amd" else ["-march=" + target.name]
    command = [tools.clang, "-cl-std=CL1.2", "-target", target.triple, *cpu, "-O3",
               *(["-nogpulib"] if target.vendor == "amd" else []),
               "-Xclang", "-mlink-builtin-bitcode", "-Xclang", str(tools.libclc_dir / target.libclc),
               *build.options, "-S", str(source), "-o", str(output)]
    what = f"{build.label()} for {target.name}"
    result = _run(command, what)
    unexpected = _unexpected_diagnostics(result.stderr)
    if unexpected:
        raise CompileError(f"{what}: compiler warnings\n$ {' '.join(command)}\n{unexpected}")


def _amd_kernel_info(assembly: str) -> dict[str, dict]:
    """{kernel: {"Occupancy": "4", "ScratchSize": "4104", ...}} from the "; Kernel info:" comment blocks."""
    kernels, name, block = {}, None, None
    for line in assembly.splitlines():
        size = re.match(r"\s*\.size\s+([\w.$]+),\s*\.Lfunc_end", line)
        if size:
            name = size.group(1)
        elif line.startswith("; Kernel info:"):
            block = kernels.setdefault(name, {})
        elif block is not None and line.startswith(";"):
            key, _, value = line[1:].partition(":")
            block[key.strip()] = value.strip()
        else:
            block = None
    return kernels


def _amd_metadata(assembly: str) -> dict[str, dict]:
    """{kernel: {".sgpr_spill_count": 0, ...}} from the amdhsa.kernels metadata (keys follow .name)."""
    kernels, name = {}, None
    for line in assembly.split(".amdgpu_metadata", 1)[-1].splitlines():
        found = re.match(r"\s+(\.\w+):\s+(\S+)\s*$", line)
        if not found:
            continue
        key, value = found.groups()
        if key == ".name":
            name = value
            kernels[name] = {}
        elif name is not None and value.isdigit():
            kernels[name][key] = int(value)
    return kernels


def compile_amd(build: Build, target: Target, tools: Tools, source: Path, work: Path) -> list[dict]:
    """Assembly with the compiler's Kernel info, assembled and checked for undefined symbols."""
    assembly_path, object_path = work / "kernel.s", work / "kernel.o"
    _clang(build, target, tools, source, assembly_path)
    _run([tools.clang, "-target", target.triple, "-mcpu=" + target.name, "-c", str(assembly_path),
          "-o", str(object_path)], f"{build.label()} for {target.name}: assembling")
    undefined = _run([tools.llvm_nm, "--undefined-only", "--format=just-symbols", str(object_path)],
                     "llvm-nm").stdout.split()
    if undefined:
        raise CompileError(f"{build.label()} for {target.name}: undefined functions {', '.join(undefined)} "
                           "(not in the kernel file nor in libclc)")
    assembly = assembly_path.read_text()
    metadata = _amd_metadata(assembly)
    records = []
    for kernel, info in _amd_kernel_info(assembly).items():
        meta = metadata.get(kernel, {})
        records.append({
            "kernel": kernel,
            "private_bytes": int(info["ScratchSize"]),
            "registers": int(info.get("TotalNumVgprs", info["NumVgprs"])),
            "occupancy": int(info["Occupancy"]),
            "sgprs": int(info["NumSgprs"]),
            "vgprs": int(info["NumVgprs"]),
            "agprs": int(info.get("NumAgprs", 0)),
            "shared_bytes": int(info["LDSByteSize"].split()[0]),
            "sgpr_spills": meta.get(".sgpr_spill_count"),
            "vgpr_spills": meta.get(".vgpr_spill_count"),
            "code_bytes": int(info["codeLenInByte"].lstrip("= ")) if "codeLenInByte" in info else None,
            "reported_by": f"{tools.clang_version} (AMDGPU Kernel info)",
        })
    return records


def _ptxas_report(text: str) -> dict[str, dict]:
    """{entry: {...}} from ``ptxas -v`` output."""
    kernels, entry = {}, None
    for line in text.splitlines():
        found = re.search(r"Compiling entry function '([\w.$]+)'", line)
        if found:
            entry = kernels.setdefault(found.group(1), {"shared_bytes": 0})
            continue
        found = re.search(r"Function properties for ([\w.$]+)", line)
        if found:
            entry = kernels.get(found.group(1))
            continue
        if entry is None:
            continue
        found = re.search(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads", line)
        if found:
            entry["stack_frame_bytes"], entry["spill_store_bytes"], entry["spill_load_bytes"] = map(int, found.groups())
        found = re.search(r"Used (\d+) registers", line)
        if found:
            entry["registers"] = int(found.group(1))
            cumulative = re.search(r"(\d+) bytes cumulative stack size", line)
            entry["private_bytes"] = int(cumulative.group(1)) if cumulative else entry.get("stack_frame_bytes", 0)
            shared = re.search(r"(\d+) bytes smem", line)
            entry["shared_bytes"] = int(shared.group(1)) if shared else 0
    return kernels


def _ptx_report(ptx: str) -> dict[str, dict]:
    """{entry: {...}} from the PTX alone: the local depot of each entry (registers are virtual)."""
    kernels = {}
    for match in re.finditer(r"\.entry\s+([\w.$]+)\s*\((.*?)\n\}", ptx, flags=re.S):
        depot = re.search(r"\.local\s+\.align\s+\d+\s+\.b8\s+__local_depot\d+\[(\d+)\]", match.group(2))
        shared = sum(int(n) for n in re.findall(r"\.shared\s+\.align\s+\d+\s+\.b8\s+[\w.$]+\[(\d+)\]", ptx))
        kernels[match.group(1)] = {"private_bytes": int(depot.group(1)) if depot else 0, "registers": None,
                                   "shared_bytes": shared}
    defined = set(re.findall(r"\.func\s+(?:\([^)]*\)\s*)?([\w.$]+)\s*\([^)]*\)\s*\{", ptx, flags=re.S))
    declared = set(re.findall(r"\.func\s+(?:\([^)]*\)\s*)?([\w.$]+)\s*(?:\([^)]*\)\s*)?;", ptx, flags=re.S))
    if declared - defined:
        raise CompileError(f"undefined functions {', '.join(sorted(declared - defined))}")
    return kernels


def compile_nvidia(build: Build, target: Target, tools: Tools, source: Path, work: Path,
                   block_size: int) -> list[dict]:
    """PTX from clang, then ptxas -v (or the PTX's own declarations without ptxas)."""
    ptx_path = work / "kernel.ptx"
    _clang(build, target, tools, source, ptx_path)
    what = f"{build.label()} for {target.name}"
    if tools.ptxas:
        command = [tools.ptxas, f"-arch={target.name}", "-v", str(ptx_path), "-o", str(work / "kernel.cubin")]
        result = _run(command, f"{what}: ptxas")
        if re.search(r"warning", result.stdout + result.stderr, flags=re.I):
            raise CompileError(f"{what}: ptxas warnings\n$ {' '.join(command)}\n{result.stdout}{result.stderr}")
        report, reported_by = _ptxas_report(result.stdout + result.stderr), tools.ptxas_version
    else:
        try:
            report = _ptx_report(ptx_path.read_text())
        except CompileError as exc:
            raise CompileError(f"{what}: {exc}") from None
        reported_by = f"{tools.clang_version} (PTX declarations; no ptxas)"
    # A kernel declared with reqd_work_group_size(N, 1, 1) always runs in
    # blocks of N (clang-14 does not carry the attribute into PTX, so it is
    # read from the source, N resolved through the build's -D defines).
    defines = dict(option[2:].split("=", 1) for option in build.options if option.startswith("-D"))
    required = {name: int(defines.get(size, size)) for size, name in re.findall(
        r"reqd_work_group_size\(\s*(\w+)\s*,\s*1\s*,\s*1\s*\)\)\)\s*void\s+(\w+)", source.read_text())}
    records = []
    for kernel, entry in report.items():
        registers = entry.get("registers")
        kernel_block_size = required.get(kernel, block_size)
        records.append({
            "kernel": kernel,
            "private_bytes": entry["private_bytes"],
            "registers": registers,
            "occupancy": None if registers is None else nvidia_occupancy(
                registers, entry["shared_bytes"], kernel_block_size, NVIDIA_LIMITS[target.name]),
            "shared_bytes": entry["shared_bytes"],
            "spill_store_bytes": entry.get("spill_store_bytes"),
            "spill_load_bytes": entry.get("spill_load_bytes"),
            "block_size": kernel_block_size,
            "reported_by": reported_by,
        })
    return records


def _shown_path(source: Path) -> str:
    """``kernels/<name>.cl`` for the repository's kernels, else the path given."""
    try:
        return str(source.resolve().relative_to(REPO))
    except ValueError:
        return str(source)


def compile_build(build: Build, target: Target, tools: Tools, kernel_dir: Path, block_size: int,
                  save_dir: Path | None = None) -> list[dict]:
    """The records of every kernel of ``build`` on ``target``; raises :class:`CompileError`.

    With ``save_dir`` the compiler's output (AMD assembly, PTX) is kept there,
    named after the build and target, also when the build fails.
    """
    with tempfile.TemporaryDirectory(prefix="kernel_resources_") as work:
        # The source octcl builds: the prelude, then the file from its line 1 (so the compiler's line
        # numbers are the file's), named as the file.
        source = Path(work) / f"{build.file}.cl"
        source.write_text(kernel_source(build.file, kernel_dir), encoding="utf-8")
        try:
            if target.vendor == "amd":
                records = compile_amd(build, target, tools, source, Path(work))
            else:
                records = compile_nvidia(build, target, tools, source, Path(work), block_size)
        finally:
            if save_dir is not None:
                for output in Path(work).glob("kernel.[sp]*"):
                    shutil.copy(output, save_dir / f"{build.stem()}-{target.name}{output.suffix}")
    if not records:
        raise CompileError(f"{build.label()} for {target.name}: no kernel found in the compiler's output")
    common = {"file": _shown_path(kernel_dir / f"{build.file}.cl"), "target": target.name, "arch": target.arch,
              "precision": build.precision, **{key: None for key in KNOBS}, **dict(build.knobs),
              "occupancy_max": target.occupancy_max, "occupancy_unit": target.occupancy_unit}
    return [{"kernel": r["kernel"], **common, **r} for r in records]


# -------------------------------------------------------------------- output
_COLUMNS = ("kernel", "file", "precision", "knobs", "target", "private B", "registers", "SGPRs",
            "spills", "shared B", "occupancy")


def _row(record: dict) -> list[str]:
    knobs = " ".join(f"{key}={record[key]}" for key in KNOBS if record.get(key) is not None)
    if record["arch"] == "amdgcn":
        spills = f"{record['sgpr_spills']} s, {record['vgpr_spills']} v"
    elif record.get("spill_store_bytes") is not None:
        spills = f"{record['spill_store_bytes']} B st, {record['spill_load_bytes']} B ld"
    else:
        spills = "?"
    occupancy = ("?" if record["occupancy"] is None
                 else f"{record['occupancy']}/{record['occupancy_max']} {record['occupancy_unit']}")
    return [record["kernel"], record["file"], record["precision"], knobs or "-", record["target"],
            f"{record['private_bytes']:,}", "?" if record["registers"] is None else str(record["registers"]),
            str(record.get("sgprs", "-")), spills, str(record["shared_bytes"]), occupancy]


def format_table(records: list[dict], markdown: bool) -> str:
    rows = [_row(record) for record in records]
    if markdown:
        lines = ["| " + " | ".join(_COLUMNS) + " |", "|" + "---|" * len(_COLUMNS)]
        return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])
    widths = [max(len(cell) for cell in column) for column in zip(_COLUMNS, *rows)]
    return "\n".join("  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip()
                     for row in [list(_COLUMNS), *rows])


def _parse_knob(text: str) -> tuple[str, tuple]:
    """``NAME=V1,V2`` or ``NAME=A..B`` (integers A to B inclusive)."""
    name, sep, values = text.partition("=")
    if not sep or name not in KNOBS:
        raise argparse.ArgumentTypeError(f"--knob {text!r}: expected NAME=VALUES with NAME one of {', '.join(KNOBS)}")
    try:
        if ".." in values:
            first, last = (int(v) for v in values.split(".."))
            return name, tuple(range(first, last + 1))
        return name, tuple(int(v) for v in values.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--knob {text!r}: values must be integers") from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    output = parser.add_mutually_exclusive_group()
    output.add_argument("--json", action="store_true", help="one JSON object per kernel and line")
    output.add_argument("--markdown", action="store_true", help="the table in Markdown")
    parser.add_argument("--targets", default=",".join(TARGETS),
                        help=f"comma-separated, of {', '.join(TARGETS)} (default: all)")
    parser.add_argument("--kernels", help="comma-separated kernel file names (default: every kernels/*.cl)")
    parser.add_argument("--knob", action="append", type=_parse_knob, default=[],
                        help="knob values, e.g. spread_width=8,16 or spread_width=2..16 "
                             f"(default: {', '.join(f'{k}={v}' for k, v in KNOBS.items())})")
    parser.add_argument("--kernel-dir", type=Path, default=REPO / "kernels")
    parser.add_argument("--clang", default=os.environ.get("CLANG", "clang-14"))
    parser.add_argument("--libclc-dir", type=Path, default=Path(os.environ.get("LIBCLC_DIR", "/usr/lib/clc")))
    parser.add_argument("--ptxas", default=os.environ.get("PTXAS", "ptxas"),
                        help="ptxas command; '' reads the PTX alone")
    parser.add_argument("--block-size", type=int, default=256, help="NVIDIA threads per block for occupancy")
    parser.add_argument("--save-dir", type=Path, help="keep the compiler's output (assembly, PTX) here")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="parallel compiles")
    args = parser.parse_args(argv)

    targets = []
    for name in args.targets.split(","):
        if name not in TARGETS:
            parser.error(f"unknown target {name!r}; known: {', '.join(TARGETS)}")
        targets.append(TARGETS[name])
    knobs = {**KNOBS, **dict(args.knob)}
    try:
        builds = enumerate_builds(args.kernel_dir, knobs, args.kernels.split(",") if args.kernels else None)
        tools = find_tools(args.clang, args.libclc_dir, args.ptxas)
    except (RegistryError, ToolMissingError) as exc:
        print(f"kernel_resources: {exc}", file=sys.stderr)
        return 2

    if args.save_dir:
        args.save_dir.mkdir(parents=True, exist_ok=True)
    jobs = [(build, target) for build in builds for target in targets]
    # Longest first (AMD float32 builds take the most time), for two busy cores.
    order = sorted(jobs, key=lambda job: (job[1].vendor != "amd", job[0].precision != "float32"))
    records, failures = {}, []
    with concurrent.futures.ThreadPoolExecutor(max(1, args.jobs)) as pool:
        futures = {pool.submit(compile_build, build, target, tools, args.kernel_dir,
                               args.block_size, args.save_dir): (build, target)
                   for build, target in order}
        for future in concurrent.futures.as_completed(futures):
            try:
                records[futures[future]] = future.result()
            except CompileError as exc:
                failures.append(str(exc))
    for failure in failures:
        print(f"kernel_resources: FAILED {failure}\n", file=sys.stderr)
    ordered = [record for job in jobs if job in records for record in records[job]]
    ordered.sort(key=lambda r: (r["file"], r["kernel"], r["precision"], [(r[k] is None, r[k]) for k in KNOBS]))
    if args.json:
        for record in ordered:
            print(json.dumps(record))
    else:
        print(format_table(ordered, args.markdown))
    status = f"{len(jobs) - len(failures)} of {len(jobs)} builds compiled ({tools.clang_version}"
    status += f"; {tools.ptxas_version})" if tools.ptxas_version else "; no ptxas)"
    print(f"kernel_resources: {status}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
