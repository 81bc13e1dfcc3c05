"""Demosaicing of float HDR Bayer data (issue 3, item 3).

Bars: the Malvar (2004) output matches colour-demosaicing's
``demosaicing_CFA_Bayer_Malvar2004`` to 1e-5 relative (bilinear likewise), for
all four layouts, on random HDR data; the PSNR against ground truth is at least
that of OpenCV's 16-bit edge-aware demosaic on the same mosaic. Run with ``-s``
for the PSNR table (copied to docs/demosaic-rectify.md).
"""

from __future__ import annotations

import warnings
import zlib

import cv2
import numpy as np
import pytest

from btfcore.capture.demosaic import (
    DEMOSAICING_METHODS,
    demosaic,
    demosaicing_CFA_Bayer_bilinear,
    demosaicing_CFA_Bayer_Malvar2004,
)
from btfcore.simulate.sensor import bayer_channel_index, mosaic

PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
OURS = {"bilinear": demosaicing_CFA_Bayer_bilinear, "malvar2004": demosaicing_CFA_Bayer_Malvar2004}

#: OpenCV's Bayer code for each layout named by its top-left 2x2 block (this project's and LibRaw's naming).
#: OpenCV's two-letter codes name the second row's second and third pixels, so they look shifted:
#: RGGB is COLOR_BayerBG2RGB_EA. OpenCV 5 adds four-letter aliases that agree with our naming.
OPENCV_EA = {
    "RGGB": cv2.COLOR_BayerBG2RGB_EA,
    "BGGR": cv2.COLOR_BayerRG2RGB_EA,
    "GRBG": cv2.COLOR_BayerGB2RGB_EA,
    "GBRG": cv2.COLOR_BayerGR2RGB_EA,
}


@pytest.fixture(scope="module")
def colour_demosaicing():
    with warnings.catch_warnings():   # colour's import-time warnings (optional backends, scipy aliases)
        warnings.simplefilter("ignore")
        import colour_demosaicing as cd
    return cd


def _reference(cd, method: str, cfa: np.ndarray, pattern: str) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fn = {"bilinear": cd.demosaicing_CFA_Bayer_bilinear, "malvar2004": cd.demosaicing_CFA_Bayer_Malvar2004}
        return fn[method](np.asarray(cfa, dtype=np.float64), pattern)


def _hdr_cfa(shape, seed: int, dtype) -> np.ndarray:
    """Log-normal HDR values spanning ~6 decades (1e-3 .. 1e3)."""
    rng = np.random.default_rng(seed)
    return np.exp(rng.normal(0.0, 2.3, shape)).astype(dtype)


def _assert_relative(ours: np.ndarray, ref: np.ndarray, cfa: np.ndarray, rtol: float = 1e-5) -> None:
    """|ours - ref| <= rtol * max(|ref|, local CFA magnitude): relative to the output, or to the inputs that the
    5x5 filter combined where that output cancels to ~0."""
    from scipy import ndimage

    scale = ndimage.maximum_filter(np.abs(cfa).astype(np.float64), size=5, mode="reflect")[..., None]
    err = np.abs(ours.astype(np.float64) - ref)
    bound = rtol * np.maximum(np.abs(ref), 1e-6 * scale)
    assert np.all(err <= bound), f"max relative error {np.max(err / np.maximum(np.abs(ref), scale * 1e-6)):.2e}"


# ----------------------------------------------------------------------------- reference match


@pytest.mark.parametrize("method", sorted(OURS))
@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("shape", [(48, 64), (37, 51)])
def test_matches_colour_demosaicing_on_random_hdr(colour_demosaicing, method, pattern, dtype, shape):
    cfa = _hdr_cfa(shape, seed=zlib.crc32(f"{method}-{pattern}-{shape}".encode()), dtype=dtype)
    ours = OURS[method](cfa, pattern)
    ref = _reference(colour_demosaicing, method, cfa, pattern)
    assert ours.shape == shape + (3,) and ours.dtype == dtype
    assert cfa.max() > 100 and cfa.min() < 0.01
    _assert_relative(ours, ref, cfa)
    if dtype == np.float64:          # float64 agrees to rounding
        np.testing.assert_allclose(ours, ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())


def test_measured_colour_is_kept_and_matches_the_sensor_layout():
    rng = np.random.default_rng(1)
    rgb = rng.uniform(0, 50, (12, 10, 3))
    for pattern in PATTERNS:
        cfa = mosaic(rgb, pattern)
        idx = bayer_channel_index(pattern, cfa.shape)
        for method in OURS:
            for border in ("mirror", "reflect"):
                out = demosaic(cfa, pattern, method, border=border)
                kept = np.take_along_axis(out, idx[..., None].astype(np.intp), -1)[..., 0]
                if border == "reflect" and method == "bilinear":   # colour-compatible border mixes the edge
                    kept, want = kept[1:-1, 1:-1], cfa[1:-1, 1:-1]
                else:
                    want = cfa
                np.testing.assert_array_equal(kept, want)


