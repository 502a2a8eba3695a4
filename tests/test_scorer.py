"""The SynthOCT score: map reading as the official metric, components, directories."""

import csv
import shutil

import numpy as np
import pytest
from PIL import Image

from octcl._io import read_png_rgb, write_grey_png
from octcl.scorer import (
    COMPONENTS,
    MAP_NAMES,
    ScoreReference,
    levels_for_metrics,
    _msssim_input,
    _prediction,
    _read_map_for_metrics,
    _scan_maps_for_metrics,
    score,
    score_directories,
    score_grey_maps,
    score_maps,
    write_score_csv,
)

UNIFORM_A = "Scan_Exp1_Uniform_A.png"
UNIFORM_B = "Scan_Exp1_Uniform_B.png"
LAYERS_A = "Scan_Exp2_Layers_A.png"


def _skimage_reading(path):
    from skimage.io import imread
    from skimage.util import img_as_float

    return img_as_float(imread(path, as_gray=True))


def _all_levels_image():
    levels = np.random.default_rng(0).integers(0, 256, (256, 512)).astype(np.uint8)
    levels[0, :256] = np.arange(256)
    return levels


def _assert_official(components, official, name):
    assert components[f"msssim_{name}"] == pytest.approx(official[name]["MS-SSIM"], abs=1e-12), name
    assert 1 - components[f"one_minus_lpips_{name}"] == pytest.approx(official[name]["LPIPS"], abs=1e-6), name


def test_levels_for_metrics_equals_reading_the_png(tmp_path):
    """All 256 levels of an opaque grey RGBA PNG: in-memory and file readings identical."""
    levels = _all_levels_image()
    write_grey_png(tmp_path / "levels.png", levels)
    np.testing.assert_array_equal(levels_for_metrics(levels), _read_map_for_metrics(tmp_path / "levels.png"))


@pytest.mark.parametrize("kind", ["grey RGBA", "RGB", "translucent RGBA", "grey"])
def test_reading_is_skimage_as_gray_up_to_the_last_bit(tmp_path, kind):
    """Same steps as ``imread(as_gray=True)`` + ``img_as_float``, but for the luminance sum's last bit.

    scikit-image forms the luminance with a BLAS matrix product whose rounding
    depends on the build (fused multiply-adds or not); the scorer sums left
    to right, which is what reproduces the official values exactly.
    """
    rng = np.random.default_rng(1)
    levels = _all_levels_image()
    if kind == "grey RGBA":
        write_grey_png(tmp_path / "map.png", levels)
    else:
        rgba = rng.integers(0, 256, (256, 512, 4)).astype(np.uint8)
        rgba[0, :256, :3] = np.arange(256)[:, None]
        image = {"RGB": Image.fromarray(rgba[..., :3]), "translucent RGBA": Image.fromarray(rgba),
                 "grey": Image.fromarray(levels)}[kind]
        image.save(tmp_path / "map.png")
    ours, skimage_value = _read_map_for_metrics(tmp_path / "map.png"), _skimage_reading(tmp_path / "map.png")
    assert ours.shape == (256, 512) and ours.dtype == np.float64
    np.testing.assert_allclose(ours, skimage_value, rtol=0, atol=2 * np.spacing(1.0))


def test_msssim_input_truncation():
    """33 levels read just below v/255 and become v − 1 in MS-SSIM's input; no other change."""
    levels = np.arange(256, dtype=np.uint8)[None]
    truncated = _msssim_input(levels_for_metrics(levels))[0].astype(int)
    assert set(np.unique(levels[0] - truncated)) == {0, 1}
    assert np.count_nonzero(truncated != levels[0]) == 33
    assert truncated[25] == 24 and truncated[255] == 255 and truncated[0] == 0


def test_score_maps_reproduces_official_values(official_data, lpips_weights, official_uniform_metrics):
    """Official map PNG levels of Uniform_A against Uniform_B: all 8 components."""
    suffixes = {"Struct": "", "OAC": "_OAC", "SC": "_SC", "RSC": "_RSC"}

    def levels(scan):
        return {name: read_png_rgb(official_data / f"Scan_{scan}{suffix}.png")[..., 0]
                for name, suffix in suffixes.items()}

    components = score_maps(levels("Exp1_Uniform_A"), levels("Exp1_Uniform_B"))
    assert tuple(components) == COMPONENTS
    for name in MAP_NAMES:
        _assert_official(components, official_uniform_metrics, name)


def test_a_reference_scored_many_times_gives_the_same_components(official_uniform_maps, lpips_weights):
    """ScoreReference computed once: every component of every prediction to the last bit of a call without it."""
    ref_maps, pred_maps = official_uniform_maps
    reference = ScoreReference(ref_maps)
    for pred in (pred_maps, ref_maps, {name: image[:, ::-1].copy() for name, image in pred_maps.items()}):
        assert score_grey_maps(ref_maps, pred, reference) == score_grey_maps(ref_maps, pred)


