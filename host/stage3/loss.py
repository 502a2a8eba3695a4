"""The scorer-aligned loss on the rendered display, in torch.

The score compares four 8-bit maps of the rendered scan with those of the
target: the scan itself (Struct) and the processor's OAC, SC and RSC maps
(:mod:`octcl.maps`), each by MS-SSIM and 1 − LPIPS. The loss is a weighted
sum of differentiable stand-ins for those comparisons, evaluated on the
display D ∈ [0, 1] of the rendering:

1. Straight-through quantisation. The scorer sees the 8-bit level
   L = quantise(D) (:func:`octcl._reference.quantise`), read back as L/255.
   The forward pass uses exactly that, P = L/255; the backward pass treats
   P as 256·D/255, the slope of floor(256·D)/255 on average, so
   ∂L/∂D = (256/255)·∂L/∂P (Bengio, Léonard & Courville, "Estimating or
   propagating gradients through stochastic neurons", arXiv:1308.3432, 2013).
2. Maps of P by :func:`octcl.maps.maps_torch` (OAC normalised by its own
   minimum and 99th percentile, SC and RSC on the fixed 0.5–5 window),
   compared with the same maps of the target, computed once.
3. The terms, each a mean over the pixels (weights in :class:`LossWeights`)::

       pixel          mean|P − T| + mean (P − T)²
       level          mean e + mean e²,  e = max(|P̃ − C| − f·H, 0)
       sc_l1          mean|SC(P) − SC(T)|
       oac_l1         mean|OAC(P) − OAC(T)|
       oac_lpips      LPIPS(OAC(T), OAC(P))
       oac_msssim     1 − MS-SSIM(OAC(T), OAC(P))
       struct_msssim  1 − MS-SSIM(T, P)
       struct_lpips   LPIPS(T, P)
       sc_lpips       LPIPS(SC(T), SC(P))
       rsc_lpips      LPIPS(RSC(T), RSC(P))

   A term with weight 0 is not computed at all (LPIPS costs most).

   ``level`` is octcl's, the term of a ``level`` phase
   (:meth:`LossWeights.for_terms`), not the published method's: P̃ = 256·D/255
   unquantised, C and H the centre and half-width of the display interval of
   the pixel's target level
   (:func:`octcl.host.stage1.levels.display_interval_of_level`, in the same
   units), f = :data:`LEVEL_MARGIN`; at level 0 it is |P − T|. The pixel term
   on P is 0 wherever the level is right, however near the interval's edge
   the display lies, so the next step's moves of the scatterers that pixel
   shares with others knock it off again; the level term keeps pulling the
   display into the middle of its interval. Measured in the tissue regime's
   stage 3 (:data:`LEVEL_MARGIN`), it puts more pixels at their level, and
   scores no higher: the tissue regime's pixel phase keeps the pixel term.

LPIPS (Zhang et al., CVPR 2018) compares unit-normalised AlexNet features;
the target's features do not change during an inversion, so they are
computed once and only the rendering goes through the network each call.
LPIPS is still most of a call (one AlexNet forward and backward per term:
on two cores, before AlexNet ran with oneDNN, 0.69–0.89 s a refinement
step for the full loss and 0.16–0.20 s without LPIPS, :class:`LossWeights`),
so a call can instead keep the LPIPS terms' value and gradient and later
calls reuse them (``lpips="keep"`` / ``"reuse"``): while the display moves
little, the gradient of the sum is
then ∂(rest)/∂D at the new display plus ∂LPIPS/∂D at the kept one.
Measured from the same starting phantoms (``scripts/bench_refine.py``,
docs/benchmarks.md, "what the loss's LPIPS terms buy per second"), neither
reusing the LPIPS gradient nor leaving LPIPS terms out gains score per
second on the development set, so refinement computes every term on every
step by default.

:class:`ExactScore` is the quantity the loss stands in for: the eight
official components (:mod:`octcl.scorer`) of a rendering's 8-bit levels
against the target, bit for bit as the scorer computes them from the saved
files.
"""

from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass

import numpy as np

from octcl.torch_import import import_torch

