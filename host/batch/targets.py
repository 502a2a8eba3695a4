"""The scans of a batch: found under a folder, named by their path, skipped when already done.

Targets are the B-scans under ``--targets``, walked recursively: ``*.npy``
(2-D ``uint8`` grey levels, as the SynthOCT challenge ships its real skin
scans, e.g. ``Male/1990-2000/Cheek/NAME.npy``) and ``*.png``, except the
official processor's map files (``*_OAC.png``, ``*_SC.png``, ``*_RSC.png``)
and the images a batch writes itself (:data:`OUTPUT_SUFFIXES`). Hidden
folders and the output folder, when it lies inside the targets, are not
entered. Each scan's outputs mirror its place in the tree under ``--out``:
``Male/1990-2000/Cheek/NAME.txt`` beside ``NAME.report.json`` and so on.

A scan is done, and skipped by the next run, when its report records a
:func:`settings_record` equal to this run's (octcl version, time budget,
seed, :func:`octcl.host.pipeline.invert.invert` options) and the SHA-256 of the
target bytes it was inverted from, and the phantom file's SHA-256 is the one
the report recorded. The report is written last, each file atomically, so a
run killed at any moment leaves either a done scan or one that is redone.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

from octcl._io import SCAN_SUFFIXES, atomic_write
from octcl.scorer import MAP_FILE_SUFFIXES

from .report import PICTURES

#: Files a batch writes for each scan, by kind: the phantom, invert's report
#: (with the batch record), the target/rendering comparison panel, the
#: score-against-time plot where the run scored more than once and, in the
#: tissue regime, the attenuation panel.
OUTPUT_SUFFIXES = {"phantom": ".txt", "report": ".report.json", "panel": ".panel.png", "plot": ".score.png",
                   "tissue": ".tissue.png"}


@dataclass(frozen=True)
class Scan:
    """One target of a batch.

    Attributes
    ----------
    name : str
        The target's path below the targets folder, with ``/`` separators
        (``Male/1990-2000/Cheek/NAME.npy``): its name in summaries.
    target : Path
        The target file.
    stem : Path
        Its outputs without suffix: ``OUT/Male/1990-2000/Cheek/NAME``.
    """

    name: str
    target: Path
    stem: Path

    def output(self, kind: str) -> Path:
        """The output file of ``kind``, a key of :data:`OUTPUT_SUFFIXES`."""
        return self.stem.with_name(self.stem.name + OUTPUT_SUFFIXES[kind])

    def write_pictures(self, pictures: dict[str, bytes]) -> None:
        """Write each picture of ``{kind: PNG}`` (:data:`~octcl.host.batch.report.PICTURES`' kinds), each
        atomically, and remove the file of a kind it lacks: no earlier run's picture is shown as this one's."""
        for kind in PICTURES:
            if kind in pictures:
                with atomic_write(self.output(kind)) as handle:
                    handle.write(pictures[kind])
            else:
                self.output(kind).unlink(missing_ok=True)

    def read_pictures(self) -> dict[str, bytes] | None:
        """``{kind: PNG}`` of the pictures on disk; None where the panel, which every scan has, is missing or
        unreadable."""
        try:
            return {kind: self.output(kind).read_bytes() for kind in PICTURES
                    if kind == "panel" or self.output(kind).exists()}
        except OSError:
            return None


def _is_target(file_name: str) -> bool:
    return (file_name.endswith(SCAN_SUFFIXES) and not file_name.startswith(".")
            and not file_name.endswith(MAP_FILE_SUFFIXES)
            and not file_name.endswith(tuple(OUTPUT_SUFFIXES.values())))


def find_scans(targets_dir, out_dir) -> list[Scan]:
    """Every target under ``targets_dir``, sorted by name, with its outputs under ``out_dir``.

    Raises
    ------
    FileNotFoundError
        ``targets_dir`` is not a folder or holds no target.
    ValueError
        Two targets would write the same outputs (``NAME.png`` and
        ``NAME.npy`` in one folder); all such pairs are named.
    """
    targets_dir, out_dir = Path(targets_dir), Path(out_dir)
    if not targets_dir.is_dir():
        raise FileNotFoundError(f"{targets_dir}: no such folder")
    skip = out_dir.resolve()
    scans = []
    for folder, subfolders, files in os.walk(targets_dir):
        folder = Path(folder)
        subfolders[:] = sorted(name for name in subfolders
                               if not name.startswith(".") and (folder / name).resolve() != skip)
        for file_name in sorted(filter(_is_target, files)):
            relative = (folder / file_name).relative_to(targets_dir)
            scans.append(Scan(relative.as_posix(), folder / file_name, out_dir / relative.with_suffix("")))
    if not scans:
        raise FileNotFoundError(f"{targets_dir}: no target scans (*.npy, or *.png other than map files), "
                                "searched recursively")
    by_stem = {}
    for scan in scans:
        by_stem.setdefault(scan.stem, []).append(scan.name)
    clashes = ["; ".join(names) for names in by_stem.values() if len(names) > 1]
    if clashes:
        raise ValueError(f"{targets_dir}: targets that would write the same outputs: {' | '.join(clashes)}; "
                         "rename one of each")
    return sorted(scans, key=lambda scan: scan.name)


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _plain(value):
    """JSON form of an invert option: dataclasses (schedules, configs) as dicts, paths as strings."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"invert option of type {type(value).__name__} has no JSON form: {value!r}")


def settings_record(time_budget_s: float, seed: int, options: dict) -> dict:
    """What a scan's result depends on besides its target: recorded in its report, compared on resume."""
    from octcl import __version__

    return {"octcl_version": __version__, "time_budget_s": float(time_budget_s), "seed": int(seed),
            "options": json.loads(json.dumps(options, default=_plain, sort_keys=True))}


def completed_report(scan: Scan, target_sha256: str, settings: dict) -> dict | None:
    """The report of an earlier run of ``scan`` on the same target bytes with the same settings, if complete.

    None when the report is missing or unreadable, records another target
    or other settings, or the phantom is missing or not the file the report
    recorded (its SHA-256).
    """
    try:
        report = json.loads(scan.output("report").read_text(encoding="utf-8"))
        record = report["batch"]
        if record["target_sha256"] != target_sha256 or any(record.get(k) != v for k, v in settings.items()):
            return None
        if sha256(scan.output("phantom").read_bytes()) != record["phantom_sha256"]:
            return None
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return report


__all__ = ["OUTPUT_SUFFIXES", "Scan", "completed_report", "find_scans", "settings_record", "sha256"]
