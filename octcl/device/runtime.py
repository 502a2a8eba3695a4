"""OpenCL runtime: the implementations octcl registers, device choice, quiet builds, clear errors.

Implementations, per system. pyopencl's wheel brings the ICD loader that
finds the drivers:

- Linux: the PoCL of PyPI's ``pocl-binary-distribution`` (x86-64), and the
  drivers the system registers in ``/etc/OpenCL/vendors`` (NVIDIA, ROCm,
  Intel GPU, the distribution's PoCL). Two more are registered by octcl
  when present, with nothing exported by the user: Intel's OpenCL CPU
  runtime from PyPI (``intel-opencl-rt``, the ``octcl[intel]`` extra; it
  builds on CPUs whose LLVM target PoCL 3.0 does not know) and Debian's
  Oclgrind simulator (package ``oclgrind``, which registers no ICD of its
  own). So is a GPU driver's OpenCL library that is on disk but named
  by no ICD file (:func:`gpu_driver_libraries`: NVIDIA's
  ``libnvidia-opencl.so.1``, AMD's ``libamdocl64.so``, Intel's
  ``libigdrcl.so``, as a container that mounts the host's driver leaves
  them). :func:`register_runtimes` writes an ICD vendor folder naming them
  and every system ICD under the cache folder and points
  ``OCL_ICD_VENDORS`` at it, unless the user has set that variable.
- Windows: the drivers registered in the registry (NVIDIA's and AMD's GPU
  drivers, Intel's graphics driver), and Intel's CPU runtime from PyPI (a
  dependency there), which :func:`register_runtimes` names in
  ``OCL_ICD_FILENAMES`` (read by the Khronos loader beside the registry)
  with its folder put on ``PATH`` for the libraries it loads, unless the
  user has set ``OCL_ICD_FILENAMES``.
- macOS: Apple's OpenCL framework, which pyopencl links directly (its GPU
  has no ``double``; octcl's kernels are float32 unless asked otherwise).

Every registration happens before the first platform query: ``pyopencl_module()``
calls it.

Device choice. The ``device`` argument, else the ``OCTCL_DEVICE``
environment variable, names a device:

- ``"gpu"`` / ``"cpu"``: the first device of that type that builds (below);
- ``"P:D"``: platform index P, device index D (as ``octcl devices`` lists);
- any other text: the first device whose implementation (``pocl``,
  ``intel``, ``oclgrind``, ...), platform or device name contains it
  (case-insensitive), e.g. ``"pocl"`` or ``"nvidia"``.

Without a choice, a device is a candidate only if a small program builds on
it (:func:`probe`, remembered per device and driver version in the cache
folder): the first GPU that builds, else the CPU implementation that builds
and measured fastest (:data:`CPU_ORDER`). A simulator (Oclgrind) is used
only when named. When no device builds, the error names each device, its
compiler's own message and the fix.

Builds print nothing: the compiler's log (vectoriser remarks, warnings)
and whatever a compiler writes to standard error itself go to the
``octcl`` logger at debug level (``octcl --debug`` shows them); a failed
build raises with its full log (:func:`quiet_build`). octcl's own programs
are built in one place, :mod:`octcl.device.programs`.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import logging
import os
import re
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

DEVICE_ENV = "OCTCL_DEVICE"
#: Folder of octcl's caches (build probes, the ICD vendor folder); default ``$XDG_CACHE_HOME/octcl``.
CACHE_ENV = "OCTCL_CACHE_DIR"
#: The ICD loader's variable: a folder of ``.icd`` files, each naming one implementation's library.
ICD_VENDORS_ENV = "OCL_ICD_VENDORS"
#: The Khronos ICD loader's variable on Windows: ICD libraries to load beside the registry's, ``;``-separated.
ICD_FILENAMES_ENV = "OCL_ICD_FILENAMES"
#: The library of Intel's OpenCL CPU runtime in its PyPI distribution, per system.
INTEL_CPU_LIBRARY = {"win32": "intelocl64.dll", "linux": "libintelocl.so"}
#: Where the system registers its OpenCL drivers.
SYSTEM_VENDORS = Path("/etc/OpenCL/vendors")
#: Debian's Oclgrind ICD library (the package installs no .icd file for it).
OCLGRIND_LIBRARY = Path("/usr/lib/oclgrind/liboclgrind-rt-icd.so")
#: GPU drivers' OpenCL libraries, per implementation, which a driver can leave on disk with no ICD file
#: naming it (a container that mounts the host's driver, a driver unpacked by hand): NVIDIA's, AMD ROCm's
#: and Intel's graphics compute runtime. Each name is looked for in :data:`DRIVER_FOLDERS`.
GPU_DRIVER_LIBRARIES = {"nvidia": ("libnvidia-opencl.so.1", "libnvidia-opencl.so"),
                        "amd": ("libamdocl64.so",),
                        "intel-gpu": ("libigdrcl.so",)}
#: Where GPU drivers put those libraries, after the folders of ``LD_LIBRARY_PATH``: the loader's usual
#: folders and the drivers' own (NVIDIA's container mount, ROCm's tree, Intel's compute runtime).
DRIVER_FOLDERS = (Path("/usr/local/nvidia/lib64"), Path("/usr/local/nvidia/lib"), Path("/usr/lib/x86_64-linux-gnu"),
                  Path("/usr/lib/aarch64-linux-gnu"), Path("/usr/lib64"), Path("/usr/lib"), Path("/opt/rocm/lib"),
                  Path("/opt/rocm/opencl/lib"), Path("/usr/lib/x86_64-linux-gnu/intel-opencl"))
#: CPU implementations, fastest first on the x86-64 CPU measured by ``scripts/bench_implementations.py``
#: (docs/benchmarks.md, "OpenCL implementations"); others follow in listing order.
CPU_ORDER = ("intel", "pocl")
#: Implementations octcl uses only when named: a simulator checks kernels, it does not run them for users.
SIMULATORS = ("oclgrind",)
#: The program a device must build to be a candidate: any kernel fails on a compiler that cannot target the CPU.
PROBE_SOURCE = ("__kernel void probe(__global float *octcl_probe_data) "
                "{ octcl_probe_data[get_global_id(0)] *= 2.0f; }")

#: How to get a device that builds, per system (the end of the "no device builds" error).
_FIX = {
    "linux": ("fix: pip install 'octcl[intel]' (Intel's OpenCL CPU runtime, any x86-64 CPU, no root; "
              "scripts/setup.sh installs it), or install a working OpenCL driver (the distribution's "
              "pocl-opencl-icd, or your GPU vendor's)"),
    "win32": ("fix: pip install intel-opencl-rt intel-cmplr-lib-rt (Intel's OpenCL CPU runtime, installed with "
              "octcl on Windows), or install or update your GPU's driver (NVIDIA, AMD or Intel), which brings "
              "its OpenCL"),
    "darwin": "fix: Apple's OpenCL comes with macOS; choose another of its devices with --device (octcl devices)",
}
_NO_PLATFORM_HELP = {
    "linux": ("no OpenCL platform found. octcl needs an OpenCL driver: on x86-64, PoCL "
              "(`pip install pocl-binary-distribution`, installed with octcl) or Intel's CPU runtime "
              "(`pip install 'octcl[intel]'`); on any CPU, the distribution's PoCL (`apt-get install "
              "pocl-opencl-icd`); for GPUs the vendor's OpenCL driver (NVIDIA, AMD ROCm, Intel)."),
    "win32": ("no OpenCL platform found. octcl needs an OpenCL driver: Intel's CPU runtime (`pip install "
              "intel-opencl-rt intel-cmplr-lib-rt`, installed with octcl), or your GPU's driver (NVIDIA, AMD, "
              "Intel), which registers its OpenCL."),
    "darwin": "no OpenCL platform found: Apple's OpenCL framework, part of macOS, did not answer.",
}


def _for_this_system(texts: dict[str, str]) -> str:
    """The text of ``texts`` for this system; Linux's for other POSIX systems (their loader works the same)."""
    return texts.get(sys.platform, texts["linux"])