# The loss is where a run's torch comes in (the exact score, the aim step, stage 3): timed here for the next
# run's budget estimates (octcl.torch_import).
torch = import_torch()

from octcl import _reference as ref
from octcl import scorer
from octcl._lpips import lpips_network
from octcl._msssim import msssim_torch
from octcl.maps import map_levels, maps_torch

from ..stage1.levels import display_interval_of_level
from .schedule import LPIPS_TERMS, LossWeights
from ..pipeline.target import target_scan, target_struct_for_metrics

#: ∂P/∂D of the straight-through quantiser: P = floor(256·D)/255 on average.
QUANTISER_SLOPE = 256.0 / 255.0
_MSSSIM_TERMS = {"struct_msssim": "Struct", "oac_msssim": "OAC"}
#: The processor's map each term compares (:func:`octcl.maps.maps_torch`); the other terms compare the scan.
_TERM_MAPS = {"sc_l1": "SC", "oac_l1": "OAC", "oac_lpips": "OAC", "oac_msssim": "OAC", "sc_lpips": "SC",
              "rsc_lpips": "RSC"}
#: The level term's margin f, a share of each level's half-width within which a display is not pulled further
#: towards the interval's centre (module docstring). Chosen on skin 6 in a first trial (16 s of the tissue
#: regime's pixel phase from its decode, two cores): f = 0.6 and 0.8 put 90.3 % and 89.5 % of the pixels at their
#: level, margins of 0.1/256 and 0.3/256 in D 89.5 % and 90.0 %, the pixel term 87.1 %. What the level phase then
#: does to the score: docs/benchmarks.md, "A level phase for stage 3: measured, not the default".
LEVEL_MARGIN = 0.6


@contextlib.contextmanager
def _onednn_off():
    """Run torch's CPU convolutions without oneDNN (see :class:`DisplayLoss`), then restore."""
    previous = torch.backends.mkldnn.enabled
    torch.backends.mkldnn.enabled = False
    try:
        yield
    finally:
        torch.backends.mkldnn.enabled = previous


