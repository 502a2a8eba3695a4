"""The whole inversion: :mod:`~.invert` runs stages 1–3 (:mod:`octcl.host.stage1`,
:mod:`octcl.host.stage2`, :mod:`octcl.host.stage3`) under one clock, writes
the phantom and its report; :mod:`~.target` reads and checks the target B-scan."""
