"""The CUDA paths (ALS, super-resolution) agree with the CPU ones.

Skipped where torch sees no CUDA device (the project's CI and laptops); run on a lent GPU with
``python3 -m pytest --noconftest tests/btfcore/test_cuda.py`` (btfcore needs only numpy, scipy,
OpenCV and torch there). The figures measured on such a device are in docs/benchmarks.md.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from btfcore.model.als import als_basis, relative_error_weights
from btfcore.superres.espcn import Espcn, EspcnConfig, load_espcn, upscale
from btfcore.superres.training import TrainingSettings, patch_pairs, train_espcn

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(),
                                reason="no CUDA device: these tests run where a GPU is lent")


def _positive(n_lv: int, n_tx: int, c: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    D = np.exp(rng.normal(0, 1.0, (n_lv, c))) @ rng.uniform(0.05, 1.0, (c, n_tx))
    return D * (1 + 0.05 * rng.standard_normal(D.shape))


@pytest.mark.parametrize("dtype, rtol", [(np.float64, 1e-9), (np.float32, 2e-3)])
def test_als_on_cuda_equals_the_numpy_reference(dtype, rtol):
    D = _positive(300, 2000, 8, seed=3).astype(dtype)
    a = als_basis(D, 6, n_iter=5, tol=0.0, backend="numpy")
    b = als_basis(D, 6, n_iter=5, tol=0.0, backend="torch")          # the default device: CUDA here
    assert b.device.startswith("cuda") and b.U.dtype == dtype
    np.testing.assert_allclose(b.objective, a.objective, rtol=rtol)
    np.testing.assert_allclose(b.U * b.sigma @ b.V, a.U * a.sigma @ a.V, rtol=rtol, atol=rtol * np.abs(D).max())


def test_als_on_cuda_takes_the_ridge_of_singular_systems():
    D = _positive(300, 2000, 3, seed=0)
    W = relative_error_weights(D)
    W[:, 5] = 0.0                                              # texel 5's normal matrix is zero
    r = als_basis(D, 5, W, n_iter=20, backend="torch", device="cuda")   # c = 5 above the rank 3
    assert np.isfinite(r.U).all() and np.isfinite(r.V).all()
    np.testing.assert_array_equal(r.V[:, 5], 0.0)


def test_upscale_on_cuda_equals_the_cpu():
    torch.manual_seed(0)
    model = Espcn(EspcnConfig(normalisation="scale")).eval()
    images = np.exp(np.random.default_rng(2).normal(-3, 1, (5, 23, 17))).astype(np.float32)
    cpu = upscale(model, images)
    gpu = upscale(model, images, device="cuda")
    assert next(model.parameters()).device.type == "cpu"                # the caller's model is left on the CPU
    # cuDNN convolves in TF32 by default (torch.backends.cudnn.allow_tf32; 10-bit mantissa): measured on an
    # H200, 5.5e-5 of the largest value apart, where float32 on both sides agrees to 1e-5
    np.testing.assert_allclose(gpu, cpu, rtol=1e-3, atol=2e-4 * np.abs(cpu).max())


def test_training_on_cuda_learns():
    rng = np.random.default_rng(1)
    high = np.exp(rng.normal(-3, 0.5, (8, 68, 68))).astype(np.float32)
    low = high.reshape(8, 34, 2, 34, 2).mean(axis=(2, 4))
    config = EspcnConfig(features=(16, 8, 8))
    result = train_espcn(*patch_pairs(low, high), config, TrainingSettings(max_epochs=3, batch_size=16, patience=3),
                         device="cuda")
    assert all(t.device.type == "cpu" for t in result.state.values())    # a state that loads anywhere
    assert np.isfinite(result.best_validation_loss)
    assert result.history[-1].train_loss < result.history[0].train_loss
    assert upscale(load_espcn(result.state, config), low[:1]).shape == (1, 68, 68)