@contextlib.contextmanager
def _one_thread():
    """Run torch on one thread, then restore the caller's count."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


@dataclass
class LossValue:
    """One evaluation of :class:`DisplayLoss`.

    Attributes
    ----------
    loss : float
        The weighted sum of the terms.
    grad_display : ndarray of float64, (Nz, Nx)
        ∂loss/∂D through the straight-through quantiser.
    terms : dict
        Each computed term's unweighted value.
    """

    loss: float
    grad_display: np.ndarray
    terms: dict


class DisplayLoss:
    """The loss of a rendered display against one target scan.

    Parameters
    ----------
    target_scan : (Nz, Nx) float array
        The target B-scan as :func:`octcl._io.read_scan` reads it (levels/255).
    weights : LossWeights
        Term weights.
    dtype : torch.dtype
        Arithmetic precision of the maps and MS-SSIM; float32 suffices to
        steer an optimiser. LPIPS runs in float32 either way (its weights
        are float32).

    Notes
    -----
    The maps and MS-SSIM run with oneDNN (mkldnn) convolutions off:
    MS-SSIM's single-channel 11-tap filters run 4.7× slower through oneDNN
    in float32 (0.85 s against 0.18 s for forward and backward of two
    256×512 maps on one core). LPIPS's AlexNet runs with it, on detached
    copies of the maps (:meth:`__call__`): the whole loss then takes 0.75–0.92
    of its time without (0.59–0.63 s against 0.67–0.81 s a refinement step
    on two cores, ``scripts/bench_refine.py``, docs/benchmarks.md). The
    backward pass picks its convolution backend again, so each part goes
    back under its own setting.
    """

    def __init__(self, target_scan: np.ndarray, weights: LossWeights = LossWeights(),
                 dtype: torch.dtype = torch.float32):
        self.weights, self.dtype = weights, dtype
        self._kept_lpips = None  # (weighted sum, its ∂/∂D, the terms) of the last lpips="keep" call
        # Only what the weighted terms compare is built: with the maps, the network and four maps' features it never
        # used, a loss of the pixel or the level term alone took as long to build as the full loss's (the tissue
        # regime's pixel phase builds one).
        weighted = self._wanted(lpips=True)
        lpips_maps = [LPIPS_TERMS[name] for name in LPIPS_TERMS if name in weighted]
        self.network = lpips_network() if lpips_maps else None
        with torch.no_grad():
            with _onednn_off():
                target = torch.as_tensor(np.asarray(target_scan), dtype=dtype)
                self.target = self._images(target, weighted)
            self._level_goal = self._level_intervals(target_scan, dtype) if "level" in weighted else None
            # AlexNet with oneDNN, as in __call__, and on one thread: the loss must not depend on the
            # thread count at which it was built. Without oneDNN, layers 2–5 differed between 1 and 2
            # threads on an EPYC; with it they did not there, but did on a first-generation Zen
            # (tests/stage3/test_refine.py, the loss whatever thread count built it).
            with _one_thread():
                self._target_taps = {name: self._taps(self.target[name]) for name in lpips_maps}

    @staticmethod
    def _level_intervals(target_scan: np.ndarray, dtype: torch.dtype) -> tuple:
        """The level term's C, f·H (module docstring) and level-0 mask, per pixel of the target."""
        levels = np.rint(np.asarray(target_scan, dtype=np.float64) * 255.0).astype(np.intp)
        low, high = display_interval_of_level()
        return (torch.as_tensor(QUANTISER_SLOPE * (low + high)[levels] / 2, dtype=dtype),
                torch.as_tensor(LEVEL_MARGIN * QUANTISER_SLOPE * (high - low)[levels] / 2, dtype=dtype),
                torch.as_tensor(levels == 0))

    def _taps(self, image: torch.Tensor) -> list[torch.Tensor]:
        """LPIPS's unit-normalised AlexNet activations of a grey (H, W) image in [0, 1]."""
        return self.network.normalised_taps(image[None, None].float())

    def _lpips(self, name: str, image: torch.Tensor) -> torch.Tensor:
        """LPIPS(target map, image) = Σ_l mean_hw w_l·(f̂_l(T) − f̂_l(P))², target features cached."""
        return self.network.distance(self._target_taps[name], self._taps(image))[0]

    def _wanted(self, lpips: bool) -> set[str]:
        """The terms with a positive weight (without the LPIPS ones unless ``lpips``)."""
        return {name for name, weight in dataclasses.asdict(self.weights).items()
                if weight > 0 and (lpips or name not in LPIPS_TERMS)}

    @staticmethod
    def _images(scan: torch.Tensor, wanted: set[str]) -> dict[str, torch.Tensor]:
        """The scan and those of its OAC, SC and RSC maps that a wanted term compares (no other is computed)."""
        names = {_TERM_MAPS[name] for name in wanted if name in _TERM_MAPS}
        return {"Struct": scan, **(maps_torch(scan, names) if names else {})}

    def _pixel_terms(self, images: dict, wanted: set[str], unquantised: torch.Tensor) -> dict[str, torch.Tensor]:
        """The wanted terms other than LPIPS: pixel, level, L1 and MS-SSIM; ``unquantised`` is P̃ (module
        docstring), the scan before the quantiser."""
        target, terms = self.target, {}
        if wanted & {"pixel", "level"}:
            difference = images["Struct"] - target["Struct"]
        if "pixel" in wanted:
            terms["pixel"] = difference.abs().mean() + (difference**2).mean()
        if "level" in wanted:
            centre, margin, floor = self._level_goal
            excess = torch.where(floor, difference.abs(), torch.relu((unquantised - centre).abs() - margin))
            terms["level"] = excess.mean() + (excess**2).mean()
        for name, map_name in (("sc_l1", "SC"), ("oac_l1", "OAC")):
            if name in wanted:
                terms[name] = (images[map_name] - target[map_name]).abs().mean()
        msssim_wanted = [name for name in _MSSSIM_TERMS if name in wanted]
        if msssim_wanted:  # one batched call for both maps
            maps = [_MSSSIM_TERMS[name] for name in msssim_wanted]
            similarity = msssim_torch(torch.stack([target[m] for m in maps]),
                                      torch.stack([images[m] for m in maps]))
            terms.update({name: 1 - value for name, value in zip(msssim_wanted, similarity)})
        return terms

    def _lpips_terms(self, images: dict, wanted: set[str]) -> dict[str, torch.Tensor]:
        return {name: self._lpips(map_name, images[map_name])
                for name, map_name in LPIPS_TERMS.items() if name in wanted}

    def terms(self, scan: torch.Tensor, lpips: bool = True) -> dict[str, torch.Tensor]:
        """The unweighted terms with a positive weight, differentiable in the scan P.

        Parameters
        ----------
        scan : (Nz, Nx) tensor
            The grey B-scan P ∈ [0, 1] as the scorer reads it (also the level term's P̃).
        lpips : bool
            Compute the LPIPS terms too.
        """
        wanted = self._wanted(lpips)
        images = self._images(scan, wanted)
        return {**self._pixel_terms(images, wanted, scan), **self._lpips_terms(images, wanted)}

    def __call__(self, display: np.ndarray, lpips: str = "compute") -> LossValue:
        """Loss and ∂loss/∂D for a display D (float array, the shape of the target).

        Parameters
        ----------
        display : (Nz, Nx) float array
        lpips : {"compute", "keep", "reuse"}
            ``compute``: every term at D. ``keep``: the same, and keep the
            LPIPS terms' weighted sum and its gradient ∂/∂D (the LPIPS part
            and the rest go back through the maps in two passes; the
            gradient agrees with ``compute`` to float rounding). ``reuse``:
            the other terms at D, plus the LPIPS values and gradient kept by
            the last ``keep`` call (whose terms appear in ``terms`` as they
            were then).

        Raises
        ------
        ValueError
            A display of the wrong shape, an unknown ``lpips``, or ``reuse``
            before any ``keep``.

        Notes
        -----
        AlexNet runs on detached copies M' of the maps it compares, with
        torch's oneDNN setting as the caller has it (on by default, and
        faster for AlexNet: class Notes), while the maps and MS-SSIM run
        without oneDNN. Its gradients
        G_m = ∂LPIPS/∂M'_m then go back through the maps as the surrogate
        Σ_m ⟨M_m, G_m⟩, whose gradient is the chain rule's
        Σ_m (∂M_m/∂D)ᵀ G_m: the maps' graph is traversed once.
        """
        display = np.asarray(display)
        if display.shape != tuple(self.target["Struct"].shape):
            raise ValueError(f"display is {display.shape}, target is {tuple(self.target['Struct'].shape)}")
        if lpips not in ("compute", "keep", "reuse"):
            raise ValueError(f"lpips must be 'compute', 'keep' or 'reuse', got {lpips!r}")
        if lpips == "reuse" and self._kept_lpips is None:
            raise ValueError("lpips='reuse' needs an earlier call with lpips='keep'")
        d = torch.tensor(display, dtype=self.dtype, requires_grad=True)
        quantised = torch.as_tensor(ref.quantise(display) / 255.0, dtype=self.dtype)
        # Forward value: the level the scorer reads; gradient: slope 256/255.
        scan = quantised + (QUANTISER_SLOPE * d - (QUANTISER_SLOPE * d).detach())
        wanted = self._wanted(lpips != "reuse")

        def weighted_sum(terms):
            # Starts from 0·ΣD so that a sum with no term still has a gradient (of zero).
            return sum((getattr(self.weights, name) * value for name, value in terms.items()), 0 * d.sum())

        with _onednn_off():
            images = self._images(scan, wanted)
            terms = self._pixel_terms(images, wanted, QUANTISER_SLOPE * d)
            loss = weighted_sum(terms)
        value = loss.item()
        if wanted & set(LPIPS_TERMS):  # AlexNet with oneDNN on the maps' copies (Notes)
            # In LPIPS_TERMS's order, so that the sums below add up the same way in every process.
            copies = {LPIPS_TERMS[name]: images[LPIPS_TERMS[name]].detach().requires_grad_(True)
                      for name in LPIPS_TERMS if name in wanted}
            lpips_terms = self._lpips_terms(copies, wanted)
            lpips_loss = weighted_sum(lpips_terms)
            grads = dict(zip(copies, torch.autograd.grad(lpips_loss, list(copies.values()))))
            terms.update(lpips_terms)
            value += lpips_loss.item()
            with _onednn_off():
                through_maps = sum(((images[m] * g).sum() for m, g in grads.items()), 0 * d.sum())
                if lpips == "keep":
                    lpips_grad, = torch.autograd.grad(through_maps, d, retain_graph=True)
                    self._kept_lpips = (lpips_loss.item(), lpips_grad.numpy().astype(np.float64),
                                        {name: term.item() for name, term in lpips_terms.items()})
                else:
                    loss = loss + through_maps
        with _onednn_off():
            loss.backward()
        grad_display = d.grad.numpy().astype(np.float64)
        terms = {name: term.item() for name, term in terms.items()}
        if lpips != "compute":
            kept_loss, kept_grad, kept_terms = self._kept_lpips
            grad_display = grad_display + kept_grad
            if lpips == "reuse":
                value += kept_loss
                terms.update(kept_terms)
        return LossValue(loss=value, grad_display=grad_display, terms=terms)