@pytest.mark.parametrize("method", sorted(OURS))
def test_batch_axes(method):
    cfa = _hdr_cfa((2, 3, 20, 22), seed=3, dtype=np.float32)
    out = demosaic(cfa, "GBRG", method)
    assert out.shape == (2, 3, 20, 22, 3)
    np.testing.assert_array_equal(out[1, 2], demosaic(cfa[1, 2], "GBRG", method))


@pytest.mark.parametrize("method", sorted(OURS))
@pytest.mark.parametrize("pattern", PATTERNS)
def test_linear_and_scale_invariant(method, pattern):
    rng = np.random.default_rng(2)
    a, b = rng.uniform(0, 1, (2, 16, 18))
    np.testing.assert_allclose(demosaic(3e4 * a - 2 * b, pattern, method),
                               3e4 * demosaic(a, pattern, method) - 2 * demosaic(b, pattern, method), rtol=1e-9,
                               atol=1e-9)


@pytest.mark.parametrize("pattern", PATTERNS)
def test_constant_image_everywhere_with_mirror_border(pattern):
    cfa = np.full((9, 12), 7.25)
    for method in OURS:
        np.testing.assert_allclose(demosaic(cfa, pattern, method, border="mirror"), 7.25, rtol=1e-14)
    # Malvar's filters sum to one, so even colour-demosaicing's reflection keeps a constant
    np.testing.assert_allclose(demosaic(cfa, pattern, border="reflect"), 7.25, rtol=1e-14)
    # colour's bilinear with that reflection over-weights R/B on the outermost rows/columns (documented)
    assert demosaic(cfa, pattern, "bilinear").max() > 7.25 * 1.4


def test_mirror_border_only_changes_the_outer_two_pixels():
    cfa = _hdr_cfa((20, 24), seed=4, dtype=np.float64)
    a = demosaic(cfa, "RGGB", border="reflect")
    b = demosaic(cfa, "RGGB", border="mirror")
    np.testing.assert_array_equal(a[2:-2, 2:-2], b[2:-2, 2:-2])
    assert not np.allclose(a, b)


# ----------------------------------------------------------------------------- bad input


def test_unknown_method_lists_the_valid_ones():
    with pytest.raises(ValueError, match="valid methods: bilinear, malvar2004"):
        demosaic(np.zeros((4, 4)), method="vng")
    assert set(DEMOSAICING_METHODS) == {"bilinear", "malvar2004"}
    assert demosaic(np.ones((4, 4)), method="Malvar2004").shape == (4, 4, 3)


@pytest.mark.parametrize("bad, match", [
    (dict(pattern="RGBG"), "unknown Bayer pattern 'RGBG'"),
    (dict(border="wrap"), "unknown border"),
    (dict(cfa=np.zeros(5)), r"must be \(\.\.\., H, W\)"),
    (dict(cfa=np.zeros((2, 8))), "at least 3x3"),
])
def test_bad_arguments(bad, match):
    kw = dict(cfa=np.zeros((6, 6)), pattern="RGGB")
    kw.update(bad)
    with pytest.raises(ValueError, match=match):
        demosaic(**kw)


def test_nan_is_reported_with_its_index():
    cfa = np.ones((2, 6, 8), dtype=np.float32)
    cfa[1, 4, 5] = np.inf
    with pytest.raises(ValueError, match=r"first at index \(1, 4, 5\)"):
        demosaic(cfa)


@pytest.mark.parametrize("method", sorted(OURS))
def test_check_finite_false_skips_the_scan_for_a_caller_that_made_sure(method):
    """The view chain checks a view's frames once and demosaics its merges with ``check_finite=False``:
    the same result on finite input, and no scan (an Inf passes through to the output, not an error)."""
    cfa = _hdr_cfa((2, 6, 8), 3, np.float32)
    np.testing.assert_array_equal(demosaic(cfa, method=method, check_finite=False), demosaic(cfa, method=method))
    cfa[1, 4, 5] = np.inf
    assert not np.isfinite(demosaic(cfa, method=method, check_finite=False)[1]).all()


# ----------------------------------------------------------------------------- quality against OpenCV


