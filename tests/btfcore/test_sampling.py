"""Sparse sampling: random swap (paper 1, Alg. 1), greedy, groups, patches, parabolic map, multiplexing, errors."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.model.abtf import patch_matrix
from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.capture.resample import lv_product, parabolic_map, ubo2014_directions
from btfcore.acquisition.synthetic_basis import synthetic_log_abrdf_basis
from btfcore.acquisition.sampling import (
    SamplingResult,
    greedy,
    multiplexed_basis,
    multiplexed_condition,
    parabolic_map_grid,
    parabolic_map_sampling,
    random_swap,
    select_samples,
    selection_condition,
)


@pytest.fixture(scope="module")
def U() -> np.ndarray:
    return synthetic_log_abrdf_basis()


def test_synthetic_basis_is_the_leading_singular_vectors():
    """Orthonormal, seeded, and the leading vectors do not depend on how many are asked for (up to sign)."""
    U = synthetic_log_abrdf_basis(n_dirs=12, n_tx=50, k=6, seed=4)
    assert U.shape == (144, 6)
    np.testing.assert_allclose(U.T @ U, np.eye(6), atol=1e-10)
    np.testing.assert_array_equal(U, synthetic_log_abrdf_basis(n_dirs=12, n_tx=50, k=6, seed=4))
    again = synthetic_log_abrdf_basis(n_dirs=12, n_tx=50, k=12, seed=4)        # same matrix, more vectors
    np.testing.assert_allclose(np.abs(np.sum(U * again[:, :6], axis=0)), 1.0, atol=1e-10)
    with pytest.raises(ValueError, match="k = 51"):
        synthetic_log_abrdf_basis(n_dirs=12, n_tx=50, k=51)


def test_random_swap_history_never_increases(U):
    res = random_swap(U, 30, max_steps=400, seed=3)
    assert isinstance(res, SamplingResult) and res.method == "random_swap"
    h = res.history
    assert h.shape == (res.steps + 1,) and res.steps == 400
    assert np.all(np.diff(h) <= 0)
    assert h[-1] < h[0]                                              # it does improve on the random start
    np.testing.assert_allclose(res.kappa, h[-1], rtol=1e-8)
    assert res.rows.size == 30 and np.unique(res.rows).size == 30
    assert res.rows.min() >= 0 and res.rows.max() < U.shape[0]
    np.testing.assert_allclose(res.kappa, np.linalg.cond(U[res.rows]), rtol=1e-10)
    again = random_swap(U, 30, max_steps=400, seed=3)
    np.testing.assert_array_equal(again.rows, res.rows)             # seeded


def test_random_swap_patience_stops_early(U):
    res = random_swap(U, 30, max_steps=100_000, seed=0, patience=50)
    assert res.converged and res.steps < 100_000


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_greedy_beats_random_swap(seed):
    U = synthetic_log_abrdf_basis(seed=seed)
    swap = random_swap(U, 30, max_steps=1500, seed=seed)
    g = greedy(U, 30, seed=seed)
    assert g.kappa <= swap.kappa
    assert np.unique(g.rows).size == 30 and g.rows.max() < U.shape[0]
    assert np.all(np.diff(g.history) < 0)                           # accepts kappa decreases only
    np.testing.assert_allclose(g.kappa, np.linalg.cond(U[g.rows]), rtol=1e-10)


def test_groups_select_whole_groups(U):
    n_l = 24                                                         # rows v * n_l + l; group = light (all views)
    groups = np.arange(U.shape[0]) % n_l
    for res in (random_swap(U, 4, groups=groups, max_steps=100, seed=0), greedy(U, 4, groups=groups)):
        assert res.units.size == 4 and np.unique(res.units).size == 4
        chosen = np.isin(groups, res.units)
        np.testing.assert_array_equal(res.rows, np.flatnonzero(chosen))   # every row of a chosen group
        np.testing.assert_allclose(res.kappa, np.linalg.cond(U[res.rows]), rtol=1e-10)
        assert np.all(np.diff(res.history) <= 0)


def test_groups_of_unequal_size_and_arbitrary_ids(U):
    rng = np.random.default_rng(5)
    groups = rng.integers(0, 40, U.shape[0]) * 7 + 100
    res = greedy(U, 6, groups=groups)
    assert set(res.units.tolist()) <= set(groups.tolist())
    np.testing.assert_array_equal(res.rows, np.flatnonzero(np.isin(groups, res.units)))


@pytest.mark.parametrize("method", ["random_swap", "greedy"])
def test_patch_kappa_is_the_kronecker_selection(method):
    rng = np.random.default_rng(0)
    n_lv, p, k = 40, 2, 20
    U_patch = np.linalg.qr(rng.standard_normal((p * p * n_lv, k)))[0]
    kw = {"max_steps": 200, "seed": 1} if method == "random_swap" else {}
    res = select_samples(U_patch, 8, method, patch=p, **kw)
    M = np.zeros((8, n_lv))
    M[np.arange(8), res.rows] = 1.0
    KM = np.kron(np.eye(p * p), M) @ U_patch                         # (I_{p^2} kron M) U_patch, built explicitly
    np.testing.assert_allclose(res.kappa, np.linalg.cond(KM), rtol=1e-10)
    np.testing.assert_allclose(selection_condition(U_patch, res.rows, patch=p), np.linalg.cond(KM), rtol=1e-10)
    assert np.all(np.diff(res.history) <= 0)


def test_patch_row_order_matches_patch_matrix():
    """Row t * n_lv + s of a patch basis is pair s of texel t: measuring rows of B = selecting those rows."""
    rng = np.random.default_rng(1)
    B = rng.random((6, 4, 4))
    P = patch_matrix(B, 2, overlap=True)
    rows = np.array([1, 4])
    sel = (np.arange(4)[:, None] * 6 + rows[None, :]).ravel()
    np.testing.assert_array_equal(P[sel], patch_matrix(B[rows], 2, overlap=True))


def test_parabolic_grid_counts_of_the_thesis():
    g = parabolic_map_grid(7)
    assert g.shape == (37, 3)                                        # 37 x 37 = 1369 samples, paper 1 §4.2
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0)
    assert np.all(g[:, 2] >= 0)
    np.testing.assert_allclose(parabolic_map(g), np.array([(x, y) for y in np.arange(-6, 7, 2) / 7
                                                           for x in np.arange(-6, 7, 2) / 7
                                                           if x * x + y * y <= 1]))
    light, view = lv_product(ubo2014_directions(), ubo2014_directions())
    assert parabolic_map_sampling(light, view, 7).size == 1369


def test_parabolic_map_snaps_to_nearest_direction():
    rng = np.random.default_rng(2)
    L = rng.normal(size=(30, 3))
    L[:, 2] = np.abs(L[:, 2])
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    V = L[:12]
    light, view = lv_product(L, V)
    rows = parabolic_map_sampling(light, view, 5)
    grid = parabolic_map_grid(5)
    near_l = np.unique([np.argmin(np.linalg.norm(L - g, axis=1)) for g in grid])      # brute force
    near_v = np.unique([np.argmin(np.linalg.norm(V - g, axis=1)) for g in grid])
    want = np.sort([v * len(L) + l for v in near_v for l in near_l])                  # lv_product: light fastest
    np.testing.assert_array_equal(rows, want)


def test_multiplexed_condition_equals_explicit_matrix():
    rng = np.random.default_rng(3)
    n_v, n_l, k = 4, 6, 10
    S = multiplexing_patterns(n_l)                                   # (7, 6)
    U = rng.standard_normal((n_v * n_l, k))
    sigma = np.sort(rng.uniform(0.5, 5.0, k))[::-1]
    M = np.kron(np.eye(n_v), S)                                      # patterns per view
    rows = rng.choice(n_v * S.shape[0], 14, replace=False)
    Sel = np.eye(n_v * S.shape[0])[rows]                             # the thesis' selector S
    want = np.linalg.cond(Sel @ M @ U @ np.diag(sigma))
    np.testing.assert_allclose(multiplexed_condition(S, rows, U, sigma), want, rtol=1e-10)
    np.testing.assert_allclose(multiplexed_basis(S, U), M @ U, rtol=1e-12)
    res = greedy(multiplexed_basis(S, U, sigma), 14)                 # sampling a multiplexed design
    np.testing.assert_allclose(res.kappa, multiplexed_condition(S, res.rows, U, sigma), rtol=1e-10)


def test_select_samples_dispatches(U):
    light, view = lv_product(ubo2014_directions()[:24], ubo2014_directions()[:24])
    pm = select_samples(U, None, "parabolic_map", light_dirs=light, view_dirs=view, grid=3)
    np.testing.assert_array_equal(pm.rows, parabolic_map_sampling(light, view, 3))
    assert select_samples(U, 20, "random_swap", max_steps=10).method == "random_swap"
    assert select_samples(U, 20).method == "greedy"
    with pytest.raises(ValueError, match="unknown sampling method"):
        select_samples(U, 20, "nielsen")


def test_errors(U):
    with pytest.raises(ValueError, match=r"n_s=5 .* fewer than its k=12 .*underdetermined.*Tikhonov"):
        random_swap(U, 5)
    with pytest.raises(ValueError, match=r"n_s=600 exceeds the 576 available"):
        greedy(U, 600)
    with pytest.raises(ValueError, match=r"groups must be .* length U.shape\[0\] = 576"):
        greedy(U, 20, groups=np.zeros(10, int))
    with pytest.raises(ValueError, match=r"n_s=30 exceeds the 24 available groups"):
        greedy(U, 30, groups=np.arange(576) % 24)
    bad = U.copy()
    bad[7, 3] = np.nan
    with pytest.raises(ValueError, match=r"U\[7, 3\] = nan"):
        random_swap(bad, 20)
    with pytest.raises(ValueError, match="patch=5"):
        greedy(U, 20, patch=5)
    with pytest.raises(ValueError, match=r"M_rows\[0\] = 99 is out of range"):
        multiplexed_condition(multiplexing_patterns(6), [99], np.ones((12, 2)))


def test_greedy_survives_candidates_that_make_the_system_singular():
    """n_s groups barely above k: some exchanges make M U singular, whose predicted spectrum
    overflowed and stopped the sampler ('Eigenvalues did not converge') before they were ranked last."""
    n_turn, n_cam, n_led = 3, 4, 16                                 # the tiny dome's (turntable, LED) groups
    t, _, led = np.meshgrid(np.arange(n_turn), np.arange(n_cam), np.arange(n_led), indexing="ij")
    groups = (t * n_led + led).ravel()
    for seed in (0, 1, 3):
        U = np.linalg.qr(np.random.default_rng(seed).standard_normal((192, 128)))[0]
        result = greedy(U, 36, groups=groups)
        assert np.isfinite(result.kappa)
        assert result.kappa == pytest.approx(np.linalg.cond(U[result.rows]), rel=1e-6)
