"""OpenCL runtime: registered implementations, the probing device choice, quiet builds.

The rule under test is "a device is a candidate only if it builds", on any
machine: one where every implementation builds, and one where PyPI's PoCL
cannot (AMD Zen 5, whose CPU LLVM 14 does not know). Two failures are made
on any machine:

- a compiler that rejects the source: a define that turns the probe
  program's source into a syntax error goes through the real build, and the
  real compiler rejects it with its own message;
- PoCL on Zen 5: the build of every PoCL device raises pyopencl's own error
  carrying the log PoCL 3.0 gives there (:data:`POCL_ZEN5_LOG`).
"""

import logging
import subprocess
import sys
import uuid
import warnings

import pytest

from octcl.device import runtime as _runtime
from octcl.device.programs import build
from octcl.device.runtime import OpenCLUnavailableError, choose_device, context_for, implementation, list_devices, probe
from octcl.cli import main

#: What PoCL 3.0 (PyPI's pocl-binary-distribution, LLVM 14) logs for any build on an AMD Zen 5 CPU: LLVM 14
#: names the host CPU "generic", which its x86 back end does not take as a target.
POCL_ZEN5_LOG = ("error: unknown target CPU 'generic'\n"
                 "note: valid target CPU values are: nocona, core2, penryn, bonnell, atom, silvermont, slm, "
                 "goldmont, goldmont-plus, tremont, nehalem, corei7, westmere, sandybridge, corei7-avx, "
                 "ivybridge, core-avx-i, haswell, core-avx2, broadwell, skylake, skylake-avx512, skx, "
                 "cascadelake, cooperlake, cannonlake, icelake-client, rocketlake, icelake-server, tigerlake, "
                 "sapphirerapids, alderlake, knl, knm, k8, athlon64, athlon-fx, opteron, k8-sse3, athlon64-sse3, "
                 "opteron-sse3, amdfam10, barcelona, btver1, btver2, bdver1, bdver2, bdver3, bdver4, znver1, "
                 "znver2, znver3, x86-64, x86-64-v2, x86-64-v3, x86-64-v4")


@pytest.fixture
def fresh_probes(tmp_path, monkeypatch):
    """An empty probe cache, on disk and in memory, for one test."""
    monkeypatch.setenv(_runtime.CACHE_ENV, str(tmp_path / "cache"))
    _runtime._probe_in_process.cache_clear()
    yield tmp_path / "cache"
    _runtime._probe_in_process.cache_clear()


def forget_probes():
    """Clear the probe cache, in memory and on disk, so that the next probes ask the (changed) builds."""
    _runtime._probe_in_process.cache_clear()
    for path in (_runtime.cache_dir() / "probes").glob("*.json"):
        path.unlink()


def break_builds_of(monkeypatch, broken: set[str]):
    """Builds on devices of the implementations in ``broken`` fail in their compiler: the probe
    program's ``octcl_probe_data`` is defined as ``)``, a syntax error there."""
    real_build = _runtime.quiet_build

    def build_breaking(context, source, options, device, **kwargs):
        if implementation(device) in broken:
            options = [*options, "-Doctcl_probe_data=)"]
        return real_build(context, source, options, device, **kwargs)

    monkeypatch.setattr(_runtime, "quiet_build", build_breaking)
    forget_probes()


def pocl_as_on_zen5(monkeypatch):
    """Every PoCL build fails as PyPI's PoCL 3.0 fails on an AMD Zen 5 CPU (:data:`POCL_ZEN5_LOG`)."""
    real_build = _runtime.quiet_build
    cl = _runtime.pyopencl_module()

    def build_as_on_zen5(context, source, options, device, **kwargs):
        if implementation(device) == "pocl":
            log = (f"clBuildProgram failed: BUILD_PROGRAM_FAILURE\n\nBuild on {device!r}:\n\n{POCL_ZEN5_LOG}\n"
                   f"(options: {' '.join(options)})")
            raise cl.RuntimeError(cl._cl._ErrorRecord("clBuildProgram", cl.status_code.BUILD_PROGRAM_FAILURE, log))
        return real_build(context, source, options, device, **kwargs)

    monkeypatch.setattr(_runtime, "quiet_build", build_as_on_zen5)
    forget_probes()


def ranked_keys(wanted=None):
    return [key for key, _, _ in _runtime._ranked(list_devices(), wanted)]


