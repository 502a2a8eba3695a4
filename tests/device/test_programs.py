"""octcl's OpenCL programs (octcl/device/programs.py): each is kernels/prelude.cl, ``#line 1``, then its kernel file.

The prelude alone defines what the files share (the real types, cmul, cconj_mul, group_sum); the
files define none of the constants their host passes as -D defines; every program builds on the
CPU implementations with its op's own defines; and a compiler's message names a line of the
kernel file, not of the prelude before it.
"""

import re
import threading
import time
from pathlib import Path

import pytest
from conftest import implementation_device

from octcl.config import DEFAULT_CONFIG
from octcl.device import depth_order, programs, runtime
from octcl.device.runtime import OpenCLUnavailableError, context_for
from octcl.device.scanner import KernelSettings
from octcl.device.scanner import program_defines as scanner_defines
from octcl.host.optim import lbfgs_device
from octcl.host.stage1 import display_device, levels_device, operator_device
from octcl.host.stage1.operator import lateral_taps

KERNELS = Path(__file__).resolve().parents[2] / "kernels"
#: The field operator's lateral reach R at the default scanner, as FieldKernels takes it.
REACH = lateral_taps(DEFAULT_CONFIG).size // 2
#: Each program's defines as its op makes them, at the default scanner, by precision (float64 or not).
PROGRAM_DEFINES = {
    "scanner": lambda double: scanner_defines(DEFAULT_CONFIG, KernelSettings(double=double)),
    "depth_order": lambda double: depth_order.program_defines(),
    "field_operator": lambda double: operator_device.program_defines(DEFAULT_CONFIG, REACH),
    "display_loss": lambda double: display_device.program_defines(DEFAULT_CONFIG, 0.1),
    "adam": lambda double: display_device.program_defines(DEFAULT_CONFIG, 0.1),
    "level_fit": lambda double: levels_device.program_defines(),
    "lbfgs": lambda double: lbfgs_device.program_defines(),
}
#: Programs without floating point, built once (float32 options).
INTEGER_PROGRAMS = {"depth_order"}
#: What only the prelude may define.
SHARED = {"real": r"^\s*typedef\s+\w+\s+real\s*;",
          **{name: rf"^\s*(?:static\s+|inline\s+)*(?!return\b)\w+\s+{name}\s*\(" for name in
             ("cmul", "cconj_mul", "group_sum")}}


def kernel_files() -> list[str]:
    return sorted(path.stem for path in KERNELS.glob("*.cl"))


def without_comments(source: str) -> str:
    return re.sub(r"//[^\n]*", "", re.sub(r"/\*.*?\*/", "", source, flags=re.S))


def header(source: str) -> str:
    """A kernel file's opening comment."""
    return re.match(r"\s*/\*.*?\*/", source, flags=re.S).group(0)


def test_every_kernel_file_but_the_prelude_is_a_program_here():
    assert set(PROGRAM_DEFINES) == set(kernel_files()) - {programs.PRELUDE}


@pytest.mark.parametrize("name", kernel_files())
def test_only_the_prelude_defines_the_shared_types_and_helpers(name):
    code = without_comments(programs.kernel_file(name))
    defined = {shared for shared, pattern in SHARED.items() if re.search(pattern, code, flags=re.M)}
    assert defined == (set(SHARED) if name == programs.PRELUDE else set())


def test_the_preludes_functions_are_static_inline():
    """So that a program that calls none of them compiles none of them."""
    code = without_comments(programs.kernel_file(programs.PRELUDE))
    definitions = re.findall(r"^([^\s#{}][^;{}]*?)\b(\w+)\s*\([^;{}]*\)\s*\{", code, flags=re.M)
    assert {function for _, function in definitions} == {"cmul", "cconj_mul", "group_sum"}
    assert all(qualifiers.startswith("static inline ") for qualifiers, _ in definitions), definitions


@pytest.mark.parametrize("name", sorted(PROGRAM_DEFINES))
def test_a_kernel_file_defines_none_of_its_hosts_constants_and_its_header_names_those_it_uses(name):
    source = programs.kernel_file(name)
    code = without_comments(source)
    for double in (False, True):
        for key, _ in PROGRAM_DEFINES[name](double):
            assert not re.search(rf"^\s*#\s*define\s+{key}\b", code, flags=re.M), f"{name}.cl defines {key}"
            if re.search(rf"\b{key}\b", code):
                assert re.search(rf"\b{key}\b", header(source)), f"{name}.cl's header does not list {key}"


@pytest.mark.parametrize("name", sorted(PROGRAM_DEFINES))
def test_the_source_is_the_prelude_then_the_file_from_its_line_1(name):
    prelude, source = programs.kernel_file(programs.PRELUDE), programs.kernel_source(name)
    assert source.startswith(prelude)
    assert source[len(prelude):] == "\n#line 1\n" + programs.kernel_file(name)


@pytest.mark.parametrize("double", [False, True], ids=["float32", "float64"])
@pytest.mark.parametrize("implementation", ["pocl", "intel"])
def test_every_program_builds_with_its_ops_defines(implementation, double):
    context, _ = context_for(implementation_device(implementation))
    for name, defines in PROGRAM_DEFINES.items():
        if not (double and name in INTEGER_PROGRAMS):
            assert programs.build(context, name, defines(double), double) is not None, name


#: A kernel file with an error on its line 4, column 12.
BROKEN = "/* line 1 */\n\n__kernel void broken(__global real *x) {\n    x[0] = undefined_name;\n}\n"


@pytest.mark.parametrize("implementation", ["pocl", "intel"])
def test_a_build_error_names_the_line_of_the_kernel_file(implementation, monkeypatch):
    """Built as every program is (the prelude before it), the error is reported at 4:12, not ~50 lines later."""
    file_text = programs.kernel_file
    monkeypatch.setattr(programs, "kernel_file",
                        lambda name, directory=None: BROKEN if name == "broken" else file_text(name, directory))
    context, _ = context_for(implementation_device(implementation))
    with pytest.raises(OpenCLUnavailableError) as error:
        programs.build(context, "broken", (), False)
    assert re.search(r"\b4:12: (error: )?use of undeclared identifier 'undefined_name'", str(error.value)), \
        str(error.value)


def test_builds_from_threads_run_one_at_a_time_and_once_per_program(monkeypatch):
    """A run builds stage 3's scanner on a thread while stage 1 builds its programs: one compile at a time (Intel's
    CPU runtime ended the process when two ran at once), and a program two threads ask for is compiled once."""
    running, most, compiled, lock = [0], [0], [], threading.Lock()

    def slow_build(context, source, options, device):
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        time.sleep(0.05)
        with lock:
            running[0] -= 1
            compiled.append(source)
        return object()

    monkeypatch.setattr(runtime, "quiet_build", slow_build)

    class Context:
        devices = [None]

    context, built = Context(), {}
    names = ["scanner", "scanner", "display_loss", "level_fit"]

    def ask(index):
        built[index] = programs.build(context, names[index], (), False)

    threads = [threading.Thread(target=ask, args=(index,)) for index in range(len(names))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert most[0] == 1 and len(compiled) == 3
    assert built[0] is built[1] and built[0] is not built[2]
