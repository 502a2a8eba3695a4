"""The repository stands alone: no tracked file names where a checkout of it lies.

A path such as the checkout's own folder or the folder beside it holds only on
one machine; a clone elsewhere must not depend on it, so none may be written in
a tracked file (code, docs or data).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

CHECKOUT = Path(__file__).absolute().parents[1]


def shared_folders() -> set[Path]:
    """Folders every machine has, as given and resolved: a root, the temporary folder, the home folder.

    A checkout cloned straight into one of them (``/tmp/octcl``) has it as its
    parent, yet a recorded command that writes under ``/tmp`` names nothing
    of this machine.
    """
    folders = {Path(tempfile.gettempdir()), Path("/tmp"), Path.home()}
    folders |= {folder.resolve() for folder in folders}
    return folders | {Path(folder.anchor) for folder in folders}


def machine_paths(checkout: Path) -> set[str]:
    """The checkout's absolute path and its parent folder's, as given and resolved, less shared folders."""
    paths = {checkout, checkout.parent, checkout.resolve(), checkout.resolve().parent}
    shared = shared_folders() | {Path(path.anchor) for path in paths}
    return {path.as_posix() for path in paths if path not in shared}


def mentions(files: list[Path], paths: set[str], root: Path) -> list[str]:
    """``file:line: path`` for every whole-path mention of one of ``paths`` in ``files``.

    A mention starts where no path character precedes it and ends at a ``/``
    or a non-name character, so that ``/a/b`` is found in ``/a/b/c`` but not
    in ``/a/bc`` or ``x/a/b``.
    """
    pattern = re.compile(
        rb"(?<![\w.~/-])(" + b"|".join(re.escape(p.encode()) for p in sorted(paths, key=len, reverse=True))
        + rb")(?![\w.-])"
    )
    found = []
    for file in files:
        if not file.is_file():  # deleted in the working tree but still tracked
            continue
        content = file.read_bytes()
        for match in pattern.finditer(content):
            line = content.count(b"\n", 0, match.start()) + 1
            found.append(f"{file.relative_to(root)}:{line}: {match.group(1).decode()}")
    return found


def tracked_files(checkout: Path) -> list[Path]:
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    result = subprocess.run(["git", "-C", str(checkout), "ls-files", "-z"], capture_output=True)
    if result.returncode != 0:
        pytest.skip(f"not a git checkout: {result.stderr.decode().strip()}")
    return [checkout / name for name in result.stdout.decode().split("\0") if name]


def test_no_tracked_file_names_the_checkout_or_its_parent_folder():
    files = tracked_files(CHECKOUT)
    assert files, "git ls-files listed no files"
    found = mentions(files, machine_paths(CHECKOUT), CHECKOUT)
    assert found == [], "tracked files name where this checkout lies:\n" + "\n".join(found)


def test_mentions_finds_whole_paths_only(tmp_path):
    checkout = tmp_path / "repo"
    checkout.mkdir()
    parent = checkout.parent.as_posix()
    (checkout / "a.md").write_text(f"ok\nrun {parent}/shared/data\n")
    (checkout / "b.py").write_bytes(f'DATA = "{checkout.as_posix()}"\n'.encode())
    (checkout / "c.txt").write_text(f"{parent}x/y and src{parent}/z and {parent}-old/\n")
    files = sorted(checkout.iterdir())

    assert mentions(files, machine_paths(checkout), checkout) == [
        f"a.md:2: {parent}", f"b.py:1: {checkout.as_posix()}"]
    assert "/" not in machine_paths(Path("/repo"))


def test_a_checkout_cloned_into_the_temporary_folder_names_only_itself():
    temporary = Path(tempfile.gettempdir())
    paths = machine_paths(temporary / "octcl")
    assert (temporary / "octcl").as_posix() in paths
    assert temporary.as_posix() not in paths and "/tmp" not in paths
    assert (temporary / "x").as_posix() in machine_paths(temporary / "x" / "octcl")
