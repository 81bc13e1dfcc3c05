"""EM-PCA streamed over column blocks (Roweis 1998; thesis paper 1 §4.1)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _lowrank_cases import assert_meets_bars, decaying, exact_svd, max_angle, uneven_blocks

from btfcore import BtfWarning
from btfcore.model.empca import empca

K = 20


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("oversample", [0, 10])
def test_empca_meets_the_bars_at_convergence(dtype, oversample):
    B = decaying().astype(dtype)
    res = empca(uneven_blocks(B), B.shape[0], K, oversample=oversample)
    assert res.method == "empca" and res.converged and res.change < 1e-4
    assert 2 <= res.iterations < 100
    assert_meets_bars(res, B, K)


def test_empca_energy_criterion_converges_on_the_residual_energy():
    B = decaying()
    res = empca(B, B.shape[0], K, criterion="energy")
    assert res.converged and res.change < 1e-4 and res.settings["criterion"] == "energy"
    _, se = exact_svd()
    excess = np.sum(se[:K] ** 2) - np.sum((res.U.T @ B) ** 2)       # squared error above the optimal
    assert excess < 1e-3 * np.sum(se[K:] ** 2)


def test_empca_is_independent_of_blocking():
    B = decaying()
    one = empca(B, B.shape[0], K)
    many = empca(uneven_blocks(B, seed=3), B.shape[0], K)
    streamed = empca(lambda: iter(np.array_split(B, 9, axis=1)), B.shape[0], K)
    for res in (many, streamed):
        assert res.iterations == one.iterations
        np.testing.assert_allclose(res.U, one.U, atol=1e-9)
        np.testing.assert_allclose(res.sigma, one.sigma, rtol=1e-12)
        np.testing.assert_allclose(res.norm_sq, one.norm_sq, rtol=1e-12)


def test_empca_is_deterministic_given_its_seed():
    B = decaying()
    a, b, c = (empca(B, B.shape[0], K, seed=s) for s in (7, 7, 8))
    np.testing.assert_array_equal(a.U, b.U)
    np.testing.assert_array_equal(a.sigma, b.sigma)
    assert max_angle(a.U, c.U) < 1e-3


def test_empca_warns_and_reports_when_not_converged():
    B = decaying()
    with pytest.warns(BtfWarning, match="max_iter=3"):
        res = empca(B, B.shape[0], K, max_iter=3)
    assert not res.converged and res.iterations == 3 and res.change > 1e-4


def test_empca_settings_are_json_and_results_read_only():
    B = decaying()
    res = empca(B, B.shape[0], K, oversample=5, seed=3, rows_id="tiny-v1")
    assert json.loads(json.dumps(res.settings, allow_nan=False)) == res.settings
    assert res.settings["oversample"] == 5 and res.settings["seed"] == 3 and res.rows_id == "tiny-v1"
    with pytest.raises(ValueError, match="read-only"):
        res.U[0, 0] = 1.0


@pytest.mark.parametrize("kwargs, match", [
    (dict(criterion="residual"), "criterion must be one of"),
    (dict(tol=0.0), "tol must be positive"),
    (dict(max_iter=0), "max_iter must be an integer >= 1"),
    (dict(oversample=-1), "oversample must be an integer >= 0"),
])
def test_empca_rejects_bad_arguments(kwargs, match):
    B = decaying()
    with pytest.raises(ValueError, match=match):
        empca(B, B.shape[0], K, **kwargs)


def test_orthonormalise_spans_the_columns_and_falls_back_when_ill_conditioned():
    from btfcore.model._lowrank import orthonormalise

    rng = np.random.default_rng(3)
    S = rng.standard_normal((500, 40)) @ np.diag(np.geomspace(1, 1e-4, 40))     # cond 1e4: CholeskyQR2
    Q = orthonormalise(S)
    assert np.abs(Q.T @ Q - np.eye(40)).max() < 1e-12
    assert np.linalg.norm(S - Q @ (Q.T @ S)) < 1e-12 * np.linalg.norm(S)           # the same span
    S[:, -1] = S[:, 0] + 1e-15 * rng.standard_normal(500)                          # numerically rank-deficient
    Q = orthonormalise(S)                                                           # Householder QR instead
    assert np.abs(Q.T @ Q - np.eye(40)).max() < 1e-12 and np.isfinite(Q).all()