def _srgb_to_linear(u8: np.ndarray) -> np.ndarray:
    v = u8.astype(np.float64) / 255.0
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _psnr(est: np.ndarray, truth: np.ndarray, crop: int = 0) -> float:
    if crop:
        est, truth = est[crop:-crop, crop:-crop], truth[crop:-crop, crop:-crop]
    return float(10 * np.log10(truth.max() ** 2 / np.mean((est - truth) ** 2)))


def _opencv_ea(cfa: np.ndarray, code: int) -> np.ndarray:
    """OpenCV's edge-aware demosaic on the mosaic quantised to 16 bits (full scale = the mosaic's maximum)."""
    scale = 65535.0 / cfa.max()
    raw = np.round(cfa * scale).astype(np.uint16)
    return cv2.cvtColor(raw, code).astype(np.float64) / scale


@pytest.fixture(scope="module")
def images():
    """Natural photographs shipped inside scikit-image (no download), decoded to linear radiance."""
    import skimage.data

    astronaut = _srgb_to_linear(skimage.data.astronaut())
    return {
        "astronaut": astronaut,
        "astronaut x1000 (HDR)": 1000.0 * astronaut,
        "coffee": _srgb_to_linear(skimage.data.coffee()),
        "chelsea": _srgb_to_linear(skimage.data.chelsea()),
    }


def test_opencv_code_per_layout_found_empirically(images):
    """The OpenCV code whose result is closest to the truth is the one in OPENCV_EA, for every layout."""
    truth = images["astronaut"][:256, :256]
    candidates = {name: getattr(cv2, f"COLOR_Bayer{name}2RGB_EA") for name in ("BG", "GB", "RG", "GR")}
    for pattern in PATTERNS:
        cfa = mosaic(truth, pattern)
        scores = {name: _psnr(_opencv_ea(cfa, code), truth, crop=2) for name, code in candidates.items()}
        best = max(scores, key=scores.get)
        assert candidates[best] == OPENCV_EA[pattern], (pattern, scores)
        assert getattr(cv2, f"COLOR_Bayer{pattern}2RGB_EA") == OPENCV_EA[pattern]   # OpenCV 5 alias


def test_psnr_at_least_opencv_edge_aware(images):
    print("\nPSNR dB against ground truth (whole image / 2-px border cropped)")
    print(f"  {'image':24s} {'layout':6s} {'malvar2004':>15s} {'bilinear':>15s} {'OpenCV EA 16-bit':>17s}")
    for name, truth in images.items():
        for pattern in PATTERNS:
            cfa = mosaic(truth, pattern)
            ours = {m: demosaic(cfa, pattern, m) for m in ("malvar2004", "bilinear")}
            cv = _opencv_ea(cfa, OPENCV_EA[pattern])
            p = {k: (_psnr(v, truth), _psnr(v, truth, crop=2)) for k, v in ours.items()}
            p_cv = (_psnr(cv, truth), _psnr(cv, truth, crop=2))
            print(f"  {name:24s} {pattern:6s} " + " ".join(f"{a:7.2f}/{b:7.2f}" for a, b in p.values())
                  + f"  {p_cv[0]:7.2f}/{p_cv[1]:7.2f}")
            assert p["malvar2004"][0] >= p_cv[0], (name, pattern)
            assert p["malvar2004"][1] >= p_cv[1], (name, pattern)
    # HDR scale does not change PSNR (linear method, peak-relative PSNR)
    t = images["astronaut"]
    assert abs(_psnr(demosaic(mosaic(1000 * t, "RGGB")), 1000 * t) - _psnr(demosaic(mosaic(t, "RGGB")), t)) < 1e-6


# ----------------------------------------------------------------------------- chunking and buffers


def test_out_buffer_is_filled_and_returned():
    cfa = _hdr_cfa((2, 10, 12), seed=10, dtype=np.float32)
    buf = np.full((2, 10, 12, 3), np.nan, dtype=np.float32)
    res = demosaic(cfa, "BGGR", out=buf)
    assert res is buf
    np.testing.assert_array_equal(buf, demosaic(cfa, "BGGR"))
    with pytest.raises(ValueError, match="out must be a float32 array of shape"):
        demosaic(cfa, "BGGR", out=np.empty((2, 10, 12, 3)))
    strided = np.empty((2, 10, 12, 6), dtype=np.float32)[..., ::2]       # a strided view works in place
    assert demosaic(cfa, "BGGR", out=strided) is strided
    np.testing.assert_array_equal(strided, buf)
    batch = _hdr_cfa((2, 3, 10, 12), seed=11, dtype=np.float32)
    swapped = np.empty((3, 2, 10, 12, 3), dtype=np.float32).transpose(1, 0, 2, 3, 4)
    with pytest.raises(ValueError, match="without a copy"):     # the batch axes cannot be merged in place
        demosaic(batch, "BGGR", out=swapped)