def test_score_reproduces_official_values(official_data, lpips_weights, official_uniform_metrics):
    """From the scans alone (maps computed by octcl.maps), all 8 components and their mean."""
    result = score(official_data / UNIFORM_A, official_data / UNIFORM_B)
    assert tuple(result) == COMPONENTS + ("mean",)
    for name in MAP_NAMES:
        _assert_official(result, official_uniform_metrics, name)
    assert result["mean"] == pytest.approx(np.mean([result[c] for c in COMPONENTS]), abs=1e-15)


def test_score_directories_and_csv(official_data, lpips_weights, official_uniform_metrics, tmp_path):
    ref_dir, pred_dir = tmp_path / "ref", tmp_path / "pred"
    ref_dir.mkdir()
    pred_dir.mkdir()
    for name in (UNIFORM_A, LAYERS_A, "Scan_Exp1_Uniform_A_OAC.png", "Scan_Exp1_Uniform_A_SC.png",
                 "Scan_Exp1_Uniform_A_RSC.png"):
        shutil.copy(official_data / name, ref_dir / name)
    shutil.copy(official_data / UNIFORM_B, pred_dir / UNIFORM_A)
    shutil.copy(official_data / LAYERS_A, pred_dir / LAYERS_A)
    calls = []

    result = score_directories(ref_dir, pred_dir, progress=lambda *call: calls.append(call))

    assert calls == [(1, 2, UNIFORM_A), (2, 2, LAYERS_A)]
    assert sorted(result["scans"]) == [UNIFORM_A, LAYERS_A]
    for name in MAP_NAMES:
        _assert_official(result["scans"][UNIFORM_A], official_uniform_metrics, name)
    identical = result["scans"][LAYERS_A]
    assert all(identical[c] == pytest.approx(1.0, abs=1e-12) for c in COMPONENTS)
    for component in COMPONENTS:
        pair = [result["scans"][name][component] for name in (UNIFORM_A, LAYERS_A)]
        assert result["medians"][component] == pytest.approx(np.mean(pair), abs=1e-15)
    assert result["score"] == pytest.approx(np.mean(list(result["medians"].values())), abs=1e-15)

    write_score_csv(result, tmp_path / "out" / "score.csv")
    with open(tmp_path / "out" / "score.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [row["scan"] for row in rows] == [UNIFORM_A, LAYERS_A, "median"]
    assert float(rows[0]["msssim_OAC"]) == result["scans"][UNIFORM_A]["msssim_OAC"]
    assert float(rows[2]["mean"]) == result["score"]


def test_score_directories_names_missing_predictions(official_data, tmp_path):
    ref_dir, pred_dir = tmp_path / "ref", tmp_path / "pred"
    ref_dir.mkdir()
    pred_dir.mkdir()
    with pytest.raises(FileNotFoundError, match="no reference scans"):
        score_directories(ref_dir, pred_dir)
    shutil.copy(official_data / UNIFORM_A, ref_dir / UNIFORM_A)
    shutil.copy(official_data / LAYERS_A, ref_dir / LAYERS_A)
    shutil.copy(official_data / LAYERS_A, pred_dir / LAYERS_A)
    with pytest.raises(FileNotFoundError, match=f"no prediction for {UNIFORM_A}$"):
        score_directories(ref_dir, pred_dir)


def _save_levels(png, npy):
    """``np.save`` the grey levels of the opaque grey scan ``png`` to ``npy``; returns them."""
    rgb = read_png_rgb(png)
    assert (rgb == rgb[..., :1]).all()
    np.save(npy, rgb[..., 0])
    return rgb[..., 0]


@pytest.mark.parametrize("scan", [UNIFORM_A, LAYERS_A, "levels"])
def test_npy_scan_maps_are_those_of_its_grey_png(official_data, tmp_path, scan):
    """The four maps as the metric reads them, from a .npy of levels L and the scanner's PNG of L: equal, bit for bit.

    Struct is the metric's reading of the grey RGBA PNG (:func:`levels_for_metrics`), not L/255: 33 levels differ.
    """
    if scan == "levels":
        levels = _all_levels_image()
        write_grey_png(tmp_path / "levels.png", levels)
        png = tmp_path / "levels.png"
        np.save(tmp_path / "levels.npy", levels)
    else:
        png = official_data / scan
        levels = _save_levels(png, tmp_path / "levels.npy")
    from_png, from_npy = _scan_maps_for_metrics(png), _scan_maps_for_metrics(tmp_path / "levels.npy")
    assert tuple(from_npy) == MAP_NAMES
    for name in MAP_NAMES:
        assert from_npy[name].dtype == np.float64 and from_npy[name].shape == (256, 512)
        np.testing.assert_array_equal(from_npy[name], from_png[name], err_msg=name)
    np.testing.assert_array_equal(from_npy["Struct"], levels_for_metrics(levels))
    assert not np.array_equal(_msssim_input(from_npy["Struct"]), levels)


def test_npy_scores_as_its_png(official_data, lpips_weights, tmp_path):
    _save_levels(official_data / UNIFORM_A, tmp_path / "a.npy")
    _save_levels(official_data / UNIFORM_B, tmp_path / "b.npy")
    expected = score(official_data / UNIFORM_A, official_data / UNIFORM_B)
    assert score(tmp_path / "a.npy", official_data / UNIFORM_B) == expected
    assert score(official_data / UNIFORM_A, tmp_path / "b.npy") == expected


def test_score_directories_with_npy_scans_as_with_pngs(official_data, lpips_weights, tmp_path):
    """.npy references, paired with PNG or .npy predictions, score as the PNG folder, number for number."""
    folders = {name: tmp_path / name for name in ("png_refs", "png_preds", "npy_refs", "mixed_preds")}
    for folder in folders.values():
        folder.mkdir()
    for name in (UNIFORM_A, LAYERS_A):
        shutil.copy(official_data / name, folders["png_refs"] / name)
        _save_levels(official_data / name, folders["npy_refs"] / name.replace(".png", ".npy"))
    for name in ("Scan_Exp1_Uniform_A_OAC.png", "Scan_Exp1_Uniform_A_SC.png", "Scan_Exp1_Uniform_A_RSC.png"):
        shutil.copy(official_data / name, folders["npy_refs"] / name)  # map files: not scans
    shutil.copy(official_data / UNIFORM_B, folders["png_preds"] / UNIFORM_A)
    shutil.copy(official_data / LAYERS_A, folders["png_preds"] / LAYERS_A)
    # A .npy reference's PNG prediction, and another's .npy prediction.
    shutil.copy(official_data / UNIFORM_B, folders["mixed_preds"] / UNIFORM_A)
    _save_levels(official_data / LAYERS_A, folders["mixed_preds"] / LAYERS_A.replace(".png", ".npy"))

    pngs = score_directories(folders["png_refs"], folders["png_preds"])
    npys = score_directories(folders["npy_refs"], folders["mixed_preds"])

    npy_names = [name.replace(".png", ".npy") for name in (UNIFORM_A, LAYERS_A)]
    assert list(npys["scans"]) == npy_names
    for png_name, npy_name in zip((UNIFORM_A, LAYERS_A), npy_names):
        assert npys["scans"][npy_name] == pngs["scans"][png_name]
    assert npys["medians"] == pngs["medians"] and npys["score"] == pngs["score"]
    assert all(pngs["scans"][LAYERS_A][c] == pytest.approx(1.0, abs=1e-12) for c in COMPONENTS)
    assert pngs["scans"][UNIFORM_A]["mean"] < 0.9


def test_score_directories_pairs_npy_and_png_by_name(tmp_path):
    ref_dir, pred_dir = tmp_path / "ref", tmp_path / "pred"
    ref_dir.mkdir()
    pred_dir.mkdir()
    levels = _all_levels_image()
    np.save(ref_dir / "a.npy", levels)
    write_grey_png(ref_dir / "b.png", levels)
    with pytest.raises(FileNotFoundError, match=r"pred: no prediction for a\.npy, b\.png$"):
        score_directories(ref_dir, pred_dir)
    # The same name first, else the other kind; a folder is no prediction.
    (pred_dir / "a.npy").mkdir()
    write_grey_png(pred_dir / "a.png", levels)
    assert _prediction(pred_dir, "a.npy") == pred_dir / "a.png"
    np.save(pred_dir / "b.npy", levels)
    assert _prediction(pred_dir, "b.png") == pred_dir / "b.npy"
    write_grey_png(pred_dir / "b.png", levels)
    assert _prediction(pred_dir, "b.png") == pred_dir / "b.png"
    (pred_dir / "a.npy").rmdir()
    np.save(pred_dir / "a.npy", levels)
    assert _prediction(pred_dir, "a.npy") == pred_dir / "a.npy"
    assert _prediction(pred_dir, "c.png") is None
    # One scan twice among the references is refused, naming the files.
    np.save(ref_dir / "b.npy", levels)
    with pytest.raises(ValueError, match=r"ref: the same reference scan twice: b\.npy and b\.png; keep one"):
        score_directories(ref_dir, pred_dir)
