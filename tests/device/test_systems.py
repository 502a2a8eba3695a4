"""Windows, macOS and Linux: requirements per platform, OpenCL registration per system, no POSIX-only main path.

What can be run here runs for real: the package imported and the main
commands run with the platform faked as Windows. The fake is sound where
it touches octcl's own code: third-party packages are imported first under
the real platform (they are tested on Windows by their makers, and some
load Windows DLLs when told they are on Windows), then ``sys.platform`` is
``"win32"``, the POSIX-only modules cannot be imported and the POSIX-only
functions of ``os`` and ``signal`` are gone, and every octcl module is
imported anew. What cannot be faked (the Windows ICD loader, the registry,
psutil's Windows counters) is listed in docs/portability.md.
"""

from __future__ import annotations

import configparser
import json
import os
import platform
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from packaging.requirements import Requirement

from octcl.device import runtime as _runtime

from conftest import load_script

ROOT = Path(__file__).resolve().parents[2]


def check_platforms():
    return load_script("check_platforms")


def setup_cfg_requirements() -> list[str]:
    """setup.cfg's requirements as the wheel's ``Requires-Dist`` lines (extras as ``extra ==`` markers)."""
    config = configparser.ConfigParser()
    config.read(ROOT / "setup.cfg")
    lines = [line for line in config["options"]["install_requires"].splitlines() if line.strip()]
    for extra, block in config["options.extras_require"].items():
        for line in filter(str.strip, block.splitlines()):
            requirement = Requirement(line)
            marker = f"({requirement.marker}) and " if requirement.marker else ""
            requirement.marker = None
            lines.append(f'{requirement}; {marker}extra == "{extra}"')
    return lines


@pytest.mark.parametrize("python", ["3.10", "3.12", "3.13"])
def test_each_platform_gets_the_opencl_runtimes_that_have_wheels_for_it(python):
    platforms = check_platforms()
    names = {platform: {Requirement(str(r)).name for r in platforms.requirements_for(setup_cfg_requirements(),
                                                                                   platform, python)}
             for platform in platforms.PLATFORMS}
    assert {"numpy", "torch", "pyopencl", "psutil"} <= set.intersection(*names.values())
    assert "pocl-binary-distribution" in names["manylinux_2_28_x86_64"]
    assert {"intel-opencl-rt", "intel-cmplr-lib-rt"} <= names["manylinux_2_28_x86_64"]  # the extra "intel"
    assert {"intel-opencl-rt", "intel-cmplr-lib-rt"} <= names["win_amd64"]
    for system in ("win_amd64", "macosx_12_0_arm64", "macosx_14_0_arm64", "manylinux_2_28_aarch64"):
        assert "pocl-binary-distribution" not in names[system], system
    for system in ("macosx_12_0_arm64", "macosx_14_0_arm64", "manylinux_2_28_aarch64"):
        assert not names[system] & {"intel-opencl-rt", "intel-cmplr-lib-rt"}, system


def test_intels_runtime_is_a_default_on_windows_and_an_extra_on_linux():
    platforms = check_platforms()
    base = [line for line in setup_cfg_requirements() if "extra ==" not in line]
    linux = {r.name for r in platforms.requirements_for(base, "manylinux_2_28_x86_64", "3.12")}
    windows = {r.name for r in platforms.requirements_for(base, "win_amd64", "3.12")}
    assert "intel-opencl-rt" in windows and "intel-opencl-rt" not in linux
    torch = next(Requirement(line) for line in base if line.startswith("torch"))
    assert not any(spec.operator == "==" for spec in torch.specifier), "torch is a range, not one release"


def test_pip_tags_give_a_linux_system_every_manylinux_tag_it_accepts():
    tags = check_platforms().pip_tags("manylinux_2_28_x86_64")
    assert tags[0] == "manylinux_2_28_x86_64" and "manylinux_2_17_x86_64" in tags and tags[-1] == "manylinux2014_x86_64"
    assert check_platforms().pip_tags("win_amd64") == ["win_amd64"]


def test_windows_registers_intels_runtime_through_the_loaders_variable(tmp_path, monkeypatch):
    library = tmp_path / "Library" / "bin" / "intelocl64.dll"
    monkeypatch.setattr(_runtime.sys, "platform", "win32")
    monkeypatch.setattr(_runtime, "bundled_libraries", lambda: {"intel": library})
    monkeypatch.setenv("PATH", "C:\\Windows")
    monkeypatch.setenv(_runtime.ICD_FILENAMES_ENV, "C:\\mine\\vendor.dll")
    assert _runtime.register_runtimes() is None  # the user's own list is kept
    monkeypatch.delenv(_runtime.ICD_FILENAMES_ENV)
    assert _runtime.register_runtimes() == str(library)
    assert os.environ[_runtime.ICD_FILENAMES_ENV] == str(library)
    assert os.environ["PATH"].split(os.pathsep)[0] == str(library.parent)  # its own DLLs load from there
    monkeypatch.delenv(_runtime.ICD_FILENAMES_ENV)
    monkeypatch.setattr(_runtime, "bundled_libraries", lambda: {})
    assert _runtime.register_runtimes() is None and _runtime.ICD_FILENAMES_ENV not in os.environ


def test_macos_registers_nothing(monkeypatch):
    monkeypatch.setattr(_runtime.sys, "platform", "darwin")
    monkeypatch.delenv(_runtime.ICD_VENDORS_ENV, raising=False)
    monkeypatch.setattr(_runtime, "bundled_libraries", lambda: {"intel": Path("/nowhere/libintelocl.so")})
    assert _runtime.register_runtimes() is None and _runtime.ICD_VENDORS_ENV not in os.environ


