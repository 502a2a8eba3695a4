"""OpenCL runtime: registered implementations, the probing device choice, quiet builds.

A device whose compiler fails is simulated on any machine by breaking the
build of that device's implementation: a define that turns the probe
program's source into a syntax error goes through the real build, and the
real compiler rejects it with its own message.
"""

import logging
import subprocess
import sys
import uuid
import warnings

import pytest

from octcl import _runtime
from octcl._runtime import (OpenCLUnavailableError, build, choose_device, context_for, implementation,
                            list_devices, probe)
from octcl.cli import main


@pytest.fixture
def fresh_probes(tmp_path, monkeypatch):
    """An empty probe cache, on disk and in memory, for one test."""
    monkeypatch.setenv(_runtime.CACHE_ENV, str(tmp_path / "cache"))
    _runtime._probe_in_process.cache_clear()
    yield tmp_path / "cache"
    _runtime._probe_in_process.cache_clear()


def break_builds_of(monkeypatch, broken: set[str]):
    """Builds on devices of the implementations in ``broken`` fail in their compiler: the probe
    program's ``octcl_probe_data`` is defined as ``)``, a syntax error there."""
    real_build = _runtime._quiet_build

    def build_breaking(program, options, device):
        if implementation(device) in broken:
            options = [*options, "-Doctcl_probe_data=)"]
        return real_build(program, options, device)

    monkeypatch.setattr(_runtime, "_quiet_build", build_breaking)


def ranked_keys(wanted=None):
    return [key for key, _, _ in _runtime._ranked(list_devices(), wanted)]


def test_every_device_here_builds_the_probe_and_one_is_chosen(fresh_probes):
    devices = list_devices()
    assert devices and all(probe(device).builds for _, device in devices)
    device, reason = choose_device()
    assert implementation(device) not in _runtime.SIMULATORS and reason
    assert list(fresh_probes.glob("probes/*.json")), "probe results are remembered on disk"


def test_a_device_whose_builds_fail_is_passed_over(fresh_probes, monkeypatch):
    """The preferred implementation's compiler fails: the next device that builds is chosen."""
    first = dict(list_devices())[ranked_keys()[0]]
    break_builds_of(monkeypatch, {implementation(first)})
    result = probe(first)
    assert not result.builds and "error" in result.error.lower() and "\n" not in result.error
    others = [key for key in ranked_keys() if implementation(dict(list_devices())[key]) != implementation(first)]
    if not others:
        pytest.skip(f"only {implementation(first)} is installed: nothing to fall back on "
                    "(pip install 'octcl[intel]')")
    device, reason = choose_device()
    assert dict(list_devices())[others[0]] == device and reason


def test_no_device_builds_is_one_line_naming_devices_error_and_fix(fresh_probes, monkeypatch, capsys, tmp_path):
    break_builds_of(monkeypatch, {implementation(device) for _, device in list_devices()})
    with pytest.raises(OpenCLUnavailableError) as raised:
        choose_device()
    message = str(raised.value)
    assert "\n" not in message and "octcl[intel]" in message
    for key in ranked_keys():
        assert f"{key} " in message
    assert "expected" in message.lower()  # the compiler's own words about the broken source

    phantom = tmp_path / "one.txt"
    phantom.write_text("0 0 100 1\n")
    status = main(["render", str(phantom), "-o", str(tmp_path / "one.png")])
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert status == 2 and len(errors) == 1 and errors[0].startswith("octcl render: error: no OpenCL device can build")
    status = main(["devices"])
    captured = capsys.readouterr()
    assert status == 2 and "does not build" in captured.out and "octcl[intel]" in captured.err


def test_probe_results_are_remembered_per_device(fresh_probes, monkeypatch):
    _, device = list_devices()[0]
    assert probe(device).builds
    _runtime._probe_in_process.cache_clear()

    def no_compiler(*_):
        raise AssertionError("the compiler was asked again")

    monkeypatch.setattr(_runtime, "_quiet_build", no_compiler)
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
    assert choose_device("cpu")[0].type & _runtime._cl().device_type.CPU
    with pytest.raises(OpenCLUnavailableError, match="no OpenCL device matches 'no-such-device'"):
        choose_device("no-such-device")


def test_successful_builds_print_nothing_and_log_under_debug(caplog):
    device, _ = choose_device()
    cl = _runtime._cl()
    context, _ = context_for(device)
    # A source not built before, so that pyopencl's binary cache cannot skip the compiler and its log.
    source = (f"#warning octcl test remark {uuid.uuid4().hex}\n"
              "__kernel void k(__global int *x) { x[0] = 1; }")
    with warnings.catch_warnings(record=True) as caught, caplog.at_level(logging.DEBUG, logger="octcl"):
        warnings.simplefilter("always")
        _runtime._quiet_build(cl.Program(context, source), [], device)
    assert not [w for w in caught if issubclass(w.category, cl.CompilerWarning)]
    assert "octcl test remark" in caplog.text


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