logger = logging.getLogger("octcl")


class OpenCLUnavailableError(RuntimeError):
    """No usable OpenCL platform or device; the message says how to get one."""


def cache_dir() -> Path:
    """octcl's cache folder: ``$OCTCL_CACHE_DIR``, else ``$XDG_CACHE_HOME/octcl``, else ``~/.cache/octcl``."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "octcl"


def _intel_cpu_library() -> Path | None:
    """The library of the installed ``intel-opencl-rt`` distribution on this system, if any."""
    name = INTEL_CPU_LIBRARY.get(sys.platform)
    try:
        files = metadata.distribution("intel-opencl-rt").files or []
    except metadata.PackageNotFoundError:
        return None
    for file in files:
        if file.name == name:
            path = Path(file.locate()).resolve()
            return path if path.exists() else None
    return None


def bundled_libraries() -> dict[str, Path]:
    """The ICD libraries octcl registers beside the system's: {implementation: library}."""
    found = {"intel": _intel_cpu_library(),
             "oclgrind": OCLGRIND_LIBRARY if sys.platform == "linux" and OCLGRIND_LIBRARY.exists() else None}
    return {name: path for name, path in found.items() if path is not None}


def _system_icds() -> dict[str, str]:
    """The system's ICD files (:data:`SYSTEM_VENDORS`): {file name: the library line it holds}."""
    icds = {}
    if SYSTEM_VENDORS.is_dir():
        for icd in sorted(SYSTEM_VENDORS.glob("*.icd")):
            try:
                icds[icd.name] = icd.read_text()
            except OSError:  # an unreadable ICD is one the system's own loader skips too
                continue
    return icds