@pytest.mark.parametrize("system, words", [("linux", ["octcl[intel]", "pocl-opencl-icd"]),
                                           ("win32", ["intel-opencl-rt", "GPU's driver"]),
                                           ("darwin", ["Apple's OpenCL"])])
def test_the_fix_named_in_errors_is_the_one_for_the_system(monkeypatch, system, words):
    monkeypatch.setattr(_runtime.sys, "platform", system)
    for texts in (_runtime._FIX, _runtime._NO_PLATFORM_HELP):
        text = _runtime._for_this_system(texts)
        assert any(word in text for word in words) and "\n" not in text


class _Device:
    """A device as Apple's GPU driver answers: no cl_khr_fp64, and an error for the double-config query."""

    extensions = "cl_khr_byte_addressable_store cl_khr_global_int32_base_atomics"

    @property
    def double_fp_config(self):
        raise _runtime.pyopencl_module().LogicError("clGetDeviceInfo failed: INVALID_VALUE")


def test_a_device_without_fp64_is_said_to_have_none_without_asking_its_config():
    assert _runtime.has_fp64(_Device()) is False
    device, _ = _runtime.choose_device()
    assert _runtime.has_fp64(device) == ("cl_khr_fp64" in device.extensions)


#: Run in a fresh interpreter: warm the third-party imports, fake Windows, import octcl anew, run commands.
FAKE_WINDOWS = textwrap.dedent('''
    import importlib, json, os, pkgutil, signal, sys
    import octcl, octcl.cli, octcl.host, octcl.host.batch
    names = sorted({m.name for package in (octcl, octcl.host, octcl.host.batch)
                    for m in pkgutil.walk_packages(package.__path__, package.__name__ + ".")})
    for name in names:  # every octcl module under the real platform: third-party imports warmed
        importlib.import_module(name)
    # Imported lazily by pyopencl's binary cache and by the batch's plots; each reads the system at import.
    import matplotlib.figure, platformdirs
    import psutil

    class WindowsMemory:  # psutil's Windows counters (peak_wset) do not exist on Linux
        peak_wset = 123 * 2**20

    psutil.Process.memory_info = lambda self: WindowsMemory()
    sys.platform = "win32"
    for module in ("resource", "fcntl", "termios", "pwd", "grp"):
        sys.modules[module] = None
    for name in ("sched_getaffinity", "fork", "forkpty", "uname", "getuid", "geteuid", "getgid", "setsid", "killpg",
                 "getpgid", "O_CLOEXEC", "O_NOFOLLOW", "mkfifo", "getloadavg"):
        if hasattr(os, name):
            delattr(os, name)
    for name in ("SIGKILL", "SIGALRM", "SIGHUP", "SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGPIPE", "setitimer",
                 "alarm", "ITIMER_REAL", "pause"):
        if hasattr(signal, name):
            delattr(signal, name)
    for name in [n for n in sys.modules if n == "octcl" or n.startswith("octcl.")]:
        del sys.modules[name]
    imported = [importlib.import_module(name).__name__ for name in names]
    from octcl.cli import main
    statuses = {}
    for command in json.loads(sys.argv[1]):
        statuses[command[0]] = main(command)
    from octcl.host.batch.worker import invert_scan  # a batch worker's work, outside Dask (its spawn is Dask's)
    with open(sys.argv[2], "rb") as target:
        scan = invert_scan("scan.png", target.read(), 5.0, 0, {})
    print("RESULT " + json.dumps({"imported": imported, "statuses": statuses, "worker": scan["worker"],
                                  "phantom_bytes": len(scan["phantom"])}))
''')


def test_the_package_and_its_main_commands_run_with_the_platform_faked_as_windows(tmp_path):
    _runtime.pyopencl_module()  # the parent's registered implementations, handed to the child: its loader is Linux's
    official = ROOT / "data" / "official"
    phantom, scan = tmp_path / "phantom.txt", tmp_path / "scan.png"
    commands = [
        ["phantom", "skin", "--seed", "3", "-o", str(phantom), "--quiet"],
        ["render", str(phantom), "-o", str(scan), "--quiet"],
        ["maps", str(scan), "-o", str(tmp_path / "maps"), "--quiet"],
        ["score", str(official / "Scan_Exp1_Uniform_A.png"), str(official / "Scan_Exp1_Uniform_B.png"), "--quiet"],
        ["devices", "--quiet"],
        # A budget the scanner-written scan never needs (it ends at its ceiling in about 3 s), so that the summary
        # has its score on a loaded machine too (a 5 s budget left it out when other processes held the cores).
        ["invert", str(scan), "-o", str(tmp_path / "inverted.txt"), "--time-budget", "30", "--json", "--quiet"],
    ]
    environment = {**os.environ, "PYTHONUNBUFFERED": "1"}
    result = subprocess.run([sys.executable, "-c", FAKE_WINDOWS, json.dumps(commands), str(scan)],
                            capture_output=True, text=True, env=environment, timeout=300, cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    outcome = json.loads(next(line for line in result.stdout.splitlines() if line.startswith("RESULT "))[7:])
    assert {"octcl.host.pipeline.invert", "octcl.host.batch.runner", "octcl.cli", "octcl.device.runtime"} <= set(outcome["imported"])
    assert outcome["statuses"] == {"phantom": 0, "render": 0, "maps": 0, "score": 0, "devices": 0, "invert": 0}
    assert outcome["worker"].rsplit(":", 1)[0] == platform.node() and outcome["phantom_bytes"] > 0
    invert = json.loads(result.stdout[result.stdout.index("{"):result.stdout.index("RESULT ")])
    assert invert["peak_memory_mib"] == 123 and invert["score"] > 0.99
    assert (tmp_path / "inverted.txt").stat().st_size > 0 and (tmp_path / "maps" / "scan_OAC.png").is_file()
