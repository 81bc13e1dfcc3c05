"""Angular resampling by barycentric interpolation on Delaunay triangulations (thesis §1.1.2)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from btfcore.capture.resample import (
    barycentric_weights,
    lv_outside_hull,
    lv_product,
    outside_hull,
    parabolic_map,
    resample,
    resample_weights,
    ubo2014_directions,
    unique_directions,
)
from btfcore.dome import get_device, spherical_to_cartesian


def _random_dirs(rng, n, theta_max_deg=80.0):
    # uniform in solid angle up to theta_max
    cos_t = rng.uniform(np.cos(np.deg2rad(theta_max_deg)), 1.0, n)
    return spherical_to_cartesian(np.rad2deg(np.arccos(cos_t)), rng.uniform(0, 360, n))


def _theta_deg(d):
    return np.rad2deg(np.arccos(np.clip(d[:, 2], -1, 1)))


def _check_stochastic(W):
    assert sp.issparse(W) and W.format == "csr"
    assert W.data.min() >= 0.0
    np.testing.assert_allclose(np.asarray(W.sum(axis=1)).ravel(), 1.0, atol=1e-12)


def _brdf(light, view, exponent=4.0):
    """cos-weighted Lambert + a broad Phong lobe about the mirror direction (normal +z)."""
    r = light * np.array([-1.0, -1.0, 1.0])                   # mirror of l about +z
    lobe = np.clip(np.einsum("ij,ij->i", r, view), 0.0, None) ** exponent
    return light[:, 2] * (0.5 / np.pi + 0.3 * lobe)


def _random_bilinear(rng):
    """``f(light, view) = a + b.p(l) + c.p(v) + p(l)^T D p(v)`` with random ``b, c, D``: exact under
    barycentric weights wherever the targets lie inside the source hulls."""
    b, c, D = rng.normal(size=2), rng.normal(size=2), rng.normal(size=(2, 2))

    def f(light, view):
        pl, pv = parabolic_map(light), parabolic_map(view)
        return 0.3 + pl @ b + pv @ c + np.einsum("ni,ij,nj->n", pl, D, pv)

    return f


def _rel(est, truth):
    return float(np.linalg.norm(est - truth) / np.linalg.norm(truth))


@pytest.fixture(scope="module")
def ubo_lv():
    return lv_product(ubo2014_directions(), ubo2014_directions())


@pytest.fixture(scope="module")
def bonn_weights(ubo_lv):
    L, V, _ = get_device("bonn-dome2").lv_directions()
    return L, V, resample_weights(L, V, *ubo_lv)


# --------------------------------------------------------------------------- directions


def test_parabolic_map_reference_values():
    th = np.array([0.0, 30.0, 60.0, 90.0, 45.0])
    ph = np.array([0.0, 0.0, 90.0, 180.0, 225.0])
    xy = parabolic_map(spherical_to_cartesian(th, ph))
    r = np.tan(np.deg2rad(th) / 2)                            # radius tan(theta / 2)
    np.testing.assert_allclose(xy, np.stack([r * np.cos(np.deg2rad(ph)), r * np.sin(np.deg2rad(ph))], 1),
                               atol=1e-15)
    np.testing.assert_allclose(parabolic_map([[0.0, 0.0, 2.0], [3.0, 0.0, 0.0]]), [[0, 0], [1, 0]])


def test_parabolic_map_rejects_lower_hemisphere_and_nan():
    d = np.array([[0, 0, 1.0], [0.1, 0, 1], [0.5, 0.5, -0.2]])
    with pytest.raises(ValueError, match=r"dirs\[2\].*below the sample plane"):
        parabolic_map(d)
    d[2] = [np.nan, 0, 1]
    with pytest.raises(ValueError, match=r"dirs\[2\].*not finite"):
        parabolic_map(d)
    with pytest.raises(ValueError, match=r"dirs\[0\].*zero vector"):
        parabolic_map(np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        parabolic_map(np.ones((4, 2)))


def test_ubo2014_directions():
    U = ubo2014_directions()
    assert U.shape == (151, 3)
    np.testing.assert_allclose(np.linalg.norm(U, axis=1), 1.0, atol=1e-15)
    th, counts = np.unique(np.round(_theta_deg(U), 6), return_counts=True)
    np.testing.assert_allclose(th, [0, 11, 23.5, 30, 37.5, 45, 52.5, 60, 67.5, 75])
    np.testing.assert_array_equal(counts, [1, 6, 12, 12, 12, 18, 18, 24, 24, 24])
    phi = np.rad2deg(np.arctan2(U[:, 1], U[:, 0])) % 360
    np.testing.assert_allclose(phi[1], 15.0)                  # ring 11 deg starts at 15 deg
    np.testing.assert_allclose(phi[1 + 6 + 12 + 12 + 12 + 18], 7.5)   # ring 52.5 deg starts at 7.5 deg
    # the same sampling as the fully parallel dome's cameras
    d = get_device("ubo-dome1")
    np.testing.assert_allclose(U, d.camera_position / np.linalg.norm(d.camera_position, axis=1)[:, None],
                               atol=1e-15)


def test_unique_directions_merges_within_tolerance():
    d = np.array([[0, 0, 1.0], [1, 0, 1], [0, 0, 1 + 1e-12], [1, 1e-9, 1], [0, 1, 0]])
    u, inv = unique_directions(d)
    assert len(u) == 3
    np.testing.assert_array_equal(inv, [0, 1, 0, 1, 2])
    np.testing.assert_allclose(u[inv], d / np.linalg.norm(d, axis=1)[:, None], atol=1e-8)


def test_lv_product_is_view_major_like_the_device():
    dev = get_device("tiny", turntable_angle_deg=[0.0])
    L, V, _ = dev.lv_directions()
    pl, pv = lv_product(dev.light_dirs(0), dev.view_dirs(0))
    np.testing.assert_allclose(pl, L, atol=1e-15)
    np.testing.assert_allclose(pv, V, atol=1e-15)


# --------------------------------------------------------------------------- 2D barycentric weights


def test_identity_on_the_source_directions():
    rng = np.random.default_rng(1)
    for src in (ubo2014_directions(), _random_dirs(rng, 60)):
        W = barycentric_weights(src, src)
        _check_stochastic(W)
        np.testing.assert_allclose(W.toarray(), np.eye(len(src)), atol=1e-12)


def test_linear_functions_in_the_parabolic_map_are_exact_inside_the_hull():
    rng = np.random.default_rng(2)
    src = np.concatenate([_random_dirs(rng, 80, 85.0), spherical_to_cartesian(np.full(12, 85.0),
                                                                               np.arange(12) * 30.0)])
    dst = _random_dirs(rng, 500, 75.0)
    assert not outside_hull(src, dst).any()
    W = barycentric_weights(src, dst)
    _check_stochastic(W)
    assert np.diff(W.indptr).max() <= 3
    a, b = 0.7, np.array([1.3, -2.1])
    f = lambda d: a + parabolic_map(d) @ b                     # noqa: E731
    np.testing.assert_allclose(W @ f(src), f(dst), atol=1e-12)
    np.testing.assert_allclose(W @ parabolic_map(src), parabolic_map(dst), atol=1e-12)


def test_outside_the_hull_goes_to_the_nearest_hull_point():
    # sources up to 40 deg; targets beyond are projected onto the hull boundary
    rng = np.random.default_rng(3)
    src = _random_dirs(rng, 40, 40.0)
    dst = spherical_to_cartesian(np.array([60.0, 89.0, 50.0, 70.0]), np.array([0.0, 100.0, 200.0, 300.0]))
    out = outside_hull(src, dst)
    assert out.all()
    W = barycentric_weights(src, dst)
    _check_stochastic(W)
    assert np.diff(W.indptr).max() <= 2                        # an edge or a vertex
    P, Q = parabolic_map(src), parabolic_map(dst)
    proj = W @ P
    # the projection is no farther than any point of any hull edge (dense check on the edges)
    from scipy.spatial import ConvexHull
    hull = ConvexHull(P)
    t = np.linspace(0, 1, 2001)[:, None, None]
    edge_pts = (P[hull.simplices[:, 0]] * (1 - t) + P[hull.simplices[:, 1]] * t).reshape(-1, 2)
    d_best = np.min(np.linalg.norm(Q[:, None] - edge_pts[None], axis=-1), axis=1)
    np.testing.assert_allclose(np.linalg.norm(proj - Q, axis=1), d_best, rtol=1e-4, atol=1e-9)
    assert not outside_hull(src, src).any()


def test_duplicate_sources_share_the_weight_and_collinear_sources_interpolate_along_the_line():
    src = spherical_to_cartesian(np.array([0.0, 30.0, 30.0, 60.0, 0.0]), np.zeros(5))   # one meridian, zenith twice
    W = barycentric_weights(src, spherical_to_cartesian(np.array([0.0, 45.0, 80.0]), np.zeros(3)))
    _check_stochastic(W)
    np.testing.assert_allclose(W.toarray()[0], [0.5, 0, 0, 0, 0.5])   # the two zenith samples averaged
    p = parabolic_map(src)[:, 0]
    np.testing.assert_allclose((W @ p)[1], np.tan(np.deg2rad(45) / 2), atol=1e-12)   # linear along the line
    np.testing.assert_allclose(W.toarray()[2], [0, 0, 0, 1, 0])        # clamped at the end
    one = barycentric_weights(src[:1], src)
    np.testing.assert_array_equal(one.toarray(), np.ones((5, 1)))


# --------------------------------------------------------------------------- 4D light x view weights


def test_cartesian_product_source_is_a_kronecker_product():
    rng = np.random.default_rng(4)
    sl, sv = _random_dirs(rng, 30, 85.0), _random_dirs(rng, 12, 85.0)
    dl, dv = _random_dirs(rng, 20, 60.0), _random_dirs(rng, 7, 60.0)
    W = resample_weights(*lv_product(sl, sv), *lv_product(dl, dv))
    _check_stochastic(W)
    K = sp.kron(barycentric_weights(sv, dv), barycentric_weights(sl, dl))   # view-major, light fastest
    np.testing.assert_allclose(W.toarray(), K.toarray(), atol=1e-14)
    assert np.diff(W.indptr).max() <= 9


def test_identity_onto_the_source_pairs(ubo_lv):
    W = resample_weights(*ubo_lv, *ubo_lv)
    _check_stochastic(W)
    assert W.nnz == W.shape[0] and (W != sp.identity(W.shape[0], format="csr")).nnz == 0
    # a turntable dome: per-view light sets differ; the zenith camera repeats (the same pairs measured
    # at several turntable angles are averaged), every other row maps to itself exactly
    L, V, _ = get_device("tiny").lv_directions()
    W = resample_weights(L, V, L, V)
    _check_stochastic(W)
    rng = np.random.default_rng(5)
    key = np.round(np.concatenate([L, V], 1) * 1e6).astype(np.int64)
    _, pair, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    g = rng.normal(size=pair.max() + 1)[pair.ravel()]         # any function of the (light, view) pair
    np.testing.assert_allclose(W @ g, g, atol=1e-12)
    single = counts[pair.ravel()] == 1
    assert single.sum() > 0.8 * len(L)
    np.testing.assert_allclose(W.toarray()[single], np.eye(len(L))[single], atol=1e-12)


def test_bilinear_functions_are_exact_on_a_turntable_dome(bonn_weights, ubo_lv):
    L, V, W = bonn_weights
    _check_stochastic(W)
    dl, dv = ubo_lv
    f = _random_bilinear(np.random.default_rng(6))
    # inside the view hull (the lowest camera ring of 12 azimuths covers theta <= 73 deg) and every
    # view's light hull: exact
    inside = (_theta_deg(dv) < 70) & (_theta_deg(dl) < 70)
    assert not outside_hull(V, dv[inside]).any()
    np.testing.assert_allclose((W @ f(L, V))[inside], f(dl, dv)[inside], atol=1e-11)


def test_smooth_brdf_resampled_onto_ubo2014(bonn_weights, ubo_lv):
    dl, dv = ubo_lv
    truth = _brdf(dl, dv)
    L, V, W = bonn_weights
    err_bonn = _rel(W @ _brdf(L, V), truth)
    err_bonn_lambert = _rel(W @ (L[:, 2] / np.pi), dl[:, 2] / np.pi)
    Lt, Vt, _ = get_device("tiny").lv_directions()
    Wt = resample_weights(Lt, Vt, dl, dv)
    _check_stochastic(Wt)
    err_tiny = _rel(Wt @ _brdf(Lt, Vt), truth)
    print(f"relative L2 error onto ubo2014: bonn-dome2 {err_bonn:.4f} (Lambert {err_bonn_lambert:.4f}), "
          f"tiny {err_tiny:.4f}")
    # measured 2026: bonn-dome2 0.029 (Lambert 0.0077), tiny 0.28 (16 LEDs, 10 distinct views)
    assert err_bonn < 0.04
    assert err_bonn_lambert < 0.01
    assert err_tiny < 0.35


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_resample_a_btf_chunk(bonn_weights, dtype):
    L, V, W = bonn_weights
    rng = np.random.default_rng(7)
    albedo = rng.uniform(0.1, 1.0, size=(8, 8, 3))
    B = (_brdf(L, V)[:, None, None, None] * albedo).astype(dtype)      # (n_lv, h, w, 3)
    out = resample(B, W)
    assert out.shape == (W.shape[0], 8, 8, 3) and out.dtype == dtype
    flat = resample(B.reshape(len(L), -1), W)
    np.testing.assert_array_equal(out.reshape(W.shape[0], -1), flat)
    # chunks of texels give the same columns
    parts = np.concatenate([resample(B.reshape(len(L), -1)[:, s:s + 50], W) for s in range(0, 192, 50)], 1)
    np.testing.assert_allclose(parts, flat, rtol=1e-6)
    rows = rng.choice(W.shape[0], 300, replace=False)        # dense reference on a subset of rows
    ref = W[rows].toarray() @ B.reshape(len(L), -1).astype(np.float64)
    np.testing.assert_allclose(flat[rows], ref, rtol=1e-5 if dtype == np.float32 else 1e-12, atol=1e-7)


def test_resample_bad_input():
    W = sp.identity(4, format="csr")
    B = np.ones((4, 3, 2))
    B[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"B\[1, 2, 0\]"):
        resample(B, W)
    with pytest.raises(ValueError, match=r"\(n_lv_dst, 5\)"):
        resample(np.ones((5, 2)), W)
    d = ubo2014_directions()
    with pytest.raises(ValueError, match="src_light has 151 rows but src_view 150"):
        resample_weights(d, d[:150], d, d)
    bad = d.copy()
    bad[7, 2] = -0.5
    with pytest.raises(ValueError, match=r"dst_view\[7\]"):
        resample_weights(d, d, d, bad)


def test_lv_outside_hull_flags_exactly_the_extrapolated_rows(ubo_lv):
    dl, dv = ubo_lv
    f = _random_bilinear(np.random.default_rng(8))
    # tiny: 10 distinct views over 3 turntable positions, 16 LEDs whose hull misses the low UBO rings
    L, V, _ = get_device("tiny").lv_directions()
    W = resample_weights(L, V, dl, dv)
    view_out, light_out = lv_outside_hull(L, V, dl, dv)
    np.testing.assert_array_equal(view_out, outside_hull(V, dv))
    err = np.abs(W @ f(L, V) - f(dl, dv))
    inside = ~(view_out | light_out)
    assert 0.1 < inside.mean() < 0.9 and light_out.any() and (light_out & ~view_out).any()
    np.testing.assert_allclose(err[inside], 0.0, atol=1e-12)      # not flagged: exact
    assert (err[~inside] > 1e-9).all()                             # flagged: extrapolated
    # the source's own pairs are never outside
    assert not np.any(lv_outside_hull(L, V, L, V))
