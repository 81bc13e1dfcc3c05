"""The ESPCN of the SR paper §4.2: shapes, the functional twin, gradients, normalisation."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from btfcore.superres.espcn import (
    Espcn, EspcnConfig, conv_flops, denormalise, espcn_functional, load_espcn, normalise,
    state_dict_problems, upscale, upscale_rgb,
)


def _trained_like(config: EspcnConfig, seed: int = 0, dtype=torch.float32) -> Espcn:
    """A model with non-trivial batch-norm statistics and affine parameters, in eval mode."""
    torch.manual_seed(seed)
    model = Espcn(config).to(dtype)
    with torch.no_grad():
        model.train()
        model(torch.randn(4, 1, 12, 12, dtype=dtype) * 2 + 1)
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.weight.uniform_(0.5, 2.0)
                m.bias.normal_()
    return model.eval()


def _hdr(rng: np.random.Generator, shape) -> np.ndarray:
    return np.exp(rng.standard_normal(shape) * 1.5).astype(np.float32) * 3e-3


@pytest.mark.parametrize("scale", [2, 3])
@pytest.mark.parametrize("hw", [(3, 3), (17, 17), (20, 33)])
def test_output_shapes(scale, hw):
    model = Espcn(EspcnConfig(scale=scale, features=(8, 4, 4)))
    h, w = hw
    assert model(torch.randn(2, 1, h, w)).shape == (2, 1, scale * h, scale * w)
    images = _hdr(np.random.default_rng(0), (3, h, w))
    sr = upscale(model, images)
    assert sr.shape == (3, scale * h, scale * w) and sr.dtype == np.float32
    rgb = upscale_rgb(model, _hdr(np.random.default_rng(1), (2, h, w, 3)))
    assert rgb.shape == (2, scale * h, scale * w, 3) and rgb.dtype == np.float32


def test_default_config_is_the_papers():
    c = EspcnConfig()
    assert (c.scale, c.features, c.kernels, c.batch_norm) == (2, (64, 32, 32), (5, 3, 3, 3), True)
    model = Espcn(c)
    assert model.conv4.in_channels == 96 and model.conv4.out_channels == 4
    assert conv_flops(c, 1) == 2 * (25 * 64 + 64 * 32 * 9 + 32 * 32 * 9 + 96 * 4 * 9)
    assert EspcnConfig.from_json(json.loads(json.dumps(c.to_json()))) == c


@pytest.mark.parametrize("padding", ["reflect", "zeros", "replicate"])
@pytest.mark.parametrize("batch_norm", [True, False])
def test_functional_twin_equals_module(padding, batch_norm):
    config = EspcnConfig(padding=padding, batch_norm=batch_norm)
    model = _trained_like(config)
    x = torch.randn(3, 1, 19, 22)
    with torch.no_grad():
        y_module = model(x)
        y_twin = espcn_functional(model.state_dict(), x, config)
    # float32: the twin folds batch norm into the convolutions, so only rounding differs
    torch.testing.assert_close(y_twin, y_module, rtol=1e-5, atol=1e-5)
    m64 = _trained_like(config, dtype=torch.float64)
    x64 = x.double()
    with torch.no_grad():
        torch.testing.assert_close(espcn_functional(m64.state_dict(), x64, config), m64(x64),
                                   rtol=1e-12, atol=1e-12)


def test_upscale_matches_the_module_and_any_batch():
    model = _trained_like(EspcnConfig(normalisation="scale"))
    images = _hdr(np.random.default_rng(2), (5, 11, 13))
    y, stats = normalise(images, "scale")
    with torch.no_grad():
        expected = denormalise(model(torch.from_numpy(y)[:, None])[:, 0].numpy(), stats, "scale")
    np.testing.assert_allclose(upscale(model, images), expected, rtol=1e-4, atol=1e-5 * np.abs(expected).max())
    # the batch changes the GEMMs' blocking, hence the rounding, nothing else
    np.testing.assert_allclose(upscale(model, images, batch=2), upscale(model, images, batch=1),
                               rtol=1e-5, atol=1e-6 * np.abs(expected).max())
    assert not model.training


def test_gradcheck_tiny_instance():
    torch.manual_seed(0)
    model = Espcn(EspcnConfig(features=(3, 2, 2), kernels=(3, 3, 3, 3))).double()
    x = torch.randn(2, 1, 5, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(model, (x,), eps=1e-6, atol=1e-5)
    model.eval()
    assert torch.autograd.gradcheck(model, (x,), eps=1e-6, atol=1e-5)


@pytest.mark.parametrize("method", ["log", "scale"])
def test_normalise_round_trip(method):
    rng = np.random.default_rng(3)
    images = _hdr(rng, (4, 9, 10))
    images[1] = 0.0                                     # a dark image keeps a finite scale
    y, stats = normalise(images, method)
    assert y.dtype == np.float32 and np.isfinite(y).all()
    np.testing.assert_allclose(denormalise(y, stats, method), images, rtol=1e-5, atol=1e-9)
    if method == "log":
        np.testing.assert_allclose(y[[0, 2, 3]].mean(axis=(1, 2)), 0.0, atol=1e-5)
    # the HR partner is normalised with the LR image's statistics, at any size
    high = np.repeat(np.repeat(images, 2, axis=1), 2, axis=2)
    y_high, same = normalise(high, method, stats)
    assert same is stats
    np.testing.assert_allclose(y_high[:, ::2, ::2], y, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(denormalise(y_high, stats, method), high, rtol=1e-5, atol=1e-9)


def test_normalise_bad_inputs():
    images = np.ones((3, 4, 4), np.float32)
    images[2, 1, 1] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf in 1 image.*index 2"):
        normalise(images, "log")
    with pytest.raises(ValueError, match="normalisation must be one of"):
        normalise(np.ones((1, 4, 4)), "gamma")
    _, stats = normalise(np.ones((2, 4, 4)), "log")
    with pytest.raises(ValueError, match="computed for normalisation 'log'"):
        denormalise(np.ones((2, 4, 4)), stats, "scale")
    with pytest.raises(ValueError, match="stats are of 2 images but there are 3"):
        normalise(np.ones((3, 4, 4)), "log", stats)


def test_bad_configs_and_inputs():
    with pytest.raises(ValueError, match="scale must be an int >= 2"):
        EspcnConfig(scale=1)
    with pytest.raises(ValueError, match="scale must be an int >= 2"):
        EspcnConfig(scale=2.0)
    with pytest.raises(ValueError, match="kernels must be 4 odd"):
        EspcnConfig(kernels=(5, 3, 3, 2))
    with pytest.raises(ValueError, match=r"unknown EspcnConfig key\(s\) \['depth'\]"):
        EspcnConfig.from_json({**EspcnConfig().to_json(), "depth": 5})
    model = Espcn(EspcnConfig(features=(4, 2, 2)))
    with pytest.raises(ValueError, match=r"got a 3-D shape \(2, 8, 8\).*x\[:, None\]"):
        model(torch.zeros(2, 8, 8))
    with pytest.raises(ValueError, match="must have 1 channel.*got 3"):
        model(torch.zeros(2, 3, 8, 8))
    with pytest.raises(ValueError, match="smaller than the 3 x 3"):
        model(torch.zeros(1, 1, 2, 8))
    with pytest.raises(ValueError, match=r"must be \(n, H, W\)"):
        upscale(model, np.zeros((2, 8, 8, 3), np.float32))
    with pytest.raises(ValueError, match=r"must be \(n, H, W, C\)"):
        upscale_rgb(model, np.zeros((2, 8, 8), np.float32))


def test_state_of_another_architecture_is_refused():
    state = Espcn(EspcnConfig(scale=3)).state_dict()
    rng_before = torch.random.get_rng_state()
    problems = state_dict_problems(state, EspcnConfig(scale=2))
    assert torch.equal(torch.random.get_rng_state(), rng_before)
    assert problems == ["conv4.bias has shape (9,), the configuration needs (4,)",
                        "conv4.weight has shape (9, 96, 3, 3), the configuration needs (4, 96, 3, 3)"]
    with pytest.raises(ValueError, match="conv4.weight has shape"):
        load_espcn(state, EspcnConfig())
    no_bn = Espcn(EspcnConfig(batch_norm=False)).state_dict()
    with pytest.raises(ValueError, match=r"missing \['bn1.bias'"):
        espcn_functional(no_bn, torch.zeros(1, 1, 8, 8), EspcnConfig())
    good = _trained_like(EspcnConfig())
    assert not load_espcn(good.state_dict(), EspcnConfig()).training