def expected_choice():
    """The device the rule picks, by asking each device's probe in octcl's order; None if none builds."""
    devices = dict(list_devices())
    return next((devices[key] for key in ranked_keys() if probe(devices[key]).builds), None)


def assert_no_device_builds_error(message: str):
    """The error when no device builds: one line, each candidate named with its compiler's error, the fix."""
    assert "\n" not in message and message.startswith("no OpenCL device can build octcl's kernels")
    assert "octcl[intel]" in message and "pocl-opencl-icd" in message
    for key in ranked_keys():
        assert f"{key} " in message


def test_every_device_builds_or_says_why_in_one_line_and_the_chosen_one_builds(fresh_probes):
    devices = list_devices()
    assert devices
    for key, device in devices:
        result = probe(device)
        assert result.builds or (result.error and "\n" not in result.error), (key, result)
    device, reason = choose_device()
    assert probe(device).builds and device == expected_choice() and reason
    assert implementation(device) not in _runtime.SIMULATORS
    assert list(fresh_probes.glob("probes/*.json")), "probe results are remembered on disk"


def test_a_device_whose_builds_fail_is_passed_over(fresh_probes, monkeypatch):
    """The preferred implementation's compiler fails: the next device that builds is chosen, or, where
    none builds, the one-line error."""
    first = expected_choice()
    break_builds_of(monkeypatch, {implementation(first)})
    result = probe(first)
    assert not result.builds and "error" in result.error.lower() and "\n" not in result.error
    following = expected_choice()
    if following is None:
        with pytest.raises(OpenCLUnavailableError) as raised:
            choose_device()
        assert_no_device_builds_error(str(raised.value))
    else:
        assert implementation(following) != implementation(first)
        device, reason = choose_device()
        assert device == following and reason


@pytest.mark.parametrize("also_broken", [(), ("intel",)], ids=["zen5", "zen5_without_intel"])
def test_pocl_failing_as_on_zen5_passes_the_choice_on(fresh_probes, monkeypatch, capfd, also_broken):
    """PoCL's real Zen 5 error: another device that builds is chosen and ``octcl devices`` names PoCL's error;
    where none is left, one line names every device and its error."""
    pocl_as_on_zen5(monkeypatch)
    break_builds_of(monkeypatch, set(also_broken))
    pocl = [(key, device) for key, device in list_devices() if implementation(device) == "pocl"]
    for _, device in pocl:
        assert probe(device).error == "error: unknown target CPU 'generic'"
    following = expected_choice()
    if following is None:
        with pytest.raises(OpenCLUnavailableError) as raised:
            choose_device()
        assert_no_device_builds_error(str(raised.value))
        assert "unknown target CPU 'generic'" in str(raised.value)
        assert main(["devices"]) == 2
    else:
        assert implementation(following) != "pocl" and choose_device()[0] == following
        assert main(["devices"]) == 0
    listing = capfd.readouterr().out
    for key, _ in pocl:
        assert f"{key} " in listing and "does not build (error: unknown target CPU 'generic')" in listing


def test_no_device_builds_is_one_line_naming_devices_error_and_fix(fresh_probes, monkeypatch, capfd, tmp_path):
    break_builds_of(monkeypatch, {implementation(device) for _, device in list_devices()} - set(_runtime.SIMULATORS))
    with pytest.raises(OpenCLUnavailableError) as raised:
        choose_device()
    message = str(raised.value)
    assert_no_device_builds_error(message)
    assert "expected" in message.lower()  # the compiler's own words about the broken source

    phantom = tmp_path / "one.txt"
    phantom.write_text("0 0 100 1\n")
    status = main(["render", str(phantom), "-o", str(tmp_path / "one.png")])
    errors = [line for line in capfd.readouterr().err.splitlines() if "error" in line]
    assert status == 2 and len(errors) == 1 and errors[0].startswith("octcl render: error: no OpenCL device can build")
    status = main(["devices"])
    captured = capfd.readouterr()
    assert status == 2 and "does not build" in captured.out and "octcl[intel]" in captured.err


def test_probe_results_are_remembered_per_device(fresh_probes, monkeypatch):
    _, device = list_devices()[0]
    assert probe(device).builds
    _runtime._probe_in_process.cache_clear()

    def no_compiler(*_, **__):
        raise AssertionError("the compiler was asked again")

    monkeypatch.setattr(_runtime, "quiet_build", no_compiler)
    assert probe(device).builds
    # Another driver version is another key, so an updated driver is probed anew.
    assert _runtime._probe_key(device) != _runtime._probe_key(_Renamed(device, driver_version="0.0"))