def gpu_driver_libraries(system_icds: dict[str, str] | None = None) -> dict[str, Path]:
    """GPU drivers' OpenCL libraries on disk that no system ICD file names (Linux): {implementation: library}.

    A driver's library counts as named where an ICD file's line ends with
    one of its file names (:data:`GPU_DRIVER_LIBRARIES`), as a path or alone
    (the loader then finds it on its own search path). The folders of
    ``LD_LIBRARY_PATH`` are searched first, then :data:`DRIVER_FOLDERS`.
    """
    if sys.platform != "linux":
        return {}
    named = {Path(text.strip()).name for text in (_system_icds() if system_icds is None else system_icds).values()}
    folders = [Path(entry) for entry in os.environ.get("LD_LIBRARY_PATH", "").split(os.pathsep) if entry]
    found = {}
    for name, files in GPU_DRIVER_LIBRARIES.items():
        if named.intersection(files):
            continue
        library = next((folder / file for folder in [*folders, *DRIVER_FOLDERS] for file in files
                        if (folder / file).is_file()), None)
        if library is not None:
            found[name] = library
    return found


def register_runtimes() -> Path | str | None:
    """Make the bundled implementations (:func:`bundled_libraries`) visible to the ICD loader.

    Linux: points ``OCL_ICD_VENDORS`` at a vendor folder of the bundled
    implementations, the GPU drivers' libraries that no ICD file names
    (:func:`gpu_driver_libraries`) and the system's ICDs
    (:func:`_register_vendor_folder`); returns the folder. Windows: names the bundled libraries in ``OCL_ICD_FILENAMES``
    and puts their folders first on ``PATH``; returns the variable's
    value. Does nothing (returns None) where the user has set the variable
    of that system, no bundled library is installed, or the system has no
    ICD loader (macOS).
    """
    bundled = bundled_libraries()
    if sys.platform == "win32":
        if os.environ.get(ICD_FILENAMES_ENV) or not bundled:
            return None
        libraries = [str(path) for path in bundled.values()]
        folders = [str(path.parent) for path in bundled.values()]
        os.environ["PATH"] = os.pathsep.join([*folders, os.environ.get("PATH", "")])
        os.environ[ICD_FILENAMES_ENV] = ";".join(libraries)
        return os.environ[ICD_FILENAMES_ENV]
    if sys.platform == "darwin" or os.environ.get(ICD_VENDORS_ENV):
        return None
    system = _system_icds()
    bundled = {**bundled, **gpu_driver_libraries(system)}
    return _register_vendor_folder(bundled, system) if bundled else None


