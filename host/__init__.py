"""The inversion's host side, one folder per stage of the pipeline.

- :mod:`~octcl.host.stage1`: the field (display fit, projections, hinge, aim) on a NumPy or OpenCL backend;
- :mod:`~octcl.host.stage2`: the decode of the field into a phantom;
- :mod:`~octcl.host.stage3`: the refinement with the scanner in the loop;
- :mod:`~octcl.host.pipeline`: ``invert`` (the stages under one clock) and the target;
- :mod:`~octcl.host.optim`: Adam and L-BFGS (host and device);
- :mod:`~octcl.host.batch`: many scans on dask.distributed;
- :mod:`~octcl.host.threads`: the host's FFT threads.
"""
