"""octcl: vendor-neutral, OpenCL-accelerated coherent inversion of OCT B-scans into digital phantoms.

Public surface:

- :class:`Phantom` — point scatterers (x, y, z in µm, energy E in %), text I/O and checks;
- :class:`ScannerConfig` — the Virtual Scanner's Configuration.ini;
- :func:`render` — phantom → B-scan (OpenCL kernels, or the float64 NumPy reference);
- :func:`score` — the SynthOCT 2026 score of a predicted B-scan against a reference;
- :func:`invert` — target B-scan (PNG or array) → phantom whose rendering matches it.

The ``octcl`` command wraps them (``octcl --help``).
"""

from .config import ScannerConfig
from .phantom import Phantom
from .render import render

#: octcl's version, the one place it is written (setup.cfg reads it: ``version = attr: octcl.__version__``).
__version__ = "0.8.14"
__all__ = ["Phantom", "ScannerConfig", "render", "score", "invert", "__version__"]


def score(ref, pred) -> dict:
    """Score a predicted B-scan PNG against a reference (see :func:`octcl.scorer.score`)."""
    from .scorer import score as _score

    return _score(ref, pred)


def invert(target, output_path, **options):
    """Invert a target B-scan (PNG path or uint8 array) into a phantom file (:func:`octcl.host.pipeline.invert.invert`)."""
    from .host.pipeline.invert import invert as _invert

    return _invert(target, output_path, **options)
