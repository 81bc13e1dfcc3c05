"""Training the SR paper's ESPCN (§5.2.2): patch pairs, convergence, reproducibility, stopping."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from scipy import ndimage

from btfcore.superres.espcn import EspcnConfig, load_espcn, normalise, upscale
from btfcore.superres.training import TrainingSettings, patch_pairs, train_espcn


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """One thread, as on a Dask worker: tiny batches on contended cores stall two threads."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _smooth_hdr(rng: np.random.Generator, n: int, size: int, sigma: float = 1.5) -> np.ndarray:
    """Smooth random log-normal radiance images (n, size, size)."""
    g = np.stack([ndimage.gaussian_filter(rng.standard_normal((size, size)), sigma, mode="wrap")
                  for _ in range(n)])
    return (np.exp(g / g.std()) * 0.02).astype(np.float32)


def _block_mean(images: np.ndarray, f: int = 2) -> np.ndarray:
    n, h, w = images.shape
    return images.reshape(n, h // f, f, w // f, f).mean(axis=(2, 4))


def test_patch_pairs_counts_and_alignment():
    rng = np.random.default_rng(0)
    high = _smooth_hdr(rng, 3, 76)[:, :75, :73]                      # odd rows/columns: dropped
    low = _block_mean(high[:, :74, :72])                            # (3, 37, 36)
    for method in ("log", "scale"):
        lp, hp = patch_pairs(low, high, normalisation=method)
        assert lp.shape == (3 * 2 * 2, 17, 17) and hp.shape == (12, 34, 34)
        assert lp.dtype == hp.dtype == np.float32
        # tile (image 1, row 1, column 0) is pair 1 * 4 + 1 * 2 + 0, normalised with the LR stats
        lo_n, stats = normalise(low, method)
        hi_n, _ = normalise(high[:, :74, :72], method, stats)
        np.testing.assert_array_equal(lp[6], lo_n[1, 17:34, 0:17])
        np.testing.assert_array_equal(hp[6], hi_n[1, 34:68, 0:34])
    # with the 'scale' normalisation (linear), an HR tile's block mean is its LR tile
    lp, hp = patch_pairs(low, high, normalisation="scale")
    np.testing.assert_allclose(_block_mean(hp), lp, rtol=1e-5, atol=1e-6)


def test_patch_pairs_bad_inputs():
    low, high = np.ones((2, 20, 20), np.float32), np.ones((2, 40, 40), np.float32)
    with pytest.raises(ValueError, match="2 low-resolution but 1 high-resolution"):
        patch_pairs(low, high[:1])
    with pytest.raises(ValueError, match="40 x 38 do not match low-resolution images of 20 x 20"):
        patch_pairs(low, high[:, :, :38])
    lp, hp = patch_pairs(low[:, :16], high[:, :32])                   # no full tile: none
    assert lp.shape == (0, 17, 17) and hp.shape == (0, 34, 34)
    with pytest.raises(ValueError, match="0 patch pair"):
        train_espcn(lp, hp, EspcnConfig(), _tiny_settings())
    bad = low.copy()
    bad[1, 3, 3] = np.nan
    with pytest.raises(ValueError, match="low-resolution images hold NaN or Inf.*index 1"):
        patch_pairs(bad, high)


def _tiny_settings(**kw) -> TrainingSettings:
    return TrainingSettings(**{"max_epochs": 12, "batch_size": 16, "patience": 12, **kw})


def test_training_beats_bicubic_on_held_out_images():
    rng = np.random.default_rng(1)
    high = _smooth_hdr(rng, 16, 68)
    high_test = _smooth_hdr(rng, 4, 68)
    low, low_test = _block_mean(high), _block_mean(high_test)
    config = EspcnConfig(normalisation="log")          # noise-free smooth images: log measured better here
    records = []
    result = train_espcn(*patch_pairs(low, high, normalisation="log"), config, _tiny_settings(batch_size=8),
                         progress=lambda epoch, record: records.append((epoch, record)))
    assert [e for e, _ in records] == list(range(1, len(result.history) + 1))
    assert result.history[result.best_epoch - 1].validation_loss == result.best_validation_loss
    assert result.samples_per_second > 0 and result.n_train + result.n_validation == 64
    json.dumps(result.provenance())
    sr = upscale(load_espcn(result.state, config), low_test)
    bicubic = np.stack([cv2.resize(im, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC) for im in low_test])
    mse_sr, mse_bicubic = np.mean((sr - high_test) ** 2), np.mean((bicubic - high_test) ** 2)
    assert mse_sr < 0.8 * mse_bicubic, (mse_sr, mse_bicubic)


def test_same_seed_gives_identical_weights():
    rng = np.random.default_rng(2)
    high = _smooth_hdr(rng, 4, 68)
    pairs = patch_pairs(_block_mean(high), high)
    config = EspcnConfig(features=(16, 8, 8))
    settings = _tiny_settings(max_epochs=2)
    before = torch.random.get_rng_state()
    a, b = (train_espcn(*pairs, config, settings) for _ in range(2))
    assert torch.equal(torch.random.get_rng_state(), before)        # the caller's RNG is untouched
    assert a.state.keys() == b.state.keys()
    assert all(torch.equal(a.state[k], b.state[k]) for k in a.state)
    assert [r.validation_loss for r in a.history] == [r.validation_loss for r in b.history]
    c = train_espcn(*pairs, config, _tiny_settings(max_epochs=2, seed=1))
    assert not torch.equal(a.state["conv1.weight"], c.state["conv1.weight"])


def test_early_stopping_when_validation_stalls():
    rng = np.random.default_rng(3)
    low = rng.standard_normal((40, 9, 9)).astype(np.float32)         # HR unrelated to LR: nothing to learn
    high = rng.standard_normal((40, 18, 18)).astype(np.float32)
    settings = _tiny_settings(max_epochs=60, patience=3, schedule="constant")
    result = train_espcn(low, high, EspcnConfig(features=(8, 4, 4)), settings)
    assert result.stopped_early and len(result.history) < 60
    assert len(result.history) == result.best_epoch + 3


def test_training_bad_inputs():
    config, settings = EspcnConfig(), _tiny_settings()
    low, high = np.zeros((4, 17, 17), np.float32), np.zeros((4, 34, 34), np.float32)
    with pytest.raises(ValueError, match="0 patch pair"):
        train_espcn(low[:0], high[:0], config, settings)
    with pytest.raises(ValueError, match="4 low-resolution but 3 high-resolution patches"):
        train_espcn(low, high[:3], config, settings)
    with pytest.raises(ValueError, match="high-resolution patches of 34 x 34 do not match .* 16 x 17 at scale 2"):
        train_espcn(low[:, :16], high, config, settings)
    bad = high.copy()
    bad[2, 0, 0] = np.inf
    with pytest.raises(ValueError, match="high-resolution patches hold NaN or Inf.*index 2"):
        train_espcn(low, bad, config, settings)
    with pytest.raises(ValueError, match="schedule must be one of"):
        TrainingSettings(schedule="step")
    with pytest.raises(ValueError, match=r"unknown TrainingSettings key\(s\) \['momentum'\]"):
        TrainingSettings.from_json({"momentum": 0.9})
    assert TrainingSettings.from_json(json.loads(json.dumps(settings.to_json()))) == settings