class _Renamed:
    """A device seen with other attributes (for the probe's cache key)."""

    def __init__(self, device, **changes):
        self._device, self._changes = device, changes

    def __getattr__(self, name):
        return self._changes.get(name, getattr(self._device, name))


def test_named_devices_and_types(fresh_probes):
    for key, device in list_devices():
        assert choose_device(key)[0] == device
        assert implementation(choose_device(implementation(device))[0]) == implementation(device)
    # Each type asked for is that type, where the machine has one (a GPU machine may have no CPU runtime).
    device_type = _runtime.pyopencl_module().device_type
    for wanted in ("cpu", "gpu"):
        kind = getattr(device_type, wanted.upper())
        if any(device.type & kind and implementation(device) not in _runtime.SIMULATORS for _, device in list_devices()):
            assert choose_device(wanted)[0].type & kind
    with pytest.raises(OpenCLUnavailableError, match="no OpenCL device matches 'no-such-device'"):
        choose_device("no-such-device")


def test_successful_builds_print_nothing_and_log_under_debug(caplog):
    device, _ = choose_device()
    cl = _runtime.pyopencl_module()
    context, _ = context_for(device)
    # A source not built before, so that pyopencl's binary cache cannot skip the compiler and its log.
    source = (f"#warning octcl test remark {uuid.uuid4().hex}\n"
              "__kernel void k(__global int *x) { x[0] = 1; }")
    with warnings.catch_warnings(record=True) as caught, caplog.at_level(logging.DEBUG, logger="octcl"):
        warnings.simplefilter("always")
        _runtime.quiet_build(context, source, [], device)
    assert not [w for w in caught if issubclass(w.category, cl.CompilerWarning)]
    assert "octcl test remark" in caplog.text


def test_a_lock_a_killed_process_left_in_the_program_cache_does_not_stop_builds(tmp_path, monkeypatch, caplog):
    """A lock older than STALE_LOCK_S (pyopencl holds it for one binary's read or write) is removed before the
    build, which then takes seconds, not pyopencl's minute and failure; a fresh lock (another process building
    now) is left alone."""
    import os
    import time

    monkeypatch.setenv("OCTCL_CACHE_DIR", str(tmp_path))
    lock = tmp_path / "programs" / "lock"
    lock.parent.mkdir(parents=True)
    lock.touch()
    assert _runtime.program_cache_dir() == lock.parent and lock.exists()  # fresh: kept
    old = time.time() - 2 * _runtime.STALE_LOCK_S
    os.utime(lock, (old, old))
    device, _ = choose_device()
    context, _ = context_for(device)
    started = time.monotonic()
    with caplog.at_level(logging.WARNING, logger="octcl"):
        _runtime.quiet_build(context, f"__kernel void k{uuid.uuid4().hex}(__global int *x) {{ x[0] = 2; }}", [],
                             device)
    assert time.monotonic() - started < 30 and not lock.exists()
    assert "removing" in caplog.text and str(lock) in caplog.text


def test_failed_builds_keep_the_compiler_log():
    device, _ = choose_device()
    context, _ = context_for(device)
    with pytest.raises(OpenCLUnavailableError) as raised:
        build(context, "depth_order", (("int", ")"),), False)
    message = str(raised.value)
    assert message.startswith("kernels/depth_order.cl failed to build on") and "error" in message.lower()
    assert message.count("\n") > 3  # the whole log, not its first line


def test_runtimes_are_registered_beside_the_systems(fresh_probes, tmp_path, monkeypatch):
    system = tmp_path / "vendors"
    system.mkdir()
    (system / "vendor.icd").write_text("libvendor-opencl.so.1\n")
    library = tmp_path / "libintelocl.so"
    library.touch()
    monkeypatch.setattr(_runtime, "SYSTEM_VENDORS", system)
    monkeypatch.setattr(_runtime, "bundled_libraries", lambda: {"intel": library})
    monkeypatch.setenv(_runtime.ICD_VENDORS_ENV, "/user/choice")
    assert _runtime.register_runtimes() is None  # the user's own folder is kept
    monkeypatch.delenv(_runtime.ICD_VENDORS_ENV)
    folder = _runtime.register_runtimes()
    assert folder.parent == fresh_probes / "icd" and str(folder) == _runtime.os.environ[_runtime.ICD_VENDORS_ENV]
    assert (folder / "octcl-intel.icd").read_text() == f"{library}\n"
    assert (folder / "vendor.icd").read_text() == "libvendor-opencl.so.1\n"
    monkeypatch.delenv(_runtime.ICD_VENDORS_ENV)
    assert _runtime.register_runtimes() == folder  # the same contents, the same folder


