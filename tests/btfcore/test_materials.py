"""Tests of btfcore.simulate.materials (procedural material maps)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from btfcore.simulate.materials import (
    MATERIAL_CLASSES,
    SOURCE_NAMES,
    MaterialMaps,
    flat_material,
    make_material,
    white_standard,
)

SHAPE = (64, 64)
SEEDS = (0, 1, 2)




@pytest.fixture(scope="module")
def grey_sources(sources) -> dict[str, np.ndarray]:
    return {k: sources[k] for k in ("brick", "grass", "gravel")}


def _assert_plain_json(obj, where="params"):
    if isinstance(obj, dict):
        for k, v in obj.items():
            assert type(k) is str, f"{where}: key {k!r} is {type(k)}"
            _assert_plain_json(v, f"{where}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            _assert_plain_json(v, f"{where}[{i}]")
    else:
        assert type(obj) in (str, int, float, bool) or obj is None, f"{where} is {type(obj)}"
        if type(obj) is float:
            assert np.isfinite(obj), where


def test_source_names():
    assert set(SOURCE_NAMES) == {"brick", "grass", "gravel", "bricks_rgb", "wood_rgb"}


@pytest.mark.parametrize("class_name", MATERIAL_CLASSES)
def test_maps_valid_and_vary_by_seed(class_name, sources):
    mats = [make_material(class_name, s, SHAPE, sources) for s in SEEDS]
    for m in mats:
        assert m.class_name == class_name
        assert m.height.shape == SHAPE and m.height.dtype == np.float32
        assert m.albedo.shape == SHAPE + (3,) and m.albedo.dtype == np.float32
        assert m.roughness.shape == SHAPE and m.specular.shape == SHAPE
        assert m.f0.shape == (3,) and m.f0.dtype == np.float32
        for arr in (m.height, m.albedo, m.roughness, m.specular, m.f0):
            assert np.all(np.isfinite(arr))
        assert m.height.min() == 0.0 and m.height.max() > 0.0
        assert 0.0 <= m.albedo.min() and m.albedo.max() <= 1.0
        assert 0.0 < m.roughness.min() and m.roughness.max() <= 1.0
        assert m.specular.min() >= 0.0
        assert m.albedo.std() > 0.0  # spatially varying
        _assert_plain_json(m.params)
        assert json.loads(json.dumps(m.params)) == m.params
        assert m.params["seed"] in SEEDS
    for a in range(3):
        for b in range(a + 1, 3):
            assert mats[a].params != mats[b].params
            assert not np.array_equal(mats[a].height, mats[b].height)
            assert not np.array_equal(mats[a].albedo, mats[b].albedo)


@pytest.mark.parametrize("class_name", MATERIAL_CLASSES)
def test_same_seed_bit_identical(class_name, sources):
    a = make_material(class_name, 7, SHAPE, sources)
    b = make_material(class_name, 7, SHAPE, sources)
    for name in ("height", "albedo", "roughness", "specular", "f0"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.params == b.params


def _relief_side(m: MaterialMaps) -> float:
    return float(m.height.max()) / m.height.shape[1]


def _median_over_seeds(class_name, sources, fn, seeds=range(6)):
    return float(np.median([fn(make_material(class_name, s, SHAPE, sources)) for s in seeds]))


def test_class_character(sources):
    """Relief, gloss and colour ranks that define the classes."""
    relief = {c: _median_over_seeds(c, sources, _relief_side) for c in MATERIAL_CLASSES}
    rough = {c: _median_over_seeds(c, sources, lambda m: float(m.roughness.mean())) for c in MATERIAL_CLASSES}
    # specular reflectance at normal incidence: lobe weight x Fresnel f0
    spec = {c: _median_over_seeds(c, sources, lambda m: float(m.specular.mean() * m.f0.mean()))
            for c in MATERIAL_CLASSES}
    # stone and carpet are the deep ones, wood and metal nearly flat
    for deep in ("stone", "carpet"):
        for flat in ("wood", "metal", "leather"):
            assert relief[deep] > 3 * relief[flat], (deep, flat, relief)
    assert relief["wood"] < 0.002 and relief["metal"] < 0.004
    assert 0.015 < relief["stone"] < 0.06
    # metal and varnished wood are the smoothest, metal the most specular;
    # finished leather has a sheen; stone/carpet/cloth are rough
    assert max(rough["metal"], rough["wood"]) < rough["leather"] < min(rough["stone"], rough["carpet"], rough["cloth"])
    assert 0.03 <= rough["metal"] <= 0.3 and 0.1 <= rough["leather"] <= 0.4
    assert spec["metal"] > spec["wood"] > max(spec["stone"], spec["carpet"], spec["cloth"])
    for s in range(3):
        metal = make_material("metal", s, SHAPE, sources)
        assert metal.f0.max() > 0.5 and metal.albedo.mean() < 0.1  # coloured mirror, dark diffuse
        stone = make_material("stone", s, SHAPE, sources)
        np.testing.assert_allclose(stone.f0, 0.04, rtol=1e-6)


def test_rgb_fallback_recorded(sources, grey_sources):
    with_rgb = make_material("wood", 3, SHAPE, sources)
    without = make_material("wood", 3, SHAPE, grey_sources)
    assert with_rgb.params["rgb_fallback"] is False and with_rgb.params["source"] == "wood_rgb"
    assert without.params["rgb_fallback"] is True and without.params["source"] == "grass"
    # the colourised grey source is still wood-toned: red > green > blue on average
    mean = without.albedo.reshape(-1, 3).mean(axis=0)
    assert mean[0] > mean[1] > mean[2]
    for s in range(6):  # stone from "brick" without bricks_rgb is a fallback too
        m = make_material("stone", s, SHAPE, grey_sources)
        assert m.params["rgb_fallback"] is (m.params["source"] == "brick")


def test_geometry_is_resolution_independent(sources):
    """Relief drawn in side units: 2x maps describe the same surface."""
    for c in MATERIAL_CLASSES:
        lo = make_material(c, 5, (48, 48), sources)
        hi = make_material(c, 5, (96, 96), sources)
        p_lo = {k: v for k, v in lo.params.items() if k not in ("shape",)}
        p_hi = {k: v for k, v in hi.params.items() if k not in ("shape",)}
        assert p_lo == p_hi, c
        assert hi.albedo.mean() == pytest.approx(lo.albedo.mean(), rel=0.05), c
        if c != "cloth":  # a 1.5-pixel thread period averages the weave's relief away
            assert hi.height.std() / 96 == pytest.approx(lo.height.std() / 48, rel=0.15), c


def test_white_standard_and_flat():
    w = white_standard((8, 10))
    assert w.shape == (8, 10)
    assert np.all(w.height == 0) and np.all(w.specular == 0)
    np.testing.assert_array_equal(w.albedo, np.float32(0.99))
    f = flat_material((4, 4), albedo=(0.2, 0.4, 0.6), roughness=0.5, specular=0.3)
    np.testing.assert_array_equal(f.albedo[2, 3], np.float32([0.2, 0.4, 0.6]))
    assert np.all(f.roughness == np.float32(0.5)) and np.all(f.specular == np.float32(0.3))
    _assert_plain_json(w.params)
    _assert_plain_json(f.params)


def test_bad_input(sources, grey_sources):
    with pytest.raises(ValueError, match="unknown material class"):
        make_material("velvet", 0, SHAPE, sources)
    with pytest.raises(KeyError, match="gravel"):
        make_material("metal", 0, SHAPE, {"grass": sources["grass"]})
    with pytest.raises(ValueError, match="greyscale"):
        make_material("carpet", 0, SHAPE, {"grass": sources["wood_rgb"]})
    with pytest.raises(ValueError, match="shape"):
        make_material("stone", 0, (1, 8), sources)
    with pytest.raises(ValueError, match="albedo"):
        flat_material((4, 4), albedo=(1.5, 0.0, 0.0))
    with pytest.raises(ValueError, match="roughness"):
        flat_material((4, 4), roughness=0.0)
    bad = np.zeros((4, 4), np.float32)
    with pytest.raises(ValueError, match="float32"):
        MaterialMaps("x", bad.astype(np.float64), np.zeros((4, 4, 3), np.float32), bad + 0.5, bad, np.zeros(3, np.float32), {})
    with pytest.raises(ValueError, match="NaN"):
        MaterialMaps("x", bad + np.nan, np.zeros((4, 4, 3), np.float32), bad + 0.5, bad, np.zeros(3, np.float32), {})
