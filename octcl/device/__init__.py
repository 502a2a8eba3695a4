"""The OpenCL device layer every stage uses.

- :mod:`~octcl.device.runtime`: the OpenCL implementations octcl registers,
  device choice (``--device``, ``OCTCL_DEVICE``), quiet builds, clear errors;
- :mod:`~octcl.device.programs`: the one place that builds octcl's kernel
  files (``kernels/*.cl`` after ``kernels/prelude.cl``) with the host's
  constants as defines;
- :mod:`~octcl.device.scanner`: the Virtual Scanner and its adjoint
  (``kernels/scanner.cl``), whose float64 reference is :mod:`octcl._reference`;
- :mod:`~octcl.device.depth_order`: the scanner's depth order
  (``kernels/depth_order.cl``) and its Python twin.

The inversion's own ops sit beside their NumPy references in the stage
that uses them (:mod:`octcl.host.stage1`, :mod:`octcl.host.optim`).
"""
