"""Sparse sampling: which light/view pairs to measure, chosen by the condition number.

A sparse measurement of a BTF ``B`` (``(n_lv, n_tx)``, rows light/view pairs)
is ``M B`` with ``M`` a row selector: ``n_s`` rows of the identity. Given a
basis ``U`` (``(n_lv, k)``) the coefficients are found from ``M U V = M B``
(paper 1, eq. 3), so ``M`` should make ``M U`` well conditioned. Matusik et
al.'s random swap (paper 1, Alg. 1; paper 4, §4.3) minimises
:math:`\\kappa(M U)` by trial swaps of one selected row. This module
represents ``M`` by the indices of the rows it selects and offers

* :func:`random_swap`: the thesis' algorithm,
* :func:`greedy`: a faster sampler (not in the thesis): batched swaps on a
  smooth condition number, then single swaps chosen by exactly predicted
  extreme eigenvalues (Rayleigh-Ritz, :math:`O(k)` per candidate swap),
* :func:`parabolic_map_sampling`: the 7 x 7 parabolic-map heuristic of
  paper 1, Fig. 3b,
* :func:`multiplexed_basis` / :func:`multiplexed_condition`: the condition
  number :math:`\\kappa(S M U \\Sigma)` of sparse multiplexed designs (paper 4, §4.3),
* :func:`select_samples`: a ``method=`` dispatcher.

Every sampler supports ABTF patch bases (``patch=p``: the measurement matrix
is :math:`I_{p^2} \\otimes M`, paper 1, §3.3-3.4) and *groups* of rows that
are measured together (camera-parallel sampling, paper 4, §5.2: a (light,
turntable) pair is measured by all cameras at once). See ``docs/sampling.md``.

References
----------
.. [1] The thesis, App. paper 1 (den Brok et al., "Patch-based sparse
   reconstruction of material BTFs", WSCG 2014), §3.3-3.4 and Alg. 1, §4.2
   and Fig. 3b (the 7x7 parabolic map); paper 4 ("Rapid material capture
   through sparse and multiplexed measurements"), §4.3-4.4, eqs. (4) and (10),
   §5.2 (camera-parallel sampling).
.. [2] W. Matusik, H. Pfister, M. Brand and L. McMillan, "Efficient isotropic
   BRDF measurement", EGSR 2003 (the random swap).
.. [3] P. Businger and G. H. Golub, "Linear least squares solutions by
   Householder transformations", Numer. Math. 7, 1965 (column pivoting).
.. [4] V. V. Fedorov, *Theory of Optimal Experiments*, Academic Press, 1972
   (exchange algorithms for optimal designs).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from scipy import linalg

from btfcore.capture.resample import DIRECTION_TOL, _as_dirs, parabolic_map, unique_directions

__all__ = [
    "SAMPLING_METHODS",
    "SamplingResult",
    "greedy",
    "multiplexed_basis",
    "multiplexed_condition",
    "parabolic_map_grid",
    "parabolic_map_sampling",
    "random_swap",
    "select_samples",
    "selection_condition",
]

#: Methods of :func:`select_samples`.
SAMPLING_METHODS: tuple[str, ...] = ("greedy", "random_swap", "parabolic_map")

#: Above this condition number kappa is recomputed from the selected rows (SVD) instead of
#: the k x k Gram matrix, whose eigenvalues lose relative accuracy ~ k eps kappa^2.
_GRAM_KAPPA_MAX = 1e5

#: The Gram matrix of the selection is rebuilt from its rows every this many accepted swaps
#: (the running sum of rank-m updates drifts by rounding).
_REFRESH = 64

#: Eigenvectors whose weight in the smooth objective is below this fraction of the largest are ignored.
_JTOL = 1e-2


# --------------------------------------------------------------------------- result


@dataclass(frozen=True)
class SamplingResult:
    """A sparse sampling: the rows of ``B`` to measure and how well they condition ``M U``.

    Attributes
    ----------
    rows : (n_rows,) ndarray of intp
        Sorted indices of the selected light/view rows of ``B`` (rows of
        ``U``; for ``patch=p`` rows of the ``n_lv = U.shape[0] / p**2``
        light/view pairs, measured at every texel of a patch). Read-only.
    units : (n_s,) ndarray of int64
        The selected units, sorted: row indices without groups, group ids
        (values of ``groups``) with groups. Read-only.
    kappa : float
        :math:`\\kappa(M U)` of the result (:math:`\\kappa((I_{p^2} \\otimes M) U)`
        for patches), computed from the singular values of the selected
        rows; ``inf`` if they do not have rank ``k``.
    history : (n_steps + 1,) ndarray of float64
        :math:`\\kappa` of the current selection at the start and after every
        step (trial swap of :func:`random_swap`, accepted swap of
        :func:`greedy`'s refinement); non-increasing. Empty for the
        parabolic map. Read-only.
    method : str
        ``'random_swap'``, ``'greedy'`` or ``'parabolic_map'``.
    steps : int
        Trial swaps evaluated (random swap) or swaps accepted (greedy).
    accepted : int
        Swaps accepted.
    converged : bool
        Random swap: ``patience`` consecutive trial swaps were all rejected.
        Greedy: no candidate swap lowered kappa.
    settings : dict
        Every argument that shaped the result (JSON-serialisable scalars).
    """

    rows: np.ndarray
    units: np.ndarray
    kappa: float
    history: np.ndarray
    method: str
    steps: int = 0
    accepted: int = 0
    converged: bool = False
    settings: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for a in (self.rows, self.units, self.history):
            a.setflags(write=False)

    @property
    def n_s(self) -> int:
        """Number of selected units (rows, or groups)."""
        return int(self.units.size)


# --------------------------------------------------------------------------- validation


def _check_basis(U: Any, name: str = "U") -> np.ndarray:
    a = np.asarray(U)
    if a.ndim != 2 or a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"{name} must be a non-empty 2-D (n_lv, k) basis, got shape {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name} must be real numbers, got dtype {a.dtype}")
    a = np.asarray(a, dtype=np.float64)
    finite = np.isfinite(a)
    if not finite.all():
        i, j = (int(v) for v in np.argwhere(~finite)[0])
        raise ValueError(
            f"{name}[{i}, {j}] = {float(a[i, j])!r}: {name} must be finite "
            f"({int(a.size - finite.sum())} NaN/Inf values in it); fix the basis first"
        )
    return a


def _check_int(v: Any, name: str, minimum: int) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {v!r}")
    return int(v)


def _check_patch(patch: Any, n_rows: int) -> int:
    if patch is None:
        return 1
    p = _check_int(patch, "patch", 1)
    if n_rows % (p * p):
        raise ValueError(
            f"patch={p}: a patch basis has p**2 * n_lv rows (btfcore.model.abtf.patch_matrix), but U has {n_rows} "
            f"rows, not a multiple of {p * p}; pass the patch size the basis was fitted with"
        )
    return p


# --------------------------------------------------------------------------- units


@dataclass
class _Units:
    """The selectable units of a sampling problem: each a set of rows of the basis.

    ``A`` is the basis with one zero row appended; ``idx[u]`` are the rows of
    ``A`` measured when unit ``u`` is selected (padded with the zero row),
    ``members[u]`` its light/view rows (padded with -1), ``ids[u]`` its
    group id (or row index).
    """

    A: np.ndarray          # (N + 1, k)
    idx: np.ndarray        # (n_units, p*p*m)
    members: np.ndarray    # (n_units, m)
    ids: np.ndarray        # (n_units,)
    n_lv: int
    p: int

    @property
    def k(self) -> int:
        return self.A.shape[1]

    @property
    def n_units(self) -> int:
        return self.idx.shape[0]

    def rows_of(self, units: np.ndarray) -> np.ndarray:
        m = self.members[units].ravel()
        return np.sort(m[m >= 0])

    def gram(self, units: np.ndarray) -> np.ndarray:
        """:math:`\\sum_u A_u^T A_u`, ``(k, k)``."""
        Y = self.A[self.idx[np.atleast_1d(units)].ravel()]
        return Y.T @ Y

    def kappa_exact(self, units: np.ndarray) -> float:
        return _kappa_svd(self.A[self.idx[units].ravel()])


def _units(U: Any, groups: Any, patch: Any) -> _Units:
    A = _check_basis(U)
    N, k = A.shape
    p = _check_patch(patch, N)
    n_lv = N // (p * p)
    if groups is None:
        members = np.arange(n_lv, dtype=np.int64)[:, None]
        ids = np.arange(n_lv, dtype=np.int64)
    else:
        g = np.asarray(groups)
        if g.ndim != 1 or g.shape[0] != n_lv:
            what = "U.shape[0] / patch**2" if p > 1 else "U.shape[0]"
            raise ValueError(
                f"groups must be a 1-D array of one group id per light/view row, length {what} = {n_lv}, "
                f"got shape {g.shape}; build it from (turntable, LED) with all cameras sharing an id"
            )
        if not np.issubdtype(g.dtype, np.integer):
            if np.issubdtype(g.dtype, np.floating) and np.isfinite(g).all() and np.all(g == np.round(g)):
                g = g.astype(np.int64)
            else:
                bad = int(np.argmax(~np.isfinite(g))) if g.dtype.kind == "f" else 0
                raise ValueError(f"groups must hold integer group ids, got dtype {g.dtype} "
                                 f"(groups[{bad}] = {g[bad]!r}); pass an int array")
        ids, inv, counts = np.unique(g, return_inverse=True, return_counts=True)
        m = int(counts.max())
        order = np.argsort(inv, kind="stable")
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        slot = np.arange(n_lv) - np.repeat(start, counts)
        members = np.full((ids.size, m), -1, dtype=np.int64)
        members[inv[order], slot] = order
        ids = ids.astype(np.int64)
    t = np.arange(p * p, dtype=np.int64)
    idx = t[None, :, None] * n_lv + members[:, None, :]          # rows t * n_lv + s, as abtf.patch_matrix
    idx = np.where(members[:, None, :] >= 0, idx, N).reshape(members.shape[0], -1)
    A = np.vstack([A, np.zeros((1, k))])
    return _Units(A=A, idx=idx, members=members, ids=ids, n_lv=n_lv, p=p)


def _check_n_s(n_s: Any, units: _Units) -> int:
    n_s = _check_int(n_s, "n_s", 1)
    what = "groups" if units.members.shape[1] > 1 or units.n_units != units.n_lv else "light/view rows"
    if n_s > units.n_units:
        raise ValueError(f"n_s={n_s} exceeds the {units.n_units} available {what}; pass n_s <= {units.n_units}")
    sizes = np.sort((units.members >= 0).sum(axis=1))[::-1]
    most = int(sizes[:n_s].sum()) * units.p ** 2
    if most < units.k:
        raise ValueError(
            f"n_s={n_s} {what} measure at most {most} rows of U, fewer than its k={units.k} columns: "
            f"M U has rank < k, kappa is infinite and unregularised reconstruction would be underdetermined; "
            f"pass a larger n_s (at least {int(np.searchsorted(np.cumsum(sizes) * units.p ** 2, units.k)) + 1}) "
            f"or a smaller basis, or reconstruct with Tikhonov regularisation (lambda Sigma^-1, paper 4 eq. 10)"
        )
    return n_s


# --------------------------------------------------------------------------- condition numbers


def _kappa_svd(Y: np.ndarray) -> float:
    s = linalg.svdvals(Y, check_finite=False)
    if s.size < Y.shape[1] or s[-1] <= s[0] * Y.shape[1] * np.finfo(np.float64).eps or s[0] == 0:
        return float("inf")
    return float(s[0] / s[-1])


def _kappa_gram(G: np.ndarray) -> float | None:
    """kappa from the eigenvalues of the Gram matrix, or None when that is not accurate enough."""
    return _kappa_from(np.linalg.eigvalsh(G))           # LAPACK syevd, as scipy's driver="evd", with less around it


def _kappa_from(w: np.ndarray) -> float | None:
    """kappa from the ascending eigenvalues of the Gram matrix, or None when they are not accurate enough."""
    if w[0] <= 0.0:
        return None
    kap = float(np.sqrt(w[-1] / w[0]))
    return kap if kap <= _GRAM_KAPPA_MAX else None


def _kappa(units: _Units, G: np.ndarray, sel: np.ndarray) -> float:
    kap = _kappa_gram(G)
    return units.kappa_exact(sel) if kap is None else kap


def selection_condition(U: np.ndarray, rows: np.ndarray, *, patch: int | None = None) -> float:
    """Condition number of the sparse measurement :math:`\\kappa(M U)` for a row selection.

    Parameters
    ----------
    U : (n_lv, k) or (p * p * n_lv, k) array_like
        Basis; for ``patch=p`` an ABTF basis with rows ordered as
        :func:`btfcore.model.abtf.patch_matrix` (row ``t * n_lv + s`` is pair ``s``
        of the patch's texel ``t``).
    rows : (n_s,) array_like of int
        Selected light/view rows (``M``'s ones), in ``range(n_lv)``.
    patch : int, optional
        Patch size ``p``.

    Returns
    -------
    kappa : float
        :math:`\\sigma_1 / \\sigma_k` of ``U[rows]``, or of
        ``U[[t * n_lv + s for t in range(p * p) for s in rows]]``, which are
        the non-zero rows of :math:`(I_{p^2} \\otimes M) U` (paper 1, §3.4); ``inf``
        when the rank is below ``k``.

    Notes
    -----
    .. math:: \\kappa(M U) = \\sigma_{max}(M U) / \\sigma_{min}(M U)

    Paper 1, §3.4 writes :math:`\\kappa(\\mathbf{1}_{p^2} \\otimes \\mathbf{M}\\mathbf{U})`;
    :math:`\\mathbf{1}` is the identity (see :func:`btfcore.model.abtf.patch_matrix`).
    """
    A = _check_basis(U)
    p = _check_patch(patch, A.shape[0])
    n_lv = A.shape[0] // (p * p)
    r = _check_rows(rows, n_lv, "rows")
    sel = (np.arange(p * p)[:, None] * n_lv + r[None, :]).ravel()    # rows of (I_{p^2} kron M) U_patch
    return _kappa_svd(A[sel])


def _check_rows(rows: Any, n: int, name: str) -> np.ndarray:
    r = np.asarray(rows)
    if r.ndim != 1 or r.size == 0 or not np.issubdtype(r.dtype, np.integer):
        raise ValueError(f"{name} must be a non-empty 1-D integer array of row indices, got {r.dtype} {r.shape}")
    bad = np.flatnonzero((r < 0) | (r >= n))
    if bad.size:
        raise ValueError(f"{name}[{int(bad[0])}] = {int(r[bad[0]])} is out of range(0, {n}); pass valid row indices")
    return r.astype(np.int64)


# --------------------------------------------------------------------------- random swap (paper 1, Alg. 1)


def random_swap(
    U: np.ndarray,
    n_s: int,
    *,
    groups: np.ndarray | None = None,
    max_steps: int = 10_000,
    seed: int = 0,
    patch: int | None = None,
    patience: int | None = None,
    start: np.ndarray | None = None,
) -> SamplingResult:
    """Matusik et al.'s random-swap minimisation of :math:`\\kappa(M U)` (paper 1, Alg. 1).

    Parameters
    ----------
    U : (n_lv, k) or (p * p * n_lv, k) array_like
        Basis (for ``patch=p`` an ABTF basis, rows as :func:`btfcore.model.abtf.patch_matrix`).
    n_s : int
        Light/view rows to select, or groups with ``groups``.
    groups : (n_lv,) array_like of int, optional
        Group id of every light/view row; a group is selected or not as a
        whole (camera-parallel sampling, paper 4, §5.2: the id of
        ``(turntable, LED)``, shared by all cameras).
    max_steps : int
        Trial swaps.
    seed : int
        Seed of the random start and of the swaps.
    patch : int, optional
        Patch size ``p`` of an ABTF basis: minimise
        :math:`\\kappa((I_{p^2} \\otimes M) U)`.
    patience : int, optional
        Stop after this many consecutive rejected trial swaps ("until
        convergence"); default: run all ``max_steps``.
    start : (n_s,) array_like of int, optional
        Initial units (rows, or group ids) instead of a random start.

    Returns
    -------
    SamplingResult
        ``history`` has ``steps + 1`` entries, non-increasing.

    Raises
    ------
    ValueError
        If ``U`` holds NaN/Inf (names the entry), ``n_s`` exceeds the
        available rows/groups or measures fewer than ``k`` rows (the system
        would be underdetermined), ``groups`` has the wrong length, or
        ``patch`` does not divide ``U``'s rows.

    Notes
    -----
    Alg. 1: start from ``n_s`` distinct random units; a step replaces one
    random selected unit by a random unselected one and reverts the change
    when :math:`\\kappa(M' U) < \\kappa(M U)` for the previous ``M'``, i.e.
    keeps it when kappa does not increase (a tie is kept; the prose of §3.4
    says "does not decrease ... reverted", which would reject ties: we
    follow the algorithm box). Kappa is evaluated from the ``k x k`` Gram
    matrix :math:`G = (MU)^T MU`, updated by the two units' rank-m terms,
    :math:`\\kappa = \\sqrt{\\lambda_{max}(G) / \\lambda_{min}(G)}`; above
    1e5 (where squaring costs accuracy) from the singular values of ``M U``.
    The reported ``kappa`` is always from the singular values.

    References
    ----------
    .. [1] Thesis, App. paper 1 (den Brok et al.), §3.4 and Alg. 1; paper 4, §4.3.
    """
    units = _units(U, groups, patch)
    n_s = _check_n_s(n_s, units)
    max_steps = _check_int(max_steps, "max_steps", 0)
    if patience is not None:
        patience = _check_int(patience, "patience", 1)
    rng = np.random.default_rng(seed)
    n = units.n_units
    if start is None:
        sel = rng.choice(n, size=n_s, replace=False)                                # Alg. 1: random M
    else:
        sel = _start_units(start, units, n_s)
    mask = np.zeros(n, dtype=bool)
    mask[sel] = True
    rest = np.flatnonzero(~mask)
    G = units.gram(sel)
    kap = _kappa(units, G, sel)
    history = [kap]
    accepted = since = 0
    converged = False
    steps = 0
    for steps in range(1, max_steps + 1):
        if rest.size == 0:
            steps -= 1
            break
        i = int(rng.integers(n_s))                                                 # Alg. 1: random row of M
        j = int(rng.integers(rest.size))                                           # Alg. 1: random unit row r
        out, inn = sel[i], rest[j]
        G_new = G - units.gram(out) + units.gram(inn)
        sel[i] = inn
        k_new = _kappa(units, G_new, sel)
        if k_new <= kap:                                                           # Alg. 1: revert if kappa grew
            G, kap = G_new, k_new
            rest[j] = out
            accepted += 1
            since = 0
            if accepted % _REFRESH == 0:
                G = units.gram(sel)
        else:
            sel[i] = out
            since += 1
        history.append(kap)
        if patience is not None and since >= patience:
            converged = True
            break
    sel = np.sort(sel)
    settings = {"n_s": n_s, "max_steps": max_steps, "seed": int(seed), "patch": units.p,
                "groups": groups is not None, "patience": patience, "start": start is not None}
    return SamplingResult(rows=units.rows_of(sel), units=units.ids[sel], kappa=units.kappa_exact(sel),
                          history=np.asarray(history), method="random_swap", steps=steps,
                          accepted=accepted, converged=converged, settings=settings)


def _start_units(start: Any, units: _Units, n_s: int) -> np.ndarray:
    s = np.asarray(start)
    if s.ndim != 1 or s.size != n_s or not np.issubdtype(s.dtype, np.integer):
        raise ValueError(f"start must be {n_s} integer unit ids (rows, or group ids), got {s.dtype} {s.shape}")
    pos = np.searchsorted(units.ids, s)
    pos = np.minimum(pos, units.n_units - 1)
    bad = np.flatnonzero(units.ids[pos] != s)
    if bad.size:
        raise ValueError(f"start[{int(bad[0])}] = {int(s[bad[0]])} is not a row index / group id of this problem")
    if np.unique(pos).size != n_s:
        raise ValueError("start holds repeated units; pass distinct rows or group ids")
    return pos.astype(np.int64)


# --------------------------------------------------------------------------- greedy (beyond the thesis)


def _pivoted_start(units: _Units) -> list[int]:
    """Block-pivoted Gram-Schmidt: units with the largest residual energy until rank k (QRCP of U^T)."""
    A, idx, k = units.A, units.idx, units.k
    res = np.einsum("ij,ij->i", A, A)                        # squared residual norms of all rows
    scale = float(res.max()) if res.size else 0.0
    Q = np.zeros((k, 0))
    chosen: list[int] = []
    taken = np.zeros(units.n_units, dtype=bool)
    while Q.shape[1] < k:
        energy = res[idx].sum(axis=1)
        energy[taken] = -1.0
        u = int(np.argmax(energy))
        if energy[u] <= 1e-12 * scale:
            break
        chosen.append(u)
        taken[u] = True
        R = A[idx[u]].T                                      # (k, m)
        R = R - Q @ (Q.T @ R)
        R = R - Q @ (Q.T @ R)                                # re-orthogonalise (CGS2)
        q, r, piv = linalg.qr(R, mode="economic", pivoting=True)
        d = np.abs(np.diag(r)) if r.size else np.zeros(0)
        keep = int(np.sum(d > 1e-10 * np.sqrt(scale)))
        q = q[:, :keep]
        if keep:
            Q = np.hstack([Q, q])
            proj = A @ q                                      # (N + 1, keep)
            res = np.maximum(res - np.einsum("ij,ij->i", proj, proj), 0.0)
    return chosen


def _start(units: _Units, n_s: int, seed: int) -> np.ndarray:
    """Seeded random start; if it has rank < k, the pivoted units replace random ones."""
    sel = np.random.default_rng(seed).choice(units.n_units, size=n_s, replace=False)
    if np.isfinite(units.kappa_exact(sel)):
        return sel
    piv = np.asarray(_pivoted_start(units)[:n_s], dtype=np.int64)
    rest = sel[~np.isin(sel, piv)][: n_s - piv.size]
    return np.concatenate([piv, rest])


def _soft_weights(w: np.ndarray, q: float) -> np.ndarray:
    """d f / d lambda_i of f = log ||lambda||_q + log ||1/lambda||_q, a smooth log kappa^2."""
    x = (w / w[-1]) ** q
    y = (w[0] / w) ** q
    return x / (w * x.sum()) - y / (w * y.sum())


def _soft_objective(w: np.ndarray, q: float) -> float:
    """f = log ||lambda||_q + log ||1/lambda||_q, a smooth upper bound of log kappa^2 (q -> inf: equal)."""
    if w[0] <= 0.0:
        return float("inf")
    return float(np.log(np.sum((w / w[-1]) ** q)) / q + np.log(np.sum((w[0] / w) ** q)) / q + np.log(w[-1] / w[0]))


def _best(values: np.ndarray, pool: np.ndarray, m: int) -> np.ndarray:
    """The ``m`` units of ``pool`` with the smallest ``values``, ascending (ties by index)."""
    v = values[pool]
    if m < pool.size:
        part = np.argpartition(v, m - 1)[:m]
        pool, v = pool[part], v[part]
    return pool[np.lexsort((pool, v))]


def _batched(units: _Units, sel: np.ndarray, max_steps: int, q: float) -> np.ndarray:
    """Construction: swaps of ``b`` units at once guided by the first-order change of the smooth objective.

    A step swaps the ``b`` selected units whose removal and the ``b`` unselected units whose
    addition lower ``f`` most to first order, and is kept if ``f`` decreases exactly; ``b``
    starts at ``min(n_s, n - n_s) / 8``, doubles after a success, halves after a failure, and
    the phase ends when it reaches 1 (single swaps are :func:`_exchange`'s).
    """
    A, idx = units.A, units.idx
    n = units.n_units
    mask = np.zeros(n, dtype=bool)
    mask[sel] = True
    G = units.gram(sel)
    w, V = linalg.eigh(G, check_finite=False, driver="evd")
    cur = _soft_objective(w, q)
    b_max = max(1, min(sel.size, n - sel.size) // 8)
    b = b_max
    steps = 0
    while steps < max_steps and b > 1 and w[0] > 0.0:
        J = _extreme(w, q, 8)
        P = A @ V[:, J]                                        # projections on the extreme eigenvectors
        su = ((P * P) @ _soft_weights(w, q)[J])[idx].sum(axis=1)   # first-order change of f when adding a unit
        inn = _best(su, np.flatnonzero(~mask), b)              # adding lowers f most first
        out = _best(-su, np.flatnonzero(mask), b)              # removing lowers f most first
        m = min(b, inn.size, out.size)
        if m == 0 or su[inn[m - 1]] - su[out[m - 1]] >= 0:
            b //= 2
            continue
        G_new = G - units.gram(out[:m]) + units.gram(inn[:m])
        w_new, V_new = linalg.eigh(G_new, check_finite=False, driver="evd")
        new = _soft_objective(w_new, q)
        steps += 1
        if new < cur:
            sel = np.concatenate([sel[~np.isin(sel, out[:m])], inn[:m]])
            G, cur, w, V = G_new, new, w_new, V_new
            mask[out[:m]], mask[inn[:m]] = False, True
            b = min(2 * b, b_max)
        else:
            b //= 2
    return sel


def _end_ritz(w: np.ndarray, X: np.ndarray, sign: np.ndarray, m: int, high: bool, iters: int = 2) -> np.ndarray:
    r"""Predicted ``m`` extreme eigenvalues of ``G + X^T S X`` for a batch of low-rank updates.

    Parameters
    ----------
    w : (k,) ndarray
        Ascending eigenvalues of ``G``.
    X : (..., n, k) ndarray
        Per update, the rows added (``sign`` +1) or removed (-1), in ``G``'s
        eigenvector coordinates; zero rows are allowed (padding).
    sign : (n,) ndarray
        The diagonal of ``S``.
    m : int
        End eigenvalues kept (``1 <= m < k``).
    high : bool
        The largest (True) or smallest end.

    Returns
    -------
    (..., m) ndarray, ascending.

    Notes
    -----
    Rayleigh-Ritz on the ``m`` end eigenvectors ``E_L`` of ``G`` and the ``n``
    vectors :math:`Z = (\Lambda_C - \mu)^{-1} X_C^T` (``C`` the other
    eigenvectors), with ``mu`` the current estimate of the new extreme
    eigenvalue, started at its Weyl bound. At the exact ``mu`` the new extreme
    eigenvector lies in this subspace (it is :math:`(\mu - \Lambda)^{-1} X^T S X v`),
    so the iteration converges to it (about 1e-6 relative after two steps,
    1e-13 after three, measured); a Ritz value is an inner bound. Everything
    is formed from ``n x n`` moments :math:`X_C D^j X_C^T`,
    :math:`D = (\Lambda_C - \mu)^{-1}`: ``O(n^2 k + n^3)`` per update
    instead of an ``O(k^3)`` eigenproblem.
    """
    k = w.size
    L = np.arange(k - m, k) if high else np.arange(m)
    C = np.arange(0, k - m) if high else np.arange(m, k)
    n = X.shape[-2]
    wC = w[C]
    XL, XC = X[..., L], X[..., C]
    norms = np.sum(X * X, axis=-1)                             # (..., n)
    if high:                                                   # Weyl bounds: start beyond the new extreme
        mu = w[-1] + np.sum(norms * (sign > 0), axis=-1)
    else:
        mu = w[0] - np.sum(norms * (sign < 0), axis=-1)
    neutral = w[k // 2]
    diag = np.arange(n)
    XLt_s = np.swapaxes(XL, -1, -2) * sign                     # (..., m, n): E_L^T X^T S
    HLL = XLt_s @ XL
    HLL[..., np.arange(m), np.arange(m)] += w[L]
    ev = np.zeros(X.shape[:-2] + (m,))
    XCt = np.swapaxes(XC, -1, -2)
    failed = np.zeros(X.shape[:-2], bool)                      # moments that overflowed (near-singular G)
    for _ in range(iters):
        gap = wC - mu[..., None]
        gap = np.where(np.abs(gap) < 1e-300, 1e-300, gap)
        d = 1.0 / gap                                          # (..., |C|)
        with np.errstate(over="ignore", invalid="ignore"):
            XCd = XC * d[..., None, :]
            F1 = XCd @ XCt                                     # X_C D X_C^T = X_C Z
            F2 = (XCd * wC) @ np.swapaxes(XCd, -1, -2)         # Z^T Lambda Z
            F3 = XCd @ np.swapaxes(XCd, -1, -2)                # Z^T Z
        bad = ~(np.isfinite(F1).all((-2, -1)) & np.isfinite(F2).all((-2, -1)) & np.isfinite(F3).all((-2, -1)))
        if bad.any():                                          # no prediction: these pairs are ranked last
            failed |= bad
            F1[bad], F2[bad], F3[bad] = 0.0, 0.0, np.eye(n)
        e3, V3 = np.linalg.eigh(F3)                            # whitening of Z (rank-deficient: drop)
        ok = e3 > 1e-10 * np.maximum(e3[..., -1:], 1e-300)
        T = V3 * np.where(ok, 1.0 / np.sqrt(np.where(ok, e3, 1.0)), 0.0)[..., None, :]
        HLZ = XLt_s @ F1 @ T                                   # E_L^T X^T S X Z T
        HZZ = np.swapaxes(T, -1, -2) @ (F2 + (F1 * sign) @ F1) @ T   # T^T Z^T (Lambda + X^T S X) Z T
        HZZ[..., diag, diag] += np.where(ok, 0.0, neutral)     # dropped directions: decoupled, neutral
        H = np.concatenate([np.concatenate([HLL, HLZ], axis=-1),
                            np.concatenate([np.swapaxes(HLZ, -1, -2), HZZ], axis=-1)], axis=-2)
        full = np.linalg.eigvalsh(H)
        ev = full[..., -m:] if high else full[..., :m]
        mu = ev[..., -1] if high else ev[..., 0]
    ev[failed] = np.inf if high else 0.0                       # predicted kappa: infinite
    return ev


def _predicted(w: np.ndarray, lo: np.ndarray, hi: np.ndarray, q: float, soft: bool) -> np.ndarray:
    """Objective (kappa, or the smooth f) of the predicted spectra [lo, w[m:-m], hi] of every pair."""
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        return _predicted_unchecked(w, lo, hi, q, soft)


def _predicted_unchecked(w: np.ndarray, lo: np.ndarray, hi: np.ndarray, q: float, soft: bool) -> np.ndarray:
    lam_min = np.maximum(lo[..., 0], 1e-300)
    lam_max = hi[..., -1]
    if not soft:
        return np.where(lo[..., 0] > 0, np.sqrt(lam_max / lam_min), np.inf)
    m = lo.shape[-1]
    mid = w[m:w.size - m]
    x = (np.sum((lo / lam_max[..., None]) ** q, -1) + np.sum((mid / lam_max[..., None]) ** q, -1)
         + np.sum((hi / lam_max[..., None]) ** q, -1))
    y = (np.sum((lam_min[..., None] / lo) ** q, -1) + np.sum((lam_min[..., None] / mid) ** q, -1)
         + np.sum((lam_min[..., None] / hi) ** q, -1))
    f = np.log(x) / q + np.log(y) / q + np.log(lam_max / lam_min)
    return np.where((lo[..., 0] > 0) & np.isfinite(f), f, np.inf)


def _extreme(w: np.ndarray, q: float, m: int) -> np.ndarray:
    """Indices of the at most ``m`` lowest and ``m`` highest eigenvalues whose smooth-objective weight counts."""
    wt = np.abs(_soft_weights(w, q))
    ends = np.unique(np.concatenate([np.arange(min(m, w.size)), np.arange(max(0, w.size - m), w.size)]))
    return ends[wt[ends] > _JTOL * wt.max()]


def _candidates(values: np.ndarray, pool: np.ndarray, width: int, rng: np.random.Generator) -> np.ndarray:
    """``width`` units of ``pool``: the half with the smallest ``values``, the rest drawn at random."""
    best = _best(values, pool, max(1, width // 2))
    rest = np.setdiff1d(pool, best, assume_unique=True)
    extra = rng.choice(rest, size=min(rest.size, width - best.size), replace=False) if rest.size else rest
    return np.concatenate([best, np.sort(extra)]).astype(np.int64)


def _exchange(units: _Units, sel: np.ndarray, max_steps: int, width: int, n_ext: int, q: float,
              soft: bool = False, tries: int = 3, seed: int = 0,
              pairs: int = 16, scan: int = 2048,
              progress: Callable[[str, int, float], None] | None = None, phase: str = "",
              rounds: int = 4) -> tuple[np.ndarray, list[float], bool]:
    """Single swaps chosen by exactly predicted extreme eigenvalues (phases 3 and 4 of :func:`greedy`).

    Candidates: ``width`` units to add and ``width`` to remove (:func:`_candidates`: half the
    best by the first-order change of the smooth objective over ``scan`` drawn unselected units
    and all selected ones, half at random). Each addition and each removal alone, then the
    ``pairs`` best pairs by the sum of the two changes, are predicted by :func:`_end_ritz`; the
    best predicted pairs (up to ``tries``) are evaluated exactly and the first that lowers the
    objective (``soft``: the smooth f, else kappa) is kept. A round without one is retried with
    a fresh draw and twice the pairs; after ``rounds`` such rounds the phase stops
    (``converged``), or after ``max_steps`` accepted swaps.
    """
    A, idx = units.A, units.idx
    k, r = units.k, idx.shape[1]
    rng = np.random.default_rng(seed)
    mask = np.zeros(units.n_units, dtype=bool)
    mask[sel] = True
    sel = sel.copy()
    G = units.gram(sel)
    w, V = linalg.eigh(G, check_finite=False, driver="evd")

    def objective(w_: np.ndarray, trial: np.ndarray) -> float:
        if soft:
            return _soft_objective(w_, q)
        kap = _kappa_from(w_)
        return units.kappa_exact(trial) if kap is None else kap

    cur = objective(w, sel)
    history = [_kappa(units, G, sel)]
    if k < 2:
        return sel, history, True
    m = max(1, min(n_ext, k // 2))

    converged = False
    steps = failed = 0
    while steps < max_steps:
        if w[0] <= 0.0:
            break
        J = _extreme(w, q, m)
        pool_in = np.flatnonzero(~mask)
        if pool_in.size > scan:                                # first-order scan of a random subset
            pool_in = np.sort(rng.choice(pool_in, size=scan, replace=False))
        pool_out = np.flatnonzero(mask)
        look = np.concatenate([pool_in, pool_out])
        su = np.zeros(units.n_units)
        P = A[idx[look]] @ V[:, J]                             # (units, r, |J|)
        su[look] = ((P * P) @ _soft_weights(w, q)[J]).sum(axis=1)   # first-order change of f when adding
        inn = _candidates(su, pool_in, width, rng)
        out = _candidates(-su, pool_out, width, rng)
        Pi = A[idx[inn]] @ V                                   # (W, r, k) in G's eigenvector coordinates
        Po = A[idx[out]] @ V
        plus, minus = np.ones(r), -np.ones(r)

        def predict(Xs: np.ndarray, sign: np.ndarray) -> np.ndarray:
            n = Xs.shape[-2]
            if (m + n) ** 3 + n * n * k > k ** 3:              # large groups: the eigenproblem is cheaper
                full = np.linalg.eigvalsh(np.diag(w) + (np.swapaxes(Xs, -1, -2) * sign) @ Xs)
                return _predicted(w, full[..., :m], full[..., -m:], q, soft)
            return _predicted(w, _end_ritz(w, Xs, sign, m, False), _end_ritz(w, Xs, sign, m, True), q, soft)

        f_in = predict(Pi, plus)                               # each addition alone
        f_out = predict(Po, minus)                             # each removal alone
        est = (f_in - cur)[:, None] + (f_out - cur)[None, :]   # additive estimate of a swap's change
        top = np.argsort(est, axis=None, kind="stable")[:pairs << failed]    # wider after a failed round
        ti, to = np.divmod(top, out.size)
        inn, out = inn[ti], out[to]                            # the best estimated pairs, predicted exactly
        pred = predict(np.concatenate([Pi[ti], Po[to]], axis=1), np.concatenate([plus, minus]))
        found = False
        for t in np.argsort(pred, kind="stable")[:tries]:
            if not pred[t] < cur:
                break
            add, rem = int(inn[t]), int(out[t])
            G_new = G - units.gram(rem) + units.gram(add)
            trial = np.where(sel == rem, add, sel)
            w_new, V_new = linalg.eigh(G_new, check_finite=False, driver="evd")
            new = objective(w_new, trial)
            if new < cur:
                sel, G, cur, w, V = trial, G_new, new, w_new, V_new
                mask[rem], mask[add] = False, True
                found = True
                break
        if not found:
            failed += 1
            if failed >= rounds:                               # fresh random candidates, then give up
                converged = True
                break
            continue
        failed = 0
        steps += 1
        if steps % _REFRESH == 0:
            G = units.gram(sel)
            w, V = linalg.eigh(G, check_finite=False, driver="evd")
        history.append(cur if not soft else float(np.sqrt(w[-1] / w[0])))
        if progress is not None:
            progress(phase, steps, history[-1])
    return sel, history, converged


def _check_greedy_settings(max_steps: Any, candidates: Any, pairs: Any, scan: Any,
                           q: Any) -> tuple[int, int, int, int, float]:
    """:func:`greedy`'s step settings, checked: ``(max_steps, candidates, pairs, scan, q)``."""
    max_steps = _check_int(max_steps, "max_steps", 0)
    candidates = _check_int(candidates, "candidates", 2)
    pairs = _check_int(pairs, "pairs", 1)
    scan = _check_int(scan, "scan", 1)
    if not q >= 1:
        raise ValueError(f"q must be >= 1 (the norm of the smooth kappa), got {q!r}")
    return max_steps, candidates, pairs, scan, float(q)


def greedy(
    U: np.ndarray,
    n_s: int,
    *,
    groups: np.ndarray | None = None,
    patch: int | None = None,
    max_steps: int = 2000,
    candidates: int = 32,
    pairs: int = 16,
    scan: int = 2048,
    q: float = 32.0,
    seed: int = 0,
    progress: Callable[[str, int, float], None] | None = None,
) -> SamplingResult:
    r"""Fast sampler: batched first-order swaps, then single swaps chosen by exact eigenvalue predictions.

    Not in the thesis; a faster replacement for :func:`random_swap` with the
    same objective (see ``benchmarks/bench_sampling.py``, ``docs/sampling.md``).

    Parameters
    ----------
    U : (n_lv, k) or (p * p * n_lv, k) array_like
        Basis (for ``patch=p`` an ABTF basis, rows as :func:`btfcore.model.abtf.patch_matrix`).
    n_s : int
        Light/view rows to select, or groups with ``groups``.
    groups : (n_lv,) array_like of int, optional
        Group id of every light/view row (camera-parallel sampling), as
        for :func:`random_swap`.
    patch : int, optional
        Patch size of an ABTF basis.
    max_steps : int
        Most steps of each phase (0: keep the start).
    candidates : int
        Units considered for addition and for removal in a single-swap step
        (half the best by first-order change, half drawn at random).
    pairs : int
        (add, remove) pairs whose new extreme eigenvalues are predicted
        exactly per step (the best by the sum of the two single changes).
    scan : int
        Unselected units whose first-order change is computed per step (a
        seeded random subset when there are more).
    q : float
        Norm of the smooth kappa of the first phases (larger: closer to kappa,
        less smooth).
    seed : int
        Seed of the random start and of the candidate draws; the result is a
        function of the inputs and the seed.
    progress : callable, optional
        Called as ``progress(phase, step, kappa)`` after every accepted step.

    Returns
    -------
    SamplingResult
        ``history``: kappa at the start of the last phase and after every
        accepted step of it (strictly decreasing); ``steps``: accepted steps
        of all phases.

    Raises
    ------
    ValueError
        As :func:`random_swap`, and on ``q < 1``.

    Notes
    -----
    With :math:`G = (MU)^T MU = V \Lambda V^T` and the smooth

    .. math:: f = \log\|\lambda\|_q + \log\|\lambda^{-1}\|_q \ge \log\kappa^2
              \quad (= \text{ as } q \to \infty),

    adding unit ``u`` (rows :math:`a_r`) changes ``f`` by about
    :math:`s_u = \sum_{r \in u} \sum_i \partial f / \partial\lambda_i\,(v_i^T a_r)^2`
    (the extreme eigenvectors only), removing it by :math:`-s_u`.

    1. *Start*: ``n_s`` seeded random units (as Alg. 1); if they have rank
       below ``k``, the units of a block-pivoted Gram-Schmidt of the basis
       (column-pivoted QR of :math:`U^T`, Businger & Golub) replace some.
    2. *Construction*: swap the ``b`` selected units of largest :math:`s_u`
       for the ``b`` unselected ones of smallest :math:`s_u`, kept if ``f``
       decreases; ``b`` from :math:`n_s / 8`, halving on failure, doubling
       on success, until 1.
    3. *Exchange on f*, then 4. *exchange on kappa*: a step takes
       ``candidates`` units to add and to remove, predicts the change of
       each alone, and for the ``pairs`` best pairs the new extreme
       eigenvalues of :math:`G + B B^T - A A^T` exactly
       (:func:`_end_ritz`: Rayleigh-Ritz on the end eigenvectors of ``G``
       and :math:`(\Lambda_C - \mu)^{-1} V_C^T a`, iterated on the shift,
       :math:`O(k)` per pair instead of an :math:`O(k^3)` eigenproblem);
       the best predicted swap is checked with one eigendecomposition and
       kept if the objective decreases (else the next, up to 3). A phase
       stops when no predicted pair improves (``converged``).

    Unlike Alg. 1, which spends one eigenvalue computation per random trial
    swap, each step spends one on the best of ``pairs`` exactly predicted
    swaps, which is why it needs far fewer of them.
    """
    units = _units(U, groups, patch)
    n_s = _check_n_s(n_s, units)
    max_steps, candidates, pairs, scan, q = _check_greedy_settings(max_steps, candidates, pairs, scan, q)
    sel = _start(units, n_s, seed)
    sel = _batched(units, sel, max_steps, q)                                          # construction
    if progress is not None:
        progress("construction", 0, units.kappa_exact(sel))
    steps = 0
    converged = True
    history: list[float] = []
    for phase, soft in (("exchange-f", True), ("exchange-kappa", False)):
        sel, history, converged = _exchange(units, sel, max_steps, candidates, 8, q, soft=soft, seed=seed,
                                            pairs=pairs, scan=scan, progress=progress, phase=phase)
        steps += len(history) - 1
    sel = np.sort(sel)
    settings = {"n_s": n_s, "max_steps": max_steps, "candidates": candidates, "pairs": pairs, "scan": scan,
                "q": q, "seed": int(seed), "patch": units.p, "groups": groups is not None}
    return SamplingResult(rows=units.rows_of(sel), units=units.ids[sel], kappa=units.kappa_exact(sel),
                          history=np.asarray(history), method="greedy", steps=steps,
                          accepted=steps, converged=converged, settings=settings)


# --------------------------------------------------------------------------- parabolic map (paper 1, Fig. 3b)


def parabolic_map_grid(n: int = 7) -> np.ndarray:
    """Directions of the ``n x n`` parabolic-map grid points that lie in the hemisphere disc.

    Parameters
    ----------
    n : int
        Grid size (paper 1: 7).

    Returns
    -------
    dirs : (m, 3) ndarray of float64
        The centres :math:`x_i = (2 i + 1)/n - 1` of an ``n x n`` grid of cells
        covering :math:`[-1, 1]^2`, row-major, those with
        :math:`x^2 + y^2 \\le 1` mapped back to the hemisphere; points
        outside the disc (below the horizon) are dropped. ``n = 7`` gives
        37 points, hence :math:`37^2 = 1369` pairs, the thesis' "1369
        samples ... 6 % of the original 22801".

    Notes
    -----
    Inverse of :func:`btfcore.capture.resample.parabolic_map`:

    .. math:: d = \\frac{(2x, 2y, 1 - x^2 - y^2)}{1 + x^2 + y^2}
    """
    n = _check_int(n, "n", 1)
    c = (2.0 * np.arange(n) + 1.0) / n - 1.0
    y, x = np.meshgrid(c, c, indexing="ij")
    x, y = x.ravel(), y.ravel()
    r2 = x * x + y * y
    keep = r2 <= 1.0 + 1e-12                                   # outside the disc: below the horizon, dropped
    x, y, r2 = x[keep], y[keep], np.minimum(r2[keep], 1.0)
    return np.stack([2 * x, 2 * y, 1 - r2], axis=1) / (1 + r2)[:, None]


def parabolic_map_sampling(light_dirs: np.ndarray, view_dirs: np.ndarray, n: int = 7) -> np.ndarray:
    """The n x n parabolic-map heuristic: grid directions snapped to the nearest measured ones.

    Parameters
    ----------
    light_dirs, view_dirs : (n_lv, 3) array_like
        Light and view direction of every light/view row (e.g. from
        :func:`btfcore.capture.resample.lv_product`), upper hemisphere.
    n : int
        Grid size (paper 1: 7).

    Returns
    -------
    rows : (n_rows,) ndarray of intp
        Sorted indices of the rows whose light is one of the chosen lights
        and whose view is one of the chosen views. For a full light x view
        product that is (chosen lights) x (chosen views); with ``n = 7`` on
        the UBO2014 151 x 151 sampling, 37 x 37 = 1369 rows.

    Raises
    ------
    ValueError
        On malformed directions (names the index) or length mismatch.

    Notes
    -----
    Paper 1, §4.2 and Fig. 3b: "a 7x7 parabolic map mapped to the closest
    light and camera positions of the acquisition setup's full sampling".
    The grid is :func:`parabolic_map_grid`; grid points outside the unit
    disc (below the horizon) are dropped. Each remaining grid direction is
    snapped to the closest distinct light (and, separately, view) direction
    by angle on the sphere (Euclidean distance of unit vectors); grid points
    that snap to the same direction give it once. Directions within
    :data:`btfcore.capture.resample.DIRECTION_TOL` count as one. The same views are
    used for every light, so a camera dome keeps its parallelism (thesis
    ch. 2.1, the summary of paper 1: "one and the same subset of the available cameras is used
    throughout").
    """
    L = _as_dirs(light_dirs, "light_dirs")
    V = _as_dirs(view_dirs, "view_dirs")
    if L.shape != V.shape:
        raise ValueError(f"light_dirs {L.shape} and view_dirs {V.shape} must both be (n_lv, 3), one per row")
    grid = parabolic_map_grid(n)
    chosen = []
    for D in (L, V):
        uniq, inverse = unique_directions(D, DIRECTION_TOL)
        dist = np.linalg.norm(grid[:, None, :] - uniq[None, :, :], axis=2)
        near = np.argmin(dist, axis=1)                         # closest available direction per grid point
        chosen.append(np.isin(inverse, np.unique(near)))
    return np.flatnonzero(chosen[0] & chosen[1])


# --------------------------------------------------------------------------- multiplexing (paper 4, §4.3)


def multiplexed_basis(S: np.ndarray, U: np.ndarray, sigma: np.ndarray | None = None) -> np.ndarray:
    """The basis seen through illumination patterns: :math:`(I_{n_v} \\otimes S)\\, U\\, \\Sigma`.

    Parameters
    ----------
    S : (n_p, n_l) array_like
        Illumination patterns (rows) over the lights (columns), e.g.
        :func:`btfcore.acquisition.hadamard.multiplexing_patterns`; any real weights.
    U : (n_v * n_l, k) array_like
        Basis whose rows are light/view pairs with the light index fastest,
        row ``v * n_l + l`` (:func:`btfcore.capture.resample.lv_product`; ``v`` runs
        over all (turntable, camera) views).
    sigma : (k,) array_like, optional
        Singular values :math:`\\Sigma` stored with the basis (paper 4, eq. 9);
        default: none (identity).

    Returns
    -------
    A : (n_v * n_p, k) ndarray of float64
        Row ``v * n_p + j``: pattern ``j`` seen from view ``v``. Sampling a
        multiplexed design is selecting rows of ``A``: pass it as ``U`` to
        :func:`select_samples` (with ``groups`` of ``(turntable, pattern)``
        for camera-parallel sampling).

    Raises
    ------
    ValueError
        If ``U``'s rows are not a multiple of ``n_l``, on NaN/Inf, or a
        ``sigma`` of the wrong length.
    """
    P = _check_basis(S, "S")
    A = _check_basis(U)
    n_p, n_l = P.shape
    n_lv, k = A.shape
    if n_lv % n_l:
        raise ValueError(
            f"U has {n_lv} rows, not a multiple of the {n_l} lights of S (S.shape = {P.shape}); U's rows must be "
            f"light/view pairs with the light fastest (row v * n_l + l)"
        )
    if sigma is not None:
        s = _check_basis(np.asarray(sigma).reshape(1, -1), "sigma").ravel()
        if s.size != k:
            raise ValueError(f"sigma must have one value per column of U ({k}), got {s.size}")
        A = A * s[None, :]                                     # U Sigma
    MU = np.einsum("pl,vlk->vpk", P, A.reshape(n_lv // n_l, n_l, k))   # (I_{n_v} kron S) U, per view
    return MU.reshape(-1, k)


def multiplexed_condition(S: np.ndarray, M_rows: np.ndarray, U: np.ndarray,
                          sigma: np.ndarray | None = None) -> float:
    """:math:`\\kappa` of a sparse multiplexed measurement (paper 4, §4.3).

    Parameters
    ----------
    S : (n_p, n_l) array_like
        Illumination patterns over the lights (the thesis' ``M`` restricted to one view).
    M_rows : (n_s,) array_like of int
        The measured (view, pattern) rows, indices ``v * n_p + j`` into the
        rows of :func:`multiplexed_basis` (the ones of the thesis' selector ``S``).
    U : (n_v * n_l, k) array_like
        Basis, rows ``v * n_l + l``.
    sigma : (k,) array_like, optional
        Singular values of the basis (:math:`\\Sigma`).

    Returns
    -------
    kappa : float
        :math:`\\kappa(S_{sel} (I_{n_v} \\otimes S) U \\Sigma)`; ``inf`` below rank ``k``.

    Notes
    -----
    Paper 4 writes the measurement as :math:`\\mathbf{S}\\mathbf{M}\\mathbf{B}`
    (eq. 4) and chooses the selector
    :math:`\\mathbf{S} \\in \\{0,1\\}^{n_s \\times n_{lv}}`, :math:`\\mathbf{S}\\mathbf{S}^T = \\mathbf{I}`,
    to minimise :math:`\\kappa(\\mathbf{S}\\mathbf{M}\\mathbf{U}\\Sigma)` (§4.3).
    ``M`` multiplexes lights only (a view is a camera, the light pattern
    changes), so it is block diagonal, one block of the pattern matrix per
    view: :math:`\\mathbf{M} = I_{n_v} \\otimes S` here, with this
    function's ``S`` the patterns (the S-matrix of :mod:`btfcore.acquisition.hadamard`),
    and the thesis' selector ``S`` is ``M_rows``. It selects *multiplexed*
    rows (view, pattern): with 199 Hadamard patterns for 198 LEDs, ``M`` has
    more rows than ``n_lv``, so ``M_rows`` ranges over ``n_v * n_p``.
    :math:`\\Sigma` scales column ``i`` of ``U`` by :math:`\\sigma_i`, so
    kappa weighs the directions by their energy, as the Tikhonov term
    :math:`\\lambda \\Sigma^{-1}` of eq. (10) does.
    """
    A = multiplexed_basis(S, U, sigma)
    rows = _check_rows(M_rows, A.shape[0], "M_rows")
    if np.unique(rows).size != rows.size:
        raise ValueError("M_rows holds repeated rows; a selector has distinct rows (S S^T = I)")
    return _kappa_svd(A[rows])                                 # kappa(S M U Sigma)


# --------------------------------------------------------------------------- dispatcher


def select_samples(
    U: np.ndarray,
    n_s: int | None,
    method: str = "greedy",
    *,
    groups: np.ndarray | None = None,
    patch: int | None = None,
    light_dirs: np.ndarray | None = None,
    view_dirs: np.ndarray | None = None,
    grid: int = 7,
    **kwargs: Any,
) -> SamplingResult:
    """Choose the rows of a sparse measurement by ``method``.

    Parameters
    ----------
    U : (n_lv, k) or (p * p * n_lv, k) array_like
        Basis.
    n_s : int or None
        Units to select; for ``'parabolic_map'`` the grid fixes the count,
        pass None (or the count it gives).
    method : {'greedy', 'random_swap', 'parabolic_map'}
        :func:`greedy`, :func:`random_swap` or :func:`parabolic_map_sampling`.
    groups, patch :
        As for :func:`random_swap` (``groups`` is ignored by the parabolic
        map, which keeps the same views for every light anyway).
    light_dirs, view_dirs : (n_lv, 3) array_like
        Per-row directions, for ``'parabolic_map'`` only.
    grid : int
        Grid size of ``'parabolic_map'``.
    **kwargs :
        Passed to the method (``max_steps``, ``seed``, ``candidates``, ...).

    Returns
    -------
    SamplingResult
    """
    if method == "greedy":
        return greedy(U, n_s, groups=groups, patch=patch, **kwargs)
    if method == "random_swap":
        return random_swap(U, n_s, groups=groups, patch=patch, **kwargs)
    if method == "parabolic_map":
        if light_dirs is None or view_dirs is None:
            raise ValueError("method='parabolic_map' needs light_dirs and view_dirs, one (n_lv, 3) row each")
        if kwargs:
            raise ValueError(f"method='parabolic_map' takes no {sorted(kwargs)}")
        rows = parabolic_map_sampling(light_dirs, view_dirs, grid)
        A = _check_basis(U)
        p = _check_patch(patch, A.shape[0])
        if len(np.asarray(light_dirs)) != A.shape[0] // (p * p):
            raise ValueError(f"light_dirs has {len(np.asarray(light_dirs))} rows, U has {A.shape[0] // (p * p)} "
                             f"light/view rows; pass one direction per row of U")
        if n_s is not None and n_s != rows.size:
            raise ValueError(f"the {grid} x {grid} parabolic map selects {rows.size} rows, not n_s={n_s}; "
                             f"pass n_s=None")
        return SamplingResult(rows=rows, units=rows.astype(np.int64), kappa=selection_condition(A, rows, patch=patch),
                              history=np.zeros(0), method="parabolic_map", converged=True,
                              settings={"grid": grid, "patch": p})
    raise ValueError(f"unknown sampling method {method!r}; choose one of {SAMPLING_METHODS}")
