"""Eigenspace merging per class and globally (paper 1 §4.1; paper 4 eq. 9; Hall et al. 2000)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _lowrank_cases import orthonormal

from btfcore.model.eigenspace_merging import merge_eigenspaces, merge_tree
from btfcore.model.truncated_svd import truncated_svd

N_LV = 300
CLASSES = ["leather"] * 3 + ["wood"] * 3 + ["stone"] * 2


def _database() -> tuple[list[np.ndarray], list[int]]:
    """Exact low-rank materials: 4 directions shared by the class and 2 (stone: 3) of their own.

    Every class has rank 10; all 8 materials together have rank 3 x 4 + 6 x 2 + 2 x 3 = 30.
    """
    rng = np.random.default_rng(11)
    shared = {c: orthonormal(rng, N_LV, 4) for c in dict.fromkeys(CLASSES)}
    mats, ranks = [], []
    for c in CLASSES:
        r = 4 + (3 if c == "stone" else 2)
        A = np.hstack([shared[c], orthonormal(rng, N_LV, r - 4)]) * rng.uniform(0.5, 2.0, r)
        mats.append(A @ rng.standard_normal((r, 500)))
        ranks.append(r)
    return mats, ranks


def _models(mats, ranks):
    return [truncated_svd(B, N_LV, r, "gram", rows_id="dome-a") for B, r in zip(mats, ranks)]


def _same_model(a, U, s, rtol=1e-6):
    k = a.sigma.size
    np.testing.assert_allclose(a.sigma, s[:k], rtol=rtol)
    assert np.linalg.norm(a.U @ a.U.T - U[:, :k] @ U[:, :k].T, 2) < rtol


@pytest.mark.parametrize("k", [10, 30])
def test_merge_reproduces_the_svd_of_the_concatenated_data(k):
    mats, ranks = _database()
    Ue, se, _ = np.linalg.svd(np.hstack(mats), full_matrices=False)
    assert np.sum(se > 1e-8 * se[0]) == 30
    merged = merge_eigenspaces(_models(mats, ranks), k)
    _same_model(merged, Ue, se)
    assert merged.method == "merge" and merged.rows_id == "dome-a" and merged.converged
    np.testing.assert_allclose(merged.norm_sq, np.sum(se**2), rtol=1e-10)
    assert merged.energy_captured == pytest.approx(np.sum(se[:k] ** 2) / np.sum(se**2), rel=1e-10)


def test_merge_tree_per_class_then_global_equals_the_flat_merge():
    mats, ranks = _database()
    models = _models(mats, ranks)
    tree = merge_tree(models, 16, CLASSES, class_k=10)      # every class model exact (rank 10)
    flat = merge_eigenspaces(models, 16)
    _same_model(tree.merged, flat.U, flat.sigma, rtol=1e-9)
    Ue, se, _ = np.linalg.svd(np.hstack(mats), full_matrices=False)
    _same_model(tree.merged, Ue, se)
    assert list(tree.classes) == ["leather", "wood", "stone"]
    for c, model in tree.classes.items():
        Uc, sc, _ = np.linalg.svd(np.hstack([B for B, g in zip(mats, CLASSES) if g == c]), full_matrices=False)
        _same_model(model, Uc, sc)


def test_merge_accepts_plain_tuples_and_keeps_the_row_fingerprint():
    mats, ranks = _database()
    models = _models(mats[:2], ranks[:2])
    tuples = [(m.U, m.sigma) for m in models]
    a, b = merge_eigenspaces(models, 8), merge_eigenspaces(tuples, 8)
    np.testing.assert_allclose(b.U, a.U, atol=1e-12)
    assert b.rows_id is None and merge_eigenspaces([(*t, "x") for t in tuples], 8).rows_id == "x"


def test_merge_refuses_bases_of_different_row_spaces():
    mats, ranks = _database()
    a, b = _models(mats[:2], ranks[:2])
    with pytest.raises(ValueError, match=r"models\[1\] has n_lv=299 rows but models\[0\] has 300"):
        merge_eigenspaces([a, (b.U[1:], b.sigma)], 4)
    with pytest.raises(ValueError, match=r"models\[1\] has rows_id='dome-b' but models\[0\] has 'dome-a'"):
        merge_eigenspaces([a, dataclasses.replace(b, rows_id="dome-b")], 4)
    with pytest.raises(ValueError, match=r"models\[1\] has rows_id=None"):
        merge_eigenspaces([a, (b.U, b.sigma)], 4)


def test_merge_refuses_k_above_size_or_rank_and_nan():
    mats, ranks = _database()
    models = _models(mats[:3], ranks[:3])                    # one class: 18 columns of rank 10
    with pytest.raises(ValueError, match=r"k=11 exceeds the numerical rank 10 of the merged models"):
        merge_eigenspaces(models, 11)
    with pytest.raises(ValueError, match=r"k=19 exceeds min\(rows, columns\) = 18"):
        merge_eigenspaces(models, 19)
    U = np.array(models[1].U)
    U[3, 0] = np.nan
    with pytest.raises(ValueError, match=r"models\[1\]\.U\[3, 0\] = nan"):
        merge_eigenspaces([models[0], (U, models[1].sigma)], 4)
    with pytest.raises(ValueError, match=r"models\[0\]\.sigma\[1\] is negative"):
        merge_eigenspaces([(models[0].U, models[0].sigma * [1, -1, 1, 1, 1, 1])], 4)
    with pytest.raises(ValueError, match="models is empty"):
        merge_eigenspaces([], 4)


def test_merge_tree_checks_classes():
    mats, ranks = _database()
    models = _models(mats, ranks)
    single = merge_tree(models[:4], 8, CLASSES[:4], class_k=6)          # 'wood' has one material: allowed
    assert single.classes["wood"].k == 6
    with pytest.raises(ValueError, match=r"class 'wood' has 1 model\(s\), fewer than min_per_class=2"):
        merge_tree(models[:4], 8, CLASSES[:4], class_k=6, min_per_class=2)
    with pytest.raises(ValueError, match=r"class 'leather': k=11 exceeds the numerical rank 10"):
        merge_tree(models, 16, CLASSES, class_k=11)
    with pytest.raises(ValueError, match="groups has 7 labels for 8 models"):
        merge_tree(models, 16, CLASSES[:7])