def _register_vendor_folder(bundled: dict[str, Path], system_icds: dict[str, str]) -> Path | None:
    """Point ``OCL_ICD_VENDORS`` at a folder of ``.icd`` files: ``bundled`` and the system's.

    The folder is named by its contents, so processes that share the cache
    share it; it is written to a temporary name and renamed.
    """
    icds = {f"octcl-{name}.icd": f"{path}\n" for name, path in bundled.items()}
    icds.update(system_icds)
    digest = hashlib.sha256(json.dumps(icds, sort_keys=True).encode()).hexdigest()[:16]
    folder = cache_dir() / "icd" / digest
    if not folder.is_dir():
        try:
            folder.parent.mkdir(parents=True, exist_ok=True)
            scratch = Path(tempfile.mkdtemp(dir=folder.parent, prefix=".tmp-"))
            for name, text in icds.items():
                (scratch / name).write_text(text)
            try:
                scratch.rename(folder)
            except OSError:  # another process wrote the same folder first
                for file in scratch.iterdir():
                    file.unlink()
                scratch.rmdir()
        except OSError as exc:
            logger.debug("octcl: cannot write the ICD vendor folder %s (%s): bundled runtimes stay unregistered",
                         folder, exc)
            return None
    os.environ[ICD_VENDORS_ENV] = str(folder)
    return folder


@functools.lru_cache(maxsize=None)
def pyopencl_module():
    """pyopencl, imported once octcl has registered its runtimes (:func:`register_runtimes`)."""
    register_runtimes()
    try:
        import pyopencl
    except ImportError as exc:  # pragma: no cover - pyopencl is a dependency
        raise OpenCLUnavailableError(f"pyopencl cannot be imported ({exc})") from None
    return pyopencl


def list_devices() -> list[tuple[str, object]]:
    """All OpenCL devices as ("P:D", device) pairs."""
    cl = pyopencl_module()
    try:
        platforms = cl.get_platforms()
    except cl.Error:
        platforms = []
    devices = []
    for p_index, platform_ in enumerate(platforms):
        try:
            platform_devices = platform_.get_devices()
        except cl.Error:
            continue
        for d_index, device in enumerate(platform_devices):
            devices.append((f"{p_index}:{d_index}", device))
    return devices


def implementation(device) -> str:
    """The OpenCL implementation behind a device: ``pocl``, ``intel`` (the CPU runtime), ``intel-gpu``,
    ``oclgrind``, or the first word of its platform's name in lower case (``nvidia``, ``amd``, ``rusticl``)."""
    name = device.platform.name.strip()
    if name == "Portable Computing Language":
        return "pocl"
    if name == "Intel(R) OpenCL":
        return "intel"
    if name == "Intel(R) OpenCL Graphics":
        return "intel-gpu"
    if name == "Oclgrind":
        return "oclgrind"
    if name == "Apple":
        return "apple"
    return re.sub(r"\(.*?\)", "", (name.split() or ["unknown"])[0]).lower()


def describe(device) -> str:
    """One line naming a device, its implementation and its memory."""
    cl = pyopencl_module()
    kinds = [(name, getattr(cl.device_type, name.upper())) for name in ("gpu", "cpu", "accelerator")]
    kind = ("simulator" if implementation(device) in SIMULATORS
            else next((name for name, bit in kinds if device.type & bit), "other"))
    return (f"{device.name.strip()} ({kind}, {implementation(device)}: {device.platform.name.strip()} "
            f"{device.driver_version.strip()}, {device.global_mem_size / 2**30:.1f} GiB, "
            f"fp64 {'yes' if has_fp64(device) else 'no'})")


def has_fp64(device) -> bool:
    """Whether ``device`` computes in ``double``: it names ``cl_khr_fp64`` and reports a double config.

    The extension is asked first: some drivers without it (Apple's GPUs)
    answer the double-config query with an error.
    """
    if "cl_khr_fp64" not in device.extensions.split():
        return False
    try:
        return bool(device.double_fp_config)
    except pyopencl_module().Error:
        return False


