"""Datasets at scale: every B-scan of a folder tree inverted on dask.distributed, resumable, with a report.

- :mod:`~octcl.host.batch.targets`: which files are targets, where their
  outputs go, and whether a scan is already done;
- :mod:`~octcl.host.batch.worker`: one scan, as a Dask worker runs it;
- :mod:`~octcl.host.batch.runner`: the cluster (embedded or remote) and the
  loop that submits scans and stores results;
- :mod:`~octcl.host.batch.report`: summary.csv, summary.json, report.html.

``octcl invert --targets DIR --out DIR`` calls :func:`invert_batch`; how to
run it on a cluster is in ``docs/batch.md``.
"""

from .runner import BatchProgress, invert_batch

__all__ = ["BatchProgress", "invert_batch"]