def scan_of_levels(levels: np.ndarray) -> np.ndarray:
    """The float32 scan :func:`octcl._io.read_scan` reads from a grey PNG of these levels.

    Same arithmetic as the reader (each of R = G = B divided by 255 in
    float32, then their float32 mean), so the processor's maps of it are
    those of the saved scan, bit for bit.
    """
    return target_scan(np.asarray(levels, dtype=np.uint8))


class ExactScore:
    """The eight official score components of rendered levels against a target.

    Parameters
    ----------
    target : ndarray of uint8
        The target B-scan (256×512), in either form of :mod:`octcl.host.pipeline.target`
        (:func:`octcl.host.pipeline.target.read_target` reads one from a PNG).

    Notes
    -----
    Each call costs the processor's maps, four exact MS-SSIMs and four
    LPIPS distances against the target's side taken once (0.16–0.25 s on
    two Zen 4 cores, 0.26–0.32 s on one; orange.png), so the refinement
    evaluates it at checkpoints only.
    """

    def __init__(self, target: np.ndarray):
        scan = target_scan(target)
        if scan.shape != scorer.SCAN_SHAPE:
            raise ValueError(f"the target is {scan.shape[0]}x{scan.shape[1]}, the scorer takes "
                             f"{scorer.SCAN_SHAPE[0]}x{scorer.SCAN_SHAPE[1]}")
        self.target_maps = scorer.maps_for_metrics(target_struct_for_metrics(target), scan)
        # The target's LPIPS features and MS-SSIM side, once: half of each score's AlexNet passes (0.24 → 0.12 s
        # of a score's 0.4 s on two cores, orange.png) and two of each MS-SSIM scale's five local means, with the
        # same bits (octcl.scorer.ScoreReference).
        self.reference = scorer.ScoreReference(self.target_maps)

    @staticmethod
    def maps_of_levels(levels: np.ndarray) -> dict[str, np.ndarray]:
        """The Struct, OAC, SC and RSC 8-bit maps of a scan saved with these levels."""
        return {"Struct": levels, **map_levels(scan_of_levels(levels))}

    def __call__(self, levels: np.ndarray) -> dict[str, float]:
        """``msssim_<map>`` and ``one_minus_lpips_<map>`` for the four maps, and ``mean``."""
        predicted = {name: scorer.levels_for_metrics(image)
                     for name, image in self.maps_of_levels(levels).items()}
        components = scorer.score_grey_maps(self.target_maps, predicted, self.reference)
        components["mean"] = float(np.mean([components[name] for name in scorer.COMPONENTS]))
        return components


__all__ = ["DisplayLoss", "ExactScore", "LossValue", "LossWeights", "QUANTISER_SLOPE",
           "scan_of_levels"]
