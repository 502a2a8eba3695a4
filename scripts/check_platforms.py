#!/usr/bin/env python3
"""Check that octcl's wheel resolves on every platform it supports.

Builds octcl's wheel, reads its requirements (``Requires-Dist``, the
extra ``intel`` included), evaluates their environment markers for each
platform and Python version below, and asks pip to resolve the ones that
apply there as binary wheels for that platform::

    pip install --dry-run --no-deps --only-binary :all: --platform TAG --python-version X.Y ...

``--no-deps`` checks octcl's direct requirements one by one: the registry
reachable from CI serves no CUDA wheels, so torch's own Linux requirements
(the nvidia-* packages) cannot be resolved from it. pip downloads each
wheel it chooses (about 3 GB in all, dominated by torch) into a temporary
folder that is removed afterwards.

Prints one line per platform and Python version with the wheel chosen for
each requirement, and exits 1 if any requirement finds no wheel (naming
it), 2 on a usage or build error.

Usage::

    python scripts/check_platforms.py                  # every platform, Python 3.12 and 3.13
    python scripts/check_platforms.py --python 3.12 --platform win_amd64
    python scripts/check_platforms.py --markers-only   # no network: which requirements apply where
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]

#: Platforms octcl supports: pip's --platform tag and the marker variables of that system (pip takes a tag
#: as "this version or older"). Intel Macs are out: PyTorch publishes no wheel for them after 2.2. On Apple
#: silicon, macOS 12 is the oldest SciPy has wheels for (none is tagged macosx_11_0_arm64, so no octcl
#: release can install on macOS 11 without compiling SciPy); torch's newest wheels need macOS 14, and
#: macOS 12 and 13 get torch 2.11, inside octcl's range.
PLATFORMS = {
    "win_amd64": {"platform_system": "Windows", "platform_machine": "AMD64", "sys_platform": "win32",
                  "os_name": "nt"},
    "macosx_12_0_arm64": {"platform_system": "Darwin", "platform_machine": "arm64", "sys_platform": "darwin",
                          "os_name": "posix"},
    "macosx_14_0_arm64": {"platform_system": "Darwin", "platform_machine": "arm64", "sys_platform": "darwin",
                          "os_name": "posix"},
    "manylinux_2_28_x86_64": {"platform_system": "Linux", "platform_machine": "x86_64", "sys_platform": "linux",
                              "os_name": "posix"},
    "manylinux_2_28_aarch64": {"platform_system": "Linux", "platform_machine": "aarch64", "sys_platform": "linux",
                               "os_name": "posix"},
}
PYTHONS = ("3.12", "3.13")


def pip_tags(platform: str) -> list[str]:
    """pip's --platform tags of a system: pip expands a macOS tag to older versions but matches a
    manylinux tag exactly, so a glibc 2.28 system is given every manylinux tag it accepts."""
    if not platform.startswith("manylinux_2_"):
        return [platform]
    glibc_minor, machine = platform.removeprefix("manylinux_2_").split("_", 1)
    return [f"manylinux_2_{minor}_{machine}" for minor in range(int(glibc_minor), 16, -1)] \
        + [f"manylinux2014_{machine}"]
#: The extras a user of each platform installs beside the base requirements.
EXTRAS = ("", "intel", "test")


def marker_environment(platform: str, python: str, extra: str = "") -> dict[str, str]:
    """The PEP 508 marker variables of CPython ``python`` on ``platform`` (a key of :data:`PLATFORMS`)."""
    return {**PLATFORMS[platform], "python_version": python, "python_full_version": f"{python}.0",
            "implementation_name": "cpython", "platform_python_implementation": "CPython",
            "implementation_version": f"{python}.0", "platform_release": "", "platform_version": "",
            "extra": extra}


def requirements_for(requires_dist: list[str], platform: str, python: str) -> list[Requirement]:
    """The requirements (base and :data:`EXTRAS`) whose markers hold for ``python`` on ``platform``, once each."""
    chosen: dict[str, Requirement] = {}
    for line in requires_dist:
        requirement = Requirement(line)
        if any(requirement.marker is None or requirement.marker.evaluate(marker_environment(platform, python, extra))
               for extra in EXTRAS):
            requirement.marker = None
            chosen.setdefault(str(requirement), requirement)
    return list(chosen.values())


def wheel_requirements(folder: Path) -> list[str]:
    """Build octcl's wheel into ``folder`` and return its ``Requires-Dist`` lines."""
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--wheel-dir", str(folder),
                    str(ROOT)], check=True)
    wheel = next(folder.glob("octcl-*.whl"))
    with zipfile.ZipFile(wheel) as archive:
        metadata = next(name for name in archive.namelist() if name.endswith(".dist-info/METADATA"))
        lines = archive.read(metadata).decode().splitlines()
    return [line.split(":", 1)[1].strip() for line in lines if line.startswith("Requires-Dist:")]