def test_intels_runtime_is_found_with_nothing_exported(tmp_path):
    """A fresh process with no OCL_ICD_VENDORS lists Intel's CPU runtime where it is installed."""
    if "intel" not in _runtime.bundled_libraries():
        pytest.skip("intel-opencl-rt is not installed: pip install 'octcl[intel]'")
    # As a user's shell would start it: without the loader's variable or the suite's Oclgrind checks.
    env = {key: value for key, value in _runtime.os.environ.items()
           if key != _runtime.ICD_VENDORS_ENV and not key.startswith("OCLGRIND_")}
    env[_runtime.CACHE_ENV] = str(tmp_path)
    result = subprocess.run([sys.executable, "-m", "octcl.cli", "devices"], capture_output=True, text=True,
                            env=env, timeout=120)
    assert result.returncode == 0 and result.stderr == ""
    assert "intel: Intel(R) OpenCL" in result.stdout and "pocl:" in result.stdout


def test_listing_devices_leaves_no_oclgrind_report(tmp_path):
    """``octcl devices`` probes every device, Oclgrind too, under Oclgrind's API check (tests/conftest.py sets
    it): octcl asks each device only what it supports, so standard error stays empty."""
    if not any(implementation(device) == "oclgrind" for _, device in list_devices()):
        pytest.skip("Oclgrind is not installed: apt-get install oclgrind")
    env = {**_runtime.os.environ, _runtime.CACHE_ENV: str(tmp_path)}  # a fresh probe cache: every probe builds
    result = subprocess.run([sys.executable, "-m", "octcl.cli", "devices"], capture_output=True, text=True,
                            env=env, timeout=120)
    assert result.returncode == 0 and "oclgrind:" in result.stdout and "builds" in result.stdout
    assert result.stderr == ""


def test_a_gpu_driver_library_without_an_icd_file_is_registered(fresh_probes, tmp_path, monkeypatch):
    """A GPU driver's OpenCL library on disk that no ICD file names (NVIDIA's in a container that mounts the
    driver: ``/usr/local/nvidia/lib64/libnvidia-opencl.so.1`` and only PoCL in ``/etc/OpenCL/vendors``) gets
    an ICD of octcl's; one that an ICD file names, by path or by name, is left to the system's."""
    if sys.platform != "linux":
        pytest.skip("the ICD vendor folder is Linux's loader's")
    driver = tmp_path / "nvidia" / "lib64"
    driver.mkdir(parents=True)
    library = driver / "libnvidia-opencl.so.1"
    library.touch()
    system = tmp_path / "vendors"
    system.mkdir()
    (system / "pocl.icd").write_text("libpocl.so.2\n")
    monkeypatch.setattr(_runtime, "SYSTEM_VENDORS", system)
    monkeypatch.setattr(_runtime, "DRIVER_FOLDERS", (tmp_path / "elsewhere", driver))
    monkeypatch.setattr(_runtime, "bundled_libraries", lambda: {})
    monkeypatch.delenv("LD_LIBRARY_PATH", raising=False)
    monkeypatch.delenv(_runtime.ICD_VENDORS_ENV, raising=False)
    assert _runtime.gpu_driver_libraries() == {"nvidia": library}
    folder = _runtime.register_runtimes()
    assert (folder / "octcl-nvidia.icd").read_text() == f"{library}\n"
    assert (folder / "pocl.icd").read_text() == "libpocl.so.2\n"
    # Found on LD_LIBRARY_PATH first, as the loader would.
    first = tmp_path / "first"
    first.mkdir()
    (first / "libnvidia-opencl.so.1").touch()
    monkeypatch.setenv("LD_LIBRARY_PATH", f"{first}{_runtime.os.pathsep}{driver}")
    assert _runtime.gpu_driver_libraries() == {"nvidia": first / "libnvidia-opencl.so.1"}
    for named in ("libnvidia-opencl.so.1\n", f"{library}\n"):
        (system / "nvidia.icd").write_text(named)
        assert _runtime.gpu_driver_libraries() == {}
    monkeypatch.delenv(_runtime.ICD_VENDORS_ENV)
    monkeypatch.delenv("LD_LIBRARY_PATH")
    assert _runtime.register_runtimes() is None  # nothing of octcl's to add: the system's loader as it is
