"""Tests of btfcore.render.btf_render (BTF renderings on a sphere, a cylinder and a plane)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from btfcore.render.btf_render import (
    BTFLookup,
    Camera,
    DirectionalLight,
    EnvLights,
    PointLight,
    env_directions,
    env_lights,
    render_btf,
    surface_geometry,
    to_srgb8,
)
from btfcore.capture.resample import lv_product, resample_weights
from btfcore.dome import get_device

ALBEDO = np.array([0.6, 0.4, 0.2])


def _fibonacci(n: int) -> np.ndarray:
    """``n`` near-uniform directions on the upper hemisphere."""
    k = np.arange(n) + 0.5
    z = 1.0 - k / n
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _ring(n: int, theta_deg: float) -> np.ndarray:
    a = 2 * math.pi * np.arange(n) / n
    t = math.radians(theta_deg)
    return np.stack([math.sin(t) * np.cos(a), math.sin(t) * np.sin(a), np.full(n, math.cos(t))], axis=1)


@pytest.fixture(scope="module")
def lambertian() -> BTFLookup:
    """Lambertian BTF ``albedo cos(theta_i) / pi`` (docs/btf-store.md) on a dense product sampling
    whose light hull reaches the horizon (400 directions + a ring at 90 deg)."""
    lights = np.concatenate([_fibonacci(400), _ring(36, 90.0)])
    views = np.concatenate([[[0.0, 0.0, 1.0]], _ring(6, 40.0), _ring(8, 70.0), _ring(8, 90.0)])
    L, V = lv_product(lights, views)
    B = (L[:, 2, None] * ALBEDO / math.pi)[:, None, None, :] * np.ones((1, 4, 4, 1))
    return BTFLookup(B.astype(np.float32), L, V)


# --------------------------------------------------------------------------- point light


@pytest.mark.parametrize("shape,kind", [("sphere", "orthographic"), ("sphere", "perspective"),
                                        ("cylinder", "orthographic")])
def test_lambertian_point_light_matches_analytic_shading(lambertian, shape, kind):
    light = PointLight((2.0, 2.0, 4.0), (24.0, 24.0, 24.0))
    geo = surface_geometry(shape, Camera((96, 96), kind=kind), tiles=1.0, texture_shape=(4, 4))
    image = render_btf(lambertian, geo, light)
    to = np.asarray(light.position) - geo.position
    r2 = np.einsum("ij,ij->i", to, to)
    cos = np.einsum("ij,ij->i", to / np.sqrt(r2)[:, None], geo.normal)
    ref = ALBEDO / math.pi * np.clip(cos, 0, None)[:, None] * 24.0 / r2[:, None]   # (a / pi) cos I / r^2
    got = image.reshape(-1, 3)[geo.pixel]
    assert np.abs(got - ref).max() <= 0.01 * ref.max()
    lit = cos > 0.2
    assert np.all(np.abs(got - ref)[lit] <= 0.015 * ref[lit])
    assert np.all(image[~geo.mask] == 0)


def test_sphere_geometry_frame_is_orthonormal_and_right_handed():
    geo = surface_geometry("sphere", Camera((32, 32)), tiles=2.0, texture_shape=(8, 8))
    frame = np.stack([geo.tangent, geo.bitangent, geo.normal], axis=1)        # (n, 3, 3)
    np.testing.assert_allclose(frame @ frame.transpose(0, 2, 1), np.broadcast_to(np.eye(3), frame.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(frame), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(geo.position, axis=1), 1.0, atol=1e-12)
    # disc of radius 1 in an orthographic view of half-width 1.1
    assert geo.mask.sum() == pytest.approx(math.pi / 4 / 1.1**2 * 32 * 32, rel=0.05)


# --------------------------------------------------------------------------- plane, nadir


@pytest.mark.parametrize("spatial", ["nearest", "bilinear"])
def test_plane_head_on_reproduces_the_nadir_texture(spatial):
    rng = np.random.default_rng(3)
    lights = np.concatenate([[[0.0, 0.0, 1.0]], _ring(5, 30.0)])
    views = np.concatenate([[[0.0, 0.0, 1.0]], _ring(4, 45.0)])
    L, V = lv_product(lights, views)
    B = rng.random((len(L), 8, 8, 3)).astype(np.float32)
    nadir = int(np.flatnonzero((L[:, 2] > 1 - 1e-12) & (V[:, 2] > 1 - 1e-12))[0])
    lookup = BTFLookup(B, L, V, spatial=spatial)
    geo = surface_geometry("plane", Camera((8, 8), extent=1.0), tiles=1.0, texture_shape=(8, 8))
    image = render_btf(lookup, geo, DirectionalLight((0.0, 0.0, 1.0), (1.0, 1.0, 1.0)))
    assert geo.mask.all()
    np.testing.assert_allclose(image, B[nadir], rtol=1e-6, atol=1e-7)        # row 0 on top, column 0 left


def test_tiles_repeat_the_texture_with_wrap_around():
    L, V = lv_product([[0.0, 0.0, 1.0]], [[0.0, 0.0, 1.0]])
    tex = np.random.default_rng(0).random((1, 4, 4, 3)).astype(np.float32)
    lookup = BTFLookup(tex, L, V, spatial="nearest")
    geo = surface_geometry("plane", Camera((8, 8), extent=1.0), tiles=2.0, texture_shape=(4, 4))
    image = render_btf(lookup, geo, DirectionalLight())
    np.testing.assert_allclose(image, np.tile(tex[0], (2, 2, 1)), rtol=1e-6)
    bil = BTFLookup(tex, L, V, spatial="bilinear")
    # halfway between the last and the first column wraps around
    got = bil.lookup(L[:1], V[:1], np.array([[4.0, 0.5]]))
    np.testing.assert_allclose(got[0], (tex[0, 0, 3] + tex[0, 0, 0]) / 2, rtol=1e-6)


# --------------------------------------------------------------------------- angular interpolation


@pytest.fixture(scope="module")
def tiny_btf():
    """A turntable sampling (the `tiny` dome, 3 positions: each view has its own light set) and a BTF
    whose value depends only on the light/view pair and the texel."""
    light, view, _ = get_device("tiny").lv_directions()
    tex = np.random.default_rng(1).random((5, 6, 3))
    f = 0.3 + light[:, 2] + 0.5 * view[:, 0] * light[:, 1] + 0.2 * view[:, 2]
    B = (f[:, None, None, None] * tex[None]).astype(np.float32)
    return light, view, B, tex


def test_weights_are_those_of_resample_weights(tiny_btf):
    light, view, B, _ = tiny_btf
    lookup = BTFLookup(B, light, view)
    assert len(lookup.light_sets) > 1                                         # per-view light sets
    rng = np.random.default_rng(2)
    q = rng.normal(size=(2, 300, 3))
    q[..., 2] = np.abs(q[..., 2])
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    W = lookup.weights(q[0], q[1]).toarray()
    ref = resample_weights(light, view, q[0], q[1]).toarray()
    np.testing.assert_allclose(W, ref, atol=1e-12)
    np.testing.assert_allclose(W.sum(axis=1), 1.0, atol=1e-12)


def test_angular_interpolation_is_exact_at_sampled_directions(tiny_btf):
    light, view, B, tex = tiny_btf
    lookup = BTFLookup(B, light, view, spatial="bilinear")
    i, j = np.meshgrid(np.arange(5), np.arange(6), indexing="ij")
    rows = np.repeat(np.arange(len(light)), i.size)
    centre = np.tile(np.stack([j.ravel() + 0.5, i.ravel() + 0.5], axis=1), (len(light), 1))
    got = lookup.lookup(light[rows], view[rows], centre)
    np.testing.assert_allclose(got, B[rows, np.tile(i.ravel(), len(light)), np.tile(j.ravel(), len(light))],
                               rtol=1e-5)
    # a row whose (light, view) pair occurs once is its own weight
    W = lookup.weights(light, view)
    key = np.round(np.concatenate([light, view], axis=1) * 1e6)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    single = np.flatnonzero(counts[inv.ravel()] == 1)
    np.testing.assert_allclose(W[single][:, single].toarray(), np.eye(len(single)), atol=1e-12)


# --------------------------------------------------------------------------- environment light


def test_env_lights_conserve_the_map_integral():
    env = np.random.default_rng(0).random((32, 64, 3))
    dirs, solid = env_directions((32, 64))
    assert solid.sum() * 64 == pytest.approx(4 * math.pi)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0)
    el = env_lights(env, 8, 16)
    assert el.directions.shape == (128, 3) and el.irradiance.shape == (128, 3)
    np.testing.assert_allclose(el.irradiance.sum(axis=0), (env * solid[:, None, None]).sum(axis=(0, 1)))
    # zenith at the top row, the centre column looks toward -z
    assert dirs[0, 32, 1] > 0.99 and dirs[16, 32, 2] < -0.99 and dirs[16, 48, 0] > 0.99
    # a single bright pixel keeps its direction
    sun = np.zeros((32, 64, 3))
    sun[5, 40] = 100.0
    el = env_lights(sun, 4, 8)
    k = int(np.argmax(el.irradiance[:, 0]))
    np.testing.assert_allclose(el.directions[k], dirs[5, 40], atol=1e-12)


@pytest.mark.parametrize("shape", ["sphere", "plane"])
def test_white_environment_on_lambertian_gives_the_albedo(lambertian, shape):
    """Constant radiance 1: irradiance pi on every surface, radiance pi * albedo / pi = albedo."""
    el = env_lights(np.ones((64, 128, 3)), 16, 32)
    geo = surface_geometry(shape, Camera((48, 48)), tiles=1.0, texture_shape=(4, 4))
    got = render_btf(lambertian, geo, el).reshape(-1, 3)[geo.pixel]
    np.testing.assert_allclose(got, np.broadcast_to(ALBEDO, got.shape), rtol=0.01)


def test_lights_add_up(lambertian):
    geo = surface_geometry("sphere", Camera((24, 24)), texture_shape=(4, 4))
    a, b = PointLight(), DirectionalLight((1.0, 1.0, 1.0), (0.5, 0.2, 0.1))
    np.testing.assert_allclose(render_btf(lambertian, geo, [a, b]),
                               render_btf(lambertian, geo, a) + render_btf(lambertian, geo, b), rtol=1e-5, atol=1e-7)
    el = EnvLights(np.array([[1.0, 1.0, 1.0]]) / math.sqrt(3), np.array([[0.5, 0.2, 0.1]]))
    np.testing.assert_allclose(render_btf(lambertian, geo, el), render_btf(lambertian, geo, b), rtol=1e-6)


def test_to_srgb8_masks_the_background():
    image = np.full((4, 4, 3), 0.5, np.float32)
    mask = np.zeros((4, 4), bool)
    mask[1:3, 1:3] = True
    out = to_srgb8(image, mask, background=(10, 20, 30))
    assert out.dtype == np.uint8 and (out[0, 0] == [10, 20, 30]).all() and out[1, 1].min() > 200


# --------------------------------------------------------------------------- bad input


def test_bad_input_names_the_argument():
    L, V = lv_product([[0.0, 0.0, 1.0]], [[0.0, 0.0, 1.0]])
    B = np.ones((1, 2, 2, 3), np.float32)
    with pytest.raises(ValueError, match=r"btf must be an \(n_lv, h, w, 3\)"):
        BTFLookup(B[..., 0], L, V)
    with pytest.raises(ValueError, match="light_dir has shape"):
        BTFLookup(B, np.ones((2, 3)), V)
    bad = B.copy()
    bad[0, 1, 0, 2] = np.nan
    with pytest.raises(ValueError, match=r"btf\[0, 1, 0, 2\]"):
        BTFLookup(bad, L, V)
    with pytest.raises(ValueError, match=r"view_dir\[0\]"):
        BTFLookup(B, L, -V)
    with pytest.raises(ValueError, match="shape must be one of"):
        surface_geometry("torus", Camera((4, 4)))
    with pytest.raises(ValueError, match="tiles must be"):
        surface_geometry("plane", Camera((4, 4)), tiles=0.0)
    with pytest.raises(ValueError, match="image_shape"):
        Camera((0, 4))
    env = np.ones((8, 16, 3))
    env[2, 3, 1] = -1.0
    with pytest.raises(ValueError, match=r"env\[2, 3, 1\]"):
        env_lights(env)
    with pytest.raises(ValueError, match="n_theta, n_phi"):
        env_lights(np.ones((8, 16, 3)), 9, 4)