def resolve(requirements: list[Requirement], platform: str, python: str, scratch: Path) -> dict[str, str]:
    """{requirement: wheel file pip chooses for it}, or {requirement: "NO WHEEL: pip's error"}."""
    def pip(names: list[str]) -> tuple[dict | None, str]:
        """pip's choice for ``names``: (its ``--report``, or None where it found no wheel; its standard error)."""
        report = scratch / "report.json"
        command = [sys.executable, "-m", "pip", "install", "--dry-run", "--ignore-installed", "--no-deps",
                   "--only-binary", ":all:", *[f"--platform={tag}" for tag in pip_tags(platform)],
                   "--python-version", python,
                   "--implementation", "cp", "--target", str(scratch / "target"), "--no-cache-dir",
                   "--disable-pip-version-check", "--quiet", "--report", str(report), *names]
        result = subprocess.run(command, capture_output=True, text=True)
        return (json.loads(report.read_text()) if result.returncode == 0 else None), result.stderr

    def wheel_file(item: dict) -> str:
        return item["download_info"]["url"].rsplit("/", 1)[-1]

    names = [str(requirement) for requirement in requirements]
    report, _ = pip(names)
    if report is not None:
        chosen = {item["metadata"]["name"].lower().replace("_", "-"): wheel_file(item) for item in report["install"]}
        return {name: chosen.get(Requirement(name).name.lower().replace("_", "-"), "?") for name in names}
    outcome = {}
    for name in names:  # one at a time, to name each that fails
        single, stderr = pip([name])
        if single is not None:
            outcome[name] = wheel_file(single["install"][0])
        else:
            error = [line for line in stderr.splitlines() if line.startswith("ERROR")]
            outcome[name] = "NO WHEEL: " + (error[0] if error else stderr.strip()[-200:])
    return outcome


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--platform", nargs="+", choices=sorted(PLATFORMS), default=list(PLATFORMS))
    parser.add_argument("--python", nargs="+", default=list(PYTHONS), help="Python versions (default: 3.12 3.13)")
    parser.add_argument("--markers-only", action="store_true",
                        help="print which requirements apply on each platform; resolve nothing")
    parser.add_argument("--jobs", type=int, default=3, help="resolutions at once (default: 3)")
    args = parser.parse_args(argv)
    failed = []
    with tempfile.TemporaryDirectory(prefix="octcl-platforms-") as folder:
        scratch = Path(folder)
        try:
            requires_dist = wheel_requirements(scratch / "wheel")
        except subprocess.CalledProcessError as exc:
            print(f"check_platforms: error: building octcl's wheel failed ({exc})", file=sys.stderr)
            return 2
        combinations = [(platform, python) for platform in args.platform for python in args.python]
        if args.markers_only:
            for platform, python in combinations:
                requirements = requirements_for(requires_dist, platform, python)
                print(f"{platform} cp{python.replace('.', '')}: " + ", ".join(map(str, requirements)))
            return 0

        def check(index: int, platform: str, python: str) -> dict[str, str]:
            folder = scratch / f"resolve-{index}"  # each pip call its own report and target
            folder.mkdir()
            return resolve(requirements_for(requires_dist, platform, python), platform, python, folder)

        # pip's resolution is mostly its own CPU time (about 15 s a platform on a slow core) and the index's
        # latency: three at once took the ten from 156 s to 92 s on two first-generation Zen cores. Printed in order.
        with concurrent.futures.ThreadPoolExecutor(max(1, args.jobs)) as pool:
            outcomes = [pool.submit(check, index, *pair) for index, pair in enumerate(combinations)]
            for (platform, python), future in zip(combinations, outcomes):
                outcome = future.result()
                bad = [name for name, wheel in outcome.items() if wheel.startswith("NO WHEEL")]
                failed += [f"{platform} cp{python.replace('.', '')}: {name}: {outcome[name]}" for name in bad]
                print(f"{'FAIL' if bad else 'ok  '} {platform} cp{python.replace('.', '')}: "
                      + "; ".join(f"{name} -> {wheel}" for name, wheel in outcome.items()), flush=True)
    if failed:
        print("check_platforms: these requirements have no wheel:\n  " + "\n  ".join(failed), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
