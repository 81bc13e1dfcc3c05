"""Seeded test matrices for the low-rank tests (EM-PCA, truncated SVD, eigenspace merging)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy import linalg


def orthonormal(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    return np.linalg.qr(rng.standard_normal((n, k)))[0]


@lru_cache(maxsize=4)
def decaying(n_lv: int = 500, n_tx: int = 4000, seed: int = 0) -> np.ndarray:
    """Full-rank ``(n_lv, n_tx)`` matrix with singular values ``10 * 0.9^i + 1e-3`` (read-only)."""
    rng = np.random.default_rng(seed)
    B = (orthonormal(rng, n_lv, n_lv) * (10 * 0.9 ** np.arange(n_lv) + 1e-3)) @ orthonormal(rng, n_tx, n_lv).T
    B.setflags(write=False)
    return B


@lru_cache(maxsize=4)
def exact_svd(n_lv: int = 500, n_tx: int = 4000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """numpy's SVD of :func:`decaying`: (U, sigma)."""
    U, s, _ = np.linalg.svd(decaying(n_lv, n_tx, seed), full_matrices=False)
    return U, s


def uneven_blocks(B: np.ndarray, seed: int = 0) -> list[np.ndarray]:
    """Column blocks of random uneven widths (one of width 1)."""
    cuts = np.sort(np.random.default_rng(seed).choice(np.arange(2, B.shape[1]), 6, replace=False))
    return np.split(B, [1, *cuts], axis=1)


def max_angle(U: np.ndarray, V: np.ndarray) -> float:
    """Largest principal angle (radians) between span(U) and span(V)."""
    return float(linalg.subspace_angles(U, V).max())


def assert_meets_bars(res, B: np.ndarray, k: int) -> None:
    """Issue 4's bars on :func:`decaying` (``B``, maybe float32): largest angle to the exact subspace
    < 1e-3 rad, captured energy within 0.1% of the optimal rank-k energy."""
    Ue, se = exact_svd(*B.shape)
    assert res.U.shape == (B.shape[0], k) and res.sigma.shape == (k,)
    np.testing.assert_allclose(res.U.T @ res.U, np.eye(k), atol=1e-10)
    assert max_angle(res.U, Ue[:, :k]) < 1e-3
    optimal = np.sum(se[:k] ** 2)
    captured = np.sum((res.U.T @ B.astype(np.float64)) ** 2)        # what the basis really captures
    assert 1 - captured / optimal < 1e-3
    assert abs(np.sum(res.sigma**2) / optimal - 1) < 1e-3           # what it reports
    assert res.energy_captured == np.sum(res.sigma**2) / res.norm_sq
    np.testing.assert_allclose(res.norm_sq, np.sum(se**2), rtol=1e-5)
