"""Stage 3: the phantom refined with the scanner in the loop.

- :mod:`~.refine`: Adam on every scatterer's depth and log-energy, through
  the scanner's hand-derived adjoint (:mod:`octcl.device.scanner`);
- :mod:`~.loss`: the scorer-aligned losses (torch on the CPU: LPIPS, MS-SSIM);
- :mod:`~.schedule`: phases, loss weights and stop rules as data.
"""