@dataclass(frozen=True)
class Probe:
    """Whether :data:`PROBE_SOURCE` builds on a device, and the compiler's message where it does not."""

    builds: bool
    log: str = ""

    @property
    def error(self) -> str:
        """The compiler's own error: the first line of its log that says ``error``, else its first line."""
        lines = [line.strip() for line in self.log.splitlines() if line.strip()]
        for line in lines:
            if "error" in line.lower() and "clBuildProgram failed" not in line:
                return line
        return lines[0] if lines else ""


def _probe_key(device) -> str:
    identity = [device.platform.name, device.platform.version, device.name, device.driver_version, PROBE_SOURCE]
    return hashlib.sha256("\0".join(identity).encode()).hexdigest()[:24]


@functools.lru_cache(maxsize=None)
def _probe_in_process(key: str, device) -> Probe:
    path = cache_dir() / "probes" / f"{key}.json"
    try:
        return Probe(**json.loads(path.read_text()))
    except (OSError, ValueError, TypeError):
        pass
    cl = pyopencl_module()
    try:
        context, _ = context_for(device)
        quiet_build(context, PROBE_SOURCE, [], device, binary_cache=False)
        result = Probe(True)
    except cl.Error as exc:
        result = Probe(False, str(exc))
    try:  # remembered for the next process; a cache that cannot be written only costs a build
        path.parent.mkdir(parents=True, exist_ok=True)
        scratch = path.with_name(f".{path.name}.{os.getpid()}")
        scratch.write_text(json.dumps({"builds": result.builds, "log": result.log}))
        os.replace(scratch, path)
    except OSError:
        pass
    return result


def probe(device) -> Probe:
    """Build :data:`PROBE_SOURCE` on ``device``, once per device, driver version and probe program.

    The result is kept in ``cache_dir()/probes`` (and in memory), so a
    later process asks no compiler.
    """
    return _probe_in_process(_probe_key(device), device)


def _ranked(devices: list[tuple[str, object]], wanted=None) -> list[tuple[str, object, str]]:
    """The devices octcl would use, best first, with the reason for each: (key, device, reason)."""
    cl = pyopencl_module()
    usable = [(key, d) for key, d in devices if implementation(d) not in SIMULATORS]
    gpus = [(key, d, "the first GPU that builds octcl's probe kernel")
            for key, d in usable if d.type & cl.device_type.GPU]
    order = {name: rank for rank, name in enumerate(CPU_ORDER)}
    cpus = sorted(((key, d) for key, d in usable if d.type & cl.device_type.CPU and not d.type & cl.device_type.GPU),
                  key=lambda item: order.get(implementation(item[1]), len(order)))
    cpu_reason = ("no GPU builds; of the CPU implementations that build, the fastest measured "
                  f"(order {', '.join(CPU_ORDER)}: docs/benchmarks.md)")
    others = [(key, d, "no GPU or CPU device builds") for key, d in usable
              if not d.type & (cl.device_type.GPU | cl.device_type.CPU)]
    ranked = gpus + [(key, d, cpu_reason) for key, d in cpus] + others
    if wanted is not None:
        ranked = [(key, d, f"the first {wanted.upper()} that builds, in octcl's order")
                  for key, d, _ in ranked if d.type & getattr(cl.device_type, wanted.upper())]
    return ranked


def choose_device(choice: str | None = None):
    """The OpenCL device for ``choice`` (see the module docstring) and why: (device, reason)."""
    devices = list_devices()
    if not devices:
        raise OpenCLUnavailableError(_for_this_system(_NO_PLATFORM_HELP))
    choice = choice if choice is not None else os.environ.get(DEVICE_ENV) or None
    text = None if choice is None else choice.strip().lower()
    if text is None or text in ("gpu", "cpu"):
        candidates = _ranked(devices, text)
        for key, device, reason in candidates:
            if probe(device).builds:
                return device, reason
        if not candidates:
            what = ("no OpenCL device but a simulator, which octcl uses only when named" if text is None
                    else f"no {text.upper()} OpenCL device")
            raise OpenCLUnavailableError(f"{what}. Devices: " + "; ".join(f"{key} {describe(d)}" for key, d in devices))
        failures = "; ".join(f"{key} {d.name.strip()} ({implementation(d)}): {probe(d).error}"
                             for key, d, _ in candidates)
        raise OpenCLUnavailableError(f"no OpenCL device can build octcl's kernels: {failures}. "
                                     f"{_for_this_system(_FIX)}")
    for key, device in devices:
        if text == key or text in implementation(device) or text in device.name.lower() \
                or text in device.platform.name.lower():
            return device, f"matches {choice!r}"
    listing = "; ".join(f"{key} {describe(d)}" for key, d in devices)
    raise OpenCLUnavailableError(f"no OpenCL device matches {choice!r}. Devices: {listing}")


