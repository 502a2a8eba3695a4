"""Stage 2: a field decoded into a phantom.

- :mod:`~.exact`: the linear regime's exact decode, two rows per cell that
  render as the field does;
- :mod:`~.capped`: the physical regime's amplitude-capped children.
"""
