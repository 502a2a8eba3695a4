"""Stage 1: a complex reflectivity field on the pixel grid whose rendering has the target's levels.

Models and maths, each a float64 NumPy reference, with its OpenCL op beside it
(``<name>.py`` and ``<name>_device.py``):

- :mod:`~.levels`: the target's levels as displays, magnitudes and intervals;
- :mod:`~.operator` / :mod:`~.operator_device`: the field operator H, Hᴴ, H⁺;
- :mod:`~.display_loss` / :mod:`~.display_device`: the display fit's loss and gradient;
- :mod:`~.levels_device`: the intervals' projection and hinge residual;
- :mod:`~.backend`: the two backends (NumPy, OpenCL) that run each step's loop.

Steps, each written once for both backends:

- :mod:`~.display` (``display``), :mod:`~.projections` (``project``),
  :mod:`~.hinge` (``hinge``), :mod:`~.aim` (``aim``, with the aimed levels
  of :mod:`~.ceiling`);
- :mod:`~.solve`: schedules of steps and the solve that runs one;
- :mod:`~.start`: the linear regime's candidate schedules, the best kept.
"""