def select_device(choice: str | None = None):
    """Return the OpenCL device for ``choice`` (see the module docstring)."""
    return choose_device(choice)[0]


@functools.lru_cache(maxsize=None)
def context_for(device):
    """A context and in-order queue on ``device`` (one per device per process)."""
    cl = pyopencl_module()
    context = cl.Context([device])
    return context, cl.CommandQueue(context)


#: Seconds after which the lock file of octcl's program cache is taken to be a dead process's. pyopencl holds it
#: while it reads or writes one program's binary (milliseconds), and waits a minute for it before failing every
#: build; a process killed in that window (SIGKILL) leaves it behind.
STALE_LOCK_S = 20.0


def program_cache_dir() -> Path:
    """Where pyopencl keeps octcl's built programs (``cache_dir()/programs``), a stale lock in it removed."""
    folder = cache_dir() / "programs"
    folder.mkdir(parents=True, exist_ok=True)
    lock = folder / "lock"
    with contextlib.suppress(FileNotFoundError):  # another process may remove it first
        if time.time() - lock.stat().st_mtime > STALE_LOCK_S:
            logger.warning("removing %s, left %.0f s ago by a process that ended while holding it", lock,
                           time.time() - lock.stat().st_mtime)
            lock.unlink()
    return folder


def quiet_build(context, source: str, options: list[str], device, *, binary_cache: bool = True):
    """Build ``source`` for ``device``; its compiler log goes to the debug log instead of a CompilerWarning on stderr.

    A failed build raises pyopencl's error, which holds the whole log.
    ``binary_cache=False`` builds without pyopencl's binary cache and
    returns the bare program (the probe, whose program is thrown away):
    deciding whether to use that cache, pyopencl asks the device for an
    NVIDIA-only attribute (``CL_DEVICE_COMPUTE_CAPABILITY_MAJOR_NV``), which
    Oclgrind's API check reports as an error. The cache is octcl's own
    (:func:`program_cache_dir`), so that a lock a killed process left in it is
    cleared before the build: in pyopencl's default one it made every later
    build wait a minute and then fail (a batch test that kills a worker
    mid-scan left one).
    """
    cl = pyopencl_module()
    with warnings.catch_warnings(), _compiler_output_to_log():
        warnings.simplefilter("ignore", cl.CompilerWarning)
        if binary_cache:
            built = cl.Program(context, source).build(options=options, cache_dir=str(program_cache_dir()))
        else:
            built = cl._cl._Program(context, source)
            built.build(" ".join(options).encode(), [device])
    if logger.isEnabledFor(logging.DEBUG):
        log = built.get_build_info(device, cl.program_build_info.LOG).strip()
        if log:
            logger.debug("OpenCL build log on %s (options %s):\n%s", describe(device), " ".join(options), log)
    return built


@contextlib.contextmanager
def _compiler_output_to_log():
    """Send what a compiler writes straight to file descriptor 2 to the debug log instead of the terminal.

    Some OpenCL compilers print to the process's standard error themselves
    (Intel's and PoCL's "1 error generated.", Oclgrind's API reports), past
    pyopencl's build log; for the build's duration, descriptor 2 is a
    temporary file. A process without a usable descriptor 2 builds as is.
    """
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield
        return
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            text = sink.read().decode(errors="replace").strip()
            if text:
                logger.debug("OpenCL compiler output on standard error:\n%s", text)
