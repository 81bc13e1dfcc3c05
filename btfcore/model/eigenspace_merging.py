"""Eigenspace merging: one basis for many materials from their per-material ``(U_i, sigma_i)``.

A truncated SVD of a whole database is too costly at once, so the thesis
fits each material and merges the eigenspaces, first per class and then
globally (paper 1, §4.1: "we merged the resulting eigenspaces first per
cluster and then globally"). For uncentred data (the thesis' bases have no
mean) with :math:`B_i = U_i \\Sigma_i V_i^T`, the concatenation
:math:`B = [B_1, \\dots, B_n]` has

.. math:: B B^T = \\sum_i U_i \\Sigma_i^2 U_i^T = M M^T, \\qquad
          M = [U_1 \\Sigma_1, \\dots, U_n \\Sigma_n],

so the left singular vectors and values of the small matrix ``M`` are those
of ``B`` (paper 4, eq. 9): exact when every per-material model is exact
(``k_i`` at least the material's rank), otherwise the merge of the
truncated models. This is Hall, Marshall and Martin's merge without the
mean and covariance-count terms.

References
----------
.. [1] P. Hall, D. Marshall and R. Martin, "Merging and splitting eigenspace
   models", IEEE TPAMI 22(9), 2000.
.. [2] The thesis, App. paper 1 (den Brok et al.) §4.1.1 (eigenspaces merged
   per cluster, then globally) and paper 4 §4.2, eq. (9).
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from typing import Any, Union

import numpy as np
from scipy import linalg

from btfcore.model._lowrank import RANK_RTOL, TruncatedSVD, check_finite, check_int, check_k, check_rank, fix_signs

__all__ = ["MergeTree", "Model", "merge_eigenspaces", "merge_tree"]

#: A model to merge: a :class:`TruncatedSVD`, ``(U, sigma)`` or ``(U, sigma, rows_id)``.
Model = Union[TruncatedSVD, tuple]


@dataclass(frozen=True)
class MergeTree:
    """Result of :func:`merge_tree`: one merged model per class and the global one."""

    classes: dict[Hashable, TruncatedSVD]
    merged: TruncatedSVD


def _as_model(m: Any, i: int) -> TruncatedSVD:
    """Validate models[i] and return it as a TruncatedSVD (``norm_sq`` defaults to ``sum(sigma^2)``)."""
    if isinstance(m, TruncatedSVD):
        U, sigma, rows_id, norm_sq, converged = m.U, m.sigma, m.rows_id, m.norm_sq, m.converged
    elif isinstance(m, tuple) and len(m) in (2, 3):
        U, sigma, rows_id = np.asarray(m[0], float), np.asarray(m[1], float), (m[2:] or (None,))[0]
        norm_sq, converged = 0.0, True
    else:
        raise ValueError(f"models[{i}] must be a TruncatedSVD, (U, sigma) or (U, sigma, rows_id); "
                         f"got {type(m).__name__}")
    if U.ndim != 2 or sigma.shape != (U.shape[1],):
        raise ValueError(f"models[{i}] has U of shape {U.shape} and sigma of shape {sigma.shape}: "
                         f"need (n_lv, k_i) and (k_i,)")
    check_finite(U, f"models[{i}].U")
    check_finite(sigma, f"models[{i}].sigma")
    if (sigma < 0).any():
        raise ValueError(f"models[{i}].sigma[{int(np.argmax(sigma < 0))}] is negative: singular values are >= 0")
    return TruncatedSVD(np.array(U, float), np.array(sigma, float), "input", converged=converged,
                        norm_sq=norm_sq or float(np.sum(sigma**2)), rows_id=rows_id)


def _check_models(models: Sequence[Model]) -> list[TruncatedSVD]:
    """Validate every model and refuse different row spaces (``n_lv`` or ``rows_id``)."""
    ms = [_as_model(m, i) for i, m in enumerate(models)]
    if not ms:
        raise ValueError("models is empty: nothing to merge")
    n_lv, ids = ms[0].U.shape[0], {m.rows_id for m in ms}
    for i, m in enumerate(ms):
        if m.U.shape[0] != n_lv:
            raise ValueError(f"models[{i}] has n_lv={m.U.shape[0]} rows but models[0] has {n_lv}: bases of "
                             f"different light/view samplings cannot be merged; resample to one sampling first")
        if len(ids) > 1 and m.rows_id != ms[0].rows_id:
            raise ValueError(f"models[{i}] has rows_id={m.rows_id!r} but models[0] has {ms[0].rows_id!r}: bases "
                             f"of different light/view samplings cannot be merged")
    return ms


def merge_eigenspaces(models: Sequence[Model], k: int, *, rank_rtol: float = RANK_RTOL) -> TruncatedSVD:
    """Merge eigenspace models of the same light/view sampling into one rank-``k`` model.

    Parameters
    ----------
    models : sequence of TruncatedSVD or (U, sigma[, rows_id]) tuples
        ``U_i`` of shape ``(n_lv, k_i)`` (orthonormal columns, as from
        :func:`btfcore.model.truncated_svd.truncated_svd`; the ALS bases of paper 4
        need only normalised columns) and ``sigma_i`` of shape ``(k_i,)``.
        All must have the same ``n_lv`` and, where any has a ``rows_id``,
        the same ``rows_id``.
    k : int
        Basis vectors of the merged model: at most ``min(n_lv, sum k_i)``
        and the numerical rank of ``M``.
    rank_rtol : float
        Singular values at or below ``rank_rtol * sigma_1`` count as zero.

    Returns
    -------
    TruncatedSVD
        ``method='merge'``; ``norm_sq`` is the sum of the inputs'
        (``sum(sigma_i^2)`` for tuples), so ``energy_captured`` refers to
        the concatenated data where the inputs carry their ``norm_sq``;
        ``converged`` is True when every input converged.

    Raises
    ------
    ValueError
        On an empty list, different ``n_lv`` or ``rows_id`` (bases of
        different row spaces), NaN/Inf or negative sigma (names the model
        and index), or ``k`` above the size or numerical rank.

    Notes
    -----
    .. math:: U \\Sigma V^T = [U_1 \\Sigma_1, \\dots, U_n \\Sigma_n] \\quad \\text{(paper 4, eq. 9)}

    truncated to the leading ``k`` columns; ``V`` is not formed.
    """
    ms = _check_models(models)
    n_lv = ms[0].U.shape[0]
    M = np.hstack([m.U * m.sigma for m in ms])
    check_k(k, n_lv, M.shape[1], "[U_1 Sigma_1, ...]")
    Um, sm, _ = linalg.svd(M, full_matrices=False)                   # U Sigma V^T = [U_1 Sigma_1, ...]  # eq. (9)
    check_rank(sm, k, f"the merged models (n_lv={n_lv}, {M.shape[1]} columns)", rank_rtol)
    settings = dict(method="merge", k=int(k), n_models=len(ms), rank_rtol=float(rank_rtol))
    return TruncatedSVD(fix_signs(Um[:, :k]), sm[:k].copy(), "merge", settings, 0, 0.0,
                        all(m.converged for m in ms),
                        sum(m.norm_sq for m in ms), ms[0].rows_id)


def merge_tree(
    models: Sequence[Model],
    k: int,
    groups: Sequence[Hashable],
    *,
    class_k: int | None = None,
    min_per_class: int = 1,
    rank_rtol: float = RANK_RTOL,
) -> MergeTree:
    """Merge per class, then merge the class models globally (paper 1, §4.1.1).

    Parameters
    ----------
    models : sequence of TruncatedSVD or (U, sigma[, rows_id]) tuples
        Per-material models (see :func:`merge_eigenspaces`).
    k : int
        Basis vectors of the global model (the thesis: 2048).
    groups : sequence of hashable
        The class of each model, e.g. ``['leather', 'leather', 'wood', ...]``.
    class_k : int, optional
        Basis vectors of each class model; default ``k``. Each class needs
        that many (numerically non-zero) columns among its models.
    min_per_class : int
        Fewest models a class may have. The numerics accept 1; a database
        build that holds materials out per class (leave-one-out) passes 2,
        making "a class with one material" an error here.
    rank_rtol : float
        See :func:`merge_eigenspaces`.

    Returns
    -------
    MergeTree
        ``classes``: class label -> merged class model (in first-appearance
        order); ``merged``: the global model from the class models.

    Raises
    ------
    ValueError
        If ``groups`` does not match ``models``, a class has fewer than
        ``min_per_class`` models (names it), or a merge fails (the message
        names the class).

    Notes
    -----
    Merging is exact for exact inputs at every level, so when every
    per-material model is exact and ``class_k`` is at least each class'
    rank the global model equals the flat merge of all materials (and the
    truncated SVD of the concatenated data).
    """
    if len(groups) != len(models):
        raise ValueError(f"groups has {len(groups)} labels for {len(models)} models: give one class per model")
    check_int(min_per_class, "min_per_class")
    members: dict[Hashable, list[TruncatedSVD]] = {}
    for g, m in zip(groups, _check_models(models)):
        members.setdefault(g, []).append(m)
    classes = {}
    for g, ms in members.items():
        if len(ms) < min_per_class:
            raise ValueError(f"class {g!r} has {len(ms)} model(s), fewer than min_per_class={min_per_class}: "
                             f"add materials to it or drop it")
        try:
            classes[g] = merge_eigenspaces(ms, k if class_k is None else class_k, rank_rtol=rank_rtol)
        except ValueError as e:
            raise ValueError(f"class {g!r}: {e}") from e
    return MergeTree(classes, merge_eigenspaces(list(classes.values()), k, rank_rtol=rank_rtol))
