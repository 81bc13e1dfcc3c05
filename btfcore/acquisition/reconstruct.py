"""Reconstruction of a full BTF from sparse and/or illumination-multiplexed measurements.

Every method here fits coefficients ``C`` of a linear basis ``U`` (``(n_lv, k)``,
docs/architecture.md, "Matrix convention") to a measurement ``G B`` and returns :math:`\\hat B = U C`. The
measurement operator ``G`` acts from the left and is built from two parts:

* a **row selection** ``rows`` (paper 1's :math:`\\mathbf M`, paper 4's
  :math:`\\mathbf S`, :math:`\\mathbf S \\mathbf S^T = \\mathbf I`): indices of
  the measured rows, in the order the measured chunk holds them;
* **illumination patterns** ``patterns`` (the ``(n_p, n_lights)`` binary
  pattern matrix of :mod:`btfcore.capture.demultiplex`, paper 4's :math:`\\mathbf M`
  restricted to one view): applied to every view, i.e.
  :math:`\\mathbf I_{n_{views}} \\otimes \\mathrm{patterns}` on ``B``'s rows,
  which are view-major with the light fastest (``lv_order``).

Note the clash of letters in the thesis: paper 1 and the VMV paper call the
*selection* :math:`\\mathbf M` resp. the *patterns* :math:`\\mathbf M`; paper 4
writes :math:`\\mathbf{SMB}` with :math:`\\mathbf S` the selection and
:math:`\\mathbf M` the patterns. The code says ``rows`` and ``patterns``.

Since the reconstruction is linear in the measurement, each method is split
into two steps so that the tasks layer can stream texel chunks:

1. :func:`solve_operator` (or :func:`abtf_operator`) builds a small
   :class:`SolveOperator` once per basis and sampling, in float64;
2. :func:`apply` maps a measured chunk ``(n_meas, m)`` to ``(n_lv, m)`` with
   one or two matrix products.

Methods (``method=``):

``'pinv'``
    Sparse: :math:`\\hat B = U (M U)^\\dagger \\tilde B` (paper 1, eq. (3)).
``'tikhonov'``
    Sparse with Nielsen et al.'s regulariser :math:`R = \\lambda \\Sigma^{-1}`
    (paper 4, eqs. (1) and (10) with the selection only).
``'direct'``
    Multiplexed (optionally sparse) without demultiplexing:
    :math:`V = ((SMU)^T SMU + R^T R)^{-1} (SMU)^T (SMB)` (paper 4, eq. (10)).
``'projection'``
    Multiplexed: :math:`U (U^T B_{demux})` (VMV paper, §4.1).
``'thresholded'``
    Multiplexed: :math:`U (\\tilde U^\\dagger \\tilde B_{demux})` without the
    textures whose variance lies above the 9th decile (VMV paper, §4.1).

ABTF patch bases (paper 1, §3.3, §4.1.2) have :func:`abtf_operator` and
:func:`reconstruct_abtf` (whole textures or bands of texture rows).

Every unregularised solve (``'pinv'``, ``'direct'`` with ``lam = 0``, the
reduced :math:`\tilde U` of ``'thresholded'``, the ABTF patch rows) whose
condition number exceeds :data:`btfcore.ILL_CONDITIONED_SOLVE` warns with a
:class:`btfcore.IllConditionedWarning` giving the figure and the fix
(docs/demultiplex-resample.md, "Ill-conditioned solves"); regularised ones
never do.

References
----------
.. [1] The thesis, App. paper 1 (den Brok et al.): D. den Brok, H. C.
   Steinhausen, M. B. Hullin and R. Klein, "Patch-based sparse reconstruction
   of material BTFs", Journal of WSCG 22, 2014, §3.1 eq. (3) and §4.1.2; the
   patch equation of the thesis' summary of it, ch. 2.1.
.. [2] The thesis, App. VMV paper: D. den Brok, H. C. Steinhausen and R. Klein,
   "Fast multiplexed acquisition of high-dynamic-range material appearance",
   Vision, Modeling & Visualization 2015, §4.1 (thresholded de-noising).
.. [3] App. paper 4, D. den Brok, M. Weinmann and R. Klein, "Rapid material
   capture through sparse and multiplexed measurements", Computers &
   Graphics 73, 2018, eqs. (1), (2), (4), (10) (§3-§4.4), λ values (§5.2,
   §5.3).
.. [4] J. B. Nielsen, H. W. Jensen and R. Ramamoorthi, "On optimal, minimal
   BRDF sampling for reflectance acquisition", ACM TOG 34(6), 2015.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import DTypeLike

from btfcore import warn_ill_conditioned
from btfcore.model._lowrank import check_finite
from btfcore.model.abtf import _patch_size, patch_grid, patch_matrix
from btfcore.model.colour import _as_float
from btfcore.capture.demultiplex import _as_patterns, demultiplex_operator

__all__ = [
    "LAMBDA_ALS",
    "LAMBDA_NIELSEN",
    "RECONSTRUCTION_METHODS",
    "THRESHOLD_DECILE",
    "THRESHOLD_FALLBACK_MARGIN",
    "SolveOperator",
    "abtf_halo",
    "abtf_operator",
    "apply",
    "coefficients",
    "measure",
    "measurement_matrix",
    "reconstruct",
    "reconstruct_abtf",
    "solve_operator",
    "texture_variance",
    "threshold_rows",
]

#: Methods of :func:`solve_operator` (``'pinv'`` and ``'tikhonov'`` also for :func:`abtf_operator`).
RECONSTRUCTION_METHODS: tuple[str, ...] = ("pinv", "tikhonov", "direct", "projection", "thresholded")
#: λ of :math:`R = \lambda \Sigma^{-1}` for Nielsen et al.'s log-mapped bases (paper 4 §5.2, after [4]).
LAMBDA_NIELSEN = 40.0
#: λ for the relative-error ALS bases of paper 4 (§5.2; also its multiplexed results, §5.3).
LAMBDA_ALS = 0.01
#: Textures whose variance lies above this decile are left out by ``'thresholded'`` (VMV paper §4.1).
THRESHOLD_DECILE = 9
#: ``'thresholded'`` falls back to the projection in the directions of the reduced basis :math:`\tilde U`
#: that are worse determined than the full basis by more than this factor (singular value below
#: :math:`s_{max}(\tilde U) / (M \kappa(U))`): docs/demultiplex-resample.md, "Thresholded fallback".
THRESHOLD_FALLBACK_MARGIN = 4.0


# --------------------------------------------------------------------------- the operator


@dataclass(frozen=True, eq=False)
class SolveOperator:
    """A reconstruction operator: :math:`\\hat B = U (R\\, y)` for a measured chunk ``y``.

    Attributes
    ----------
    coefficients : (k, n_meas) ndarray
        :math:`R`, mapping a measured chunk to basis coefficients. Read-only.
    basis : (n_out, k) ndarray
        :math:`U` (``n_out = n_lv``; ``p² n_lv`` for an ABTF patch basis). Read-only.
    fused : (n_out, n_meas) ndarray or None
        :math:`U R`, when :func:`apply` uses one GEMM instead of two (see
        :func:`solve_operator`, ``fused``). Read-only.
    method : str
        One of :data:`RECONSTRUCTION_METHODS`.
    lam : float
        λ of the regulariser :math:`\\lambda \\Sigma^{-1}` (0: none).
    rows : (n_sel,) ndarray of int64 or None
        The selected measurement rows (into ``n_lv``, or into the
        ``n_views * n_p`` multiplexed rows when patterns are given); None:
        all rows.
    dropped : (n_drop,) ndarray of int64 or None
        ``'thresholded'``: the rows of the demultiplexed BTF left out.
    condition : float
        Condition number of the system solved (:math:`\\kappa(GU)`, or of
        the regularised system :math:`[G U \\Sigma; \\lambda I]`); NaN for
        ``'projection'``.
    patch_size : int or None
        ``p`` for an ABTF operator (:func:`abtf_operator`), else None.
    fallback : int
        ``'thresholded'``: the directions of the reduced basis taken from the projection instead
        (:data:`THRESHOLD_FALLBACK_MARGIN`); 0 for a plain thresholded solve and other methods.
    """

    coefficients: np.ndarray
    basis: np.ndarray
    fused: np.ndarray | None
    method: str
    lam: float = 0.0
    rows: np.ndarray | None = None
    dropped: np.ndarray | None = None
    condition: float = float("nan")
    patch_size: int | None = None
    fallback: int = 0

    def __post_init__(self) -> None:
        for a in (self.coefficients, self.basis, self.fused, self.rows, self.dropped):
            if a is not None:
                a.setflags(write=False)

    @property
    def k(self) -> int:
        """Number of basis vectors."""
        return int(self.basis.shape[1])

    @property
    def n_meas(self) -> int:
        """Rows of a measured chunk."""
        return int(self.coefficients.shape[1])

    @property
    def n_out(self) -> int:
        """Rows of the reconstruction (``n_lv``, or ``p² n_lv`` for ABTF patches)."""
        return int(self.basis.shape[0])

    @property
    def dtype(self) -> np.dtype:
        """The precision :func:`apply` computes in."""
        return self.coefficients.dtype


# --------------------------------------------------------------------------- validation


def _as_basis(U, name: str = "U") -> np.ndarray:
    u = _as_float(U, name, ndim=(2,)).astype(np.float64, copy=False)
    if 0 in u.shape:
        raise ValueError(f"{name} must be a non-empty (n_lv, k) basis, got shape {u.shape}")
    return u


def _as_sigma(sigma, k: int) -> np.ndarray:
    if sigma is None:
        raise ValueError("sigma (the basis' singular values, (k,)) is needed for the regulariser lam * Sigma^-1; "
                         "pass the sigma stored with the basis, or lam=0")
    s = _as_float(sigma, "sigma", ndim=(1,)).astype(np.float64, copy=False)
    if s.shape != (k,):
        raise ValueError(f"sigma has shape {s.shape} but U has k={k} columns: pass the (k,) singular values of U")
    bad = np.flatnonzero(~(s > 0))
    if bad.size:
        raise ValueError(f"sigma[{bad[0]}] = {float(s[bad[0]])!r}: Sigma^-1 needs every singular value > 0; "
                         f"truncate U and sigma to their positive singular values")
    return s


def _as_lam(lam, method: str) -> float:
    if lam is None:
        if method == "tikhonov":
            raise ValueError(f"method='tikhonov' needs lam: LAMBDA_NIELSEN = {LAMBDA_NIELSEN} for log-mapped "
                             f"(Nielsen) bases, LAMBDA_ALS = {LAMBDA_ALS} for relative-error ALS bases (paper 4)")
        return 0.0
    v = float(lam)
    if not (np.isfinite(v) and v >= 0):
        raise ValueError(f"lam must be a finite number >= 0, got {lam!r}")
    if v > 0 and method not in ("tikhonov", "direct"):
        raise ValueError(f"method={method!r} has no regulariser; use method='tikhonov' (sparse) or 'direct' "
                         f"(multiplexed) for lam > 0")
    return v


def _as_rows(rows, n_total: int, what: str) -> np.ndarray | None:
    if rows is None:
        return None
    r = np.asarray(rows)
    if r.dtype == np.bool_:
        raise ValueError("rows must be integer indices of the measured rows in measurement order, not a mask; "
                         "pass np.flatnonzero(mask)")
    if r.ndim != 1 or r.size == 0 or r.dtype.kind not in "iu":
        raise ValueError(f"rows must be a non-empty 1-D array of integer row indices, got {r.dtype} shape {r.shape}")
    r = r.astype(np.int64)
    bad = np.flatnonzero((r < 0) | (r >= n_total))
    if bad.size:
        raise ValueError(f"rows[{bad[0]}] = {r[bad[0]]} is outside the {n_total} {what}; pass indices in "
                         f"[0, {n_total})")
    uniq, first, counts = np.unique(r, return_index=True, return_counts=True)
    if uniq.size < r.size:
        j = int(np.flatnonzero(counts > 1)[0])
        dup = int(np.flatnonzero(r == uniq[j])[1])
        raise ValueError(f"rows[{dup}] = {r[dup]} repeats rows[{first[j]}]: a selection measures each row once "
                         f"(S S^T = I); average repeated measurements before reconstructing")
    return r


def _views(n_lv: int, p: np.ndarray) -> int:
    n_lights = p.shape[1]
    if n_lv % n_lights:
        raise ValueError(f"{n_lv} rows (light/view pairs) are not a multiple of the {n_lights} lights (columns of "
                         f"patterns): rows must be (view, light) pairs, view-major with the light fastest")
    return n_lv // n_lights


def _multiplex_rows(X: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``kron(I_views, p) @ X`` for X ``(n_views * n_lights, m)``, without forming the Kronecker product."""
    n_views = _views(X.shape[0], p)
    return np.matmul(p.astype(X.dtype), X.reshape(n_views, p.shape[1], -1)).reshape(n_views * p.shape[0], -1)


# --------------------------------------------------------------------------- solves


def _rank_error(A: np.ndarray, s: np.ndarray, tol: float, what: str) -> ValueError:
    rank = int(np.sum(s > tol))
    return ValueError(
        f"{what} ({A.shape[0]} x {A.shape[1]}) has numerical rank {rank} < k={A.shape[1]} (smallest singular "
        f"value {s[-1]:.3g} of {s[0]:.3g}): the measured rows do not determine the k coefficients; measure "
        f"other or more rows, use fewer basis vectors, or regularise (lam > 0)")


#: What to do about an ill-conditioned unregularised solve (:func:`btfcore.warn_ill_conditioned`).
_FIX_PINV = ("regularise (method='tikhonov', or lam > 0 for 'direct'), measure better-spread rows (`btf sample` "
             "minimises the condition number), or use fewer basis vectors")


def _regularised_solve(A: np.ndarray, sigma: np.ndarray | None, lam: float, what: str,
                       hint: str, fix: str | None = None, *, warn: bool = True) -> tuple[np.ndarray, float]:
    """``R`` with ``C = R b`` the minimiser of ``||A C - b||² + ||lam Sigma^-1 C||²`` (lam = 0: ``A^+``);
    an unregularised one warns (:class:`btfcore.IllConditionedWarning`) with ``fix`` when its condition
    number exceeds :data:`btfcore.ILL_CONDITIONED_SOLVE` (unless ``warn`` is False: the caller decides); a
    regularised one is the fix and does not (its noise gain is at most ``1 / (2 lam)``)."""
    n_meas, k = A.shape
    if lam == 0.0:
        if n_meas < k:
            raise ValueError(
                f"{n_meas} measured rows for k={k} basis vectors: the system {what} is under-determined; "
                f"{hint}")
        Ua, s, Vt = np.linalg.svd(A, full_matrices=False)
        tol = max(A.shape) * np.finfo(np.float64).eps * s[0]
        if s[0] == 0 or s[-1] <= tol:
            raise _rank_error(A, s, tol, what)
        cond = float(s[0] / s[-1])
        if warn:
            warn_ill_conditioned(cond, what, fix or _FIX_PINV, stacklevel=4)
        return (Vt.T / s) @ Ua.T, cond                                # eq. (3) of paper 1: (M U)^+
    # Substitute C = Sigma D: ||A Sigma D - b||² + lam² ||D||², a ridge regression on A Sigma.
    As = A * sigma                                                    # A Sigma (paper 4, 4.3: kappa(S M U Sigma))
    Ua, s, Vt = np.linalg.svd(As, full_matrices=False)
    filt = s / (s * s + lam * lam)                                    # eq. (10): (As^T As + lam² I)^-1 As^T, by SVD
    R = (sigma[:, None] * (Vt.T * filt)) @ Ua.T                       # C = Sigma D
    smin = s[-1] if n_meas >= k else 0.0
    return R, float(np.sqrt((s[0] ** 2 + lam**2) / (smin**2 + lam**2)))  # regularised: never warns (the fix)


def _finish(R: np.ndarray, U: np.ndarray, fused: bool | None, dtype, **kw) -> SolveOperator:
    n_out, k = U.shape
    n_meas = R.shape[1]
    if fused is None:                                                 # fewer flops per texel wins
        fused = n_out * n_meas <= k * (n_out + n_meas)
    dt = np.dtype(dtype)
    if dt not in (np.float32, np.float64):
        raise ValueError(f"dtype must be float32 or float64, got {dt}")
    F = (U @ R).astype(dt) if fused else None
    return SolveOperator(coefficients=R.astype(dt), basis=U.astype(dt), fused=F, **kw)


def _thresholded_fallback(u: np.ndarray, kept: np.ndarray) -> tuple[np.ndarray, float, int] | None:
    r"""The thresholded solve with its badly determined directions taken from the projection, or None
    when every direction of ``U~ = u[kept]`` is within :data:`THRESHOLD_FALLBACK_MARGIN` of the full
    basis' conditioning: ``(R, condition, n_directions)``.

    With :math:`\tilde U = Q S W^T` and :math:`g` the directions with
    :math:`s_i\, M \kappa(U) \ge s_1` (:math:`b` the others),

    .. math:: C = W_g S_g^{-1} Q_g^T \tilde B + W_b W_b^T U^T B,

    so the well-determined directions are exactly the thresholded solve's (the dropped rows do not enter
    them) and the others the projection's (VMV §4.1), which uses every row; for data in the span of
    ``U`` both parts are exact, so the fallback adds no bias."""
    s_full = np.linalg.svd(u, compute_uv=False)
    if not s_full[-1] > 0 or kept.size < u.shape[1]:
        return None
    Q, s, Wt = np.linalg.svd(u[kept], full_matrices=False)
    bad = s * (THRESHOLD_FALLBACK_MARGIN * s_full[0] / s_full[-1]) < s[0]
    if not bad.any():
        return None
    good = ~bad
    R = np.zeros((u.shape[1], u.shape[0]))
    R[:, kept] = (Wt[good].T / s[good]) @ Q[:, good].T                # W_g S_g^-1 Q_g^T on the kept rows
    R += Wt[bad].T @ (Wt[bad] @ u.T)                                  # W_b W_b^T U^T on every row
    s_eff = np.concatenate([s[good], np.ones(int(bad.sum()))])        # the projection's directions: gain 1
    return R, float(s_eff.max() / s_eff.min()), int(bad.sum())


def _denoise_operator(u: np.ndarray, method: str, variance: np.ndarray | None, decile: float, *, warn: bool = True
                      ) -> tuple[np.ndarray, np.ndarray | None, float | None, int]:
    """``(R, dropped, condition, fallback)`` of the VMV de-noising of a demultiplexed BTF: ``R = U^T``
    (``'projection'``) or ``U~^+`` on the rows kept below ``decile`` of ``variance``, zero on the
    dropped ones (``'thresholded'``), with the :func:`_thresholded_fallback` where ``U~`` is worse
    conditioned than ``U`` by :data:`THRESHOLD_FALLBACK_MARGIN`; ``condition`` is None for the projection."""
    n_lv, k = u.shape
    if method == "projection":
        return u.T.copy(), None, None, 0                              # VMV §4.1: U (U^T B_demux)
    if variance is None:
        raise ValueError("method='thresholded' needs variance, the (n_lv,) per-texture variance of the "
                         "demultiplexed BTF (texture_variance)")
    var = _as_float(variance, "variance", ndim=(1,))
    if var.shape != (n_lv,):
        raise ValueError(f"variance has shape {var.shape}; it must be ({n_lv},), one value per row of U")
    kept, dropped = threshold_rows(var, decile)
    fallback = _thresholded_fallback(u, kept)
    if fallback is not None:
        R, cond, n_bad = fallback
        return R, dropped, cond, n_bad
    Rk, cond = _regularised_solve(u[kept], None, 0.0, "U~ (U without the dropped rows)",
                                  "use a higher decile or fewer basis vectors",
                                  "use method='projection', a higher decile (fewer rows dropped) or fewer basis "
                                  "vectors", warn=warn)
    R = np.zeros((k, n_lv))
    R[:, kept] = Rk                                                   # VMV §4.1: U~^+ B~_demux
    return R, dropped, cond, 0


def solve_operator(
    U: np.ndarray,
    sigma: np.ndarray | None = None,
    *,
    method: str = "pinv",
    rows: np.ndarray | None = None,
    patterns: np.ndarray | None = None,
    lam: float | None = None,
    variance: np.ndarray | None = None,
    decile: float = THRESHOLD_DECILE,
    fused: bool | None = None,
    dtype: DTypeLike = np.float32,
    warn: bool = True,
) -> SolveOperator:
    """Build the reconstruction operator of a basis and a measurement.

    Parameters
    ----------
    U : (n_lv, k) array_like
        Basis, rows view-major (light fastest) when ``patterns`` are given.
    sigma : (k,) array_like, optional
        Singular values stored with ``U`` (all > 0); needed when ``lam > 0``.
    method : {'pinv', 'tikhonov', 'direct', 'projection', 'thresholded'}
        See the module docstring and Notes.
    rows : (n_sel,) array_like of int, optional
        Measured rows, distinct, in the order of the measured chunk's rows:
        indices into ``n_lv`` (``'pinv'``, ``'tikhonov'``) or, with
        ``patterns``, into the ``n_views * n_p`` multiplexed rows ``(view,
        pattern)``, view-major (``'direct'``). None: all rows.
        ``'projection'`` and ``'thresholded'`` use all rows.
    patterns : (n_p, n_lights) array_like, optional
        Binary illumination patterns of every view (``n_lv = n_views *
        n_lights``). ``'direct'`` needs them; ``'projection'`` and
        ``'thresholded'`` fold the demultiplexing into the operator when given
        (the chunk is then the multiplexed measurement, otherwise the
        demultiplexed BTF); ``'pinv'`` and ``'tikhonov'`` refuse them.
    lam : float, optional
        λ of :math:`R = \\lambda \\Sigma^{-1}`, >= 0. ``'tikhonov'`` needs it
        (:data:`LAMBDA_NIELSEN` or :data:`LAMBDA_ALS`); ``'direct'`` defaults
        to 0 (paper 4 uses :data:`LAMBDA_ALS`); other methods refuse lam > 0.
    variance : (n_lv,) array_like, optional
        ``'thresholded'``: per-texture variance of the demultiplexed BTF
        (:func:`texture_variance`).
    decile : float
        ``'thresholded'``: rows with variance above this decile are left out.
    fused : bool, optional
        Store :math:`F = U R` so that :func:`apply` is one GEMM :math:`F y` (``2 n_lv n_meas`` flops per
        column) instead of two, :math:`U (R y)` (``2 k (n_lv + n_meas)``). None: whichever has fewer flops.
    dtype : float32 or float64
        Precision of :func:`apply` (the operator is computed in float64 and rounded once).
    warn : bool
        False: no :class:`btfcore.IllConditionedWarning`; the caller reports ``operator.condition`` itself.

    Returns
    -------
    operator : SolveOperator
        :func:`apply` ``(operator, y)`` maps a measured chunk ``(n_meas, m)``
        to ``(n_lv, m)``.

    Raises
    ------
    ValueError
        On an unknown method; fewer measured rows than basis vectors without
        regularisation (names both counts); a rank-deficient measured system
        (names the rank; with patterns: the patterns do not separate the
        basis on the sampled rows); mismatched shapes; rows out of range or
        repeated; NaN/Inf (names the index); sigma missing or not positive
        where lam > 0.

    Notes
    -----
    With :math:`G` the measurement (:func:`measurement_matrix`) and
    :math:`A = G U`:

    * ``'pinv'`` (paper 1, eq. (3)): :math:`R = A^\\dagger` by the SVD;
      needs ``n_meas >= k`` and full column rank.
    * ``'tikhonov'`` and ``'direct'`` (paper 4, eq. (10)):

      .. math:: C = \\left(A^T A + R^T R\\right)^{-1} A^T b, \\qquad
                R = \\lambda \\Sigma^{-1},

      i.e. :math:`\\arg\\min_C \\|A C - b\\|^2 + \\|\\lambda \\Sigma^{-1} C\\|^2`:
      coefficient :math:`i` is penalised by :math:`(\\lambda/\\sigma_i)^2`,
      so directions the training data seldom used shrink most. It is
      solved as a ridge regression on :math:`A\\Sigma` (substituting
      :math:`C = \\Sigma D`): with :math:`A\\Sigma = Q S W^T`,
      :math:`R_{op} = \\Sigma W \\operatorname{diag}(s/(s^2 + \\lambda^2)) Q^T`,
      which is defined for any number of rows and tends to
      :math:`A^\\dagger` as :math:`\\lambda \\to 0`. ``'direct'`` has
      :math:`A = S (I_{n_{views}} \\otimes M) U`: the multiplexed
      measurement is fitted as is, never demultiplexed.
    * ``'projection'`` (VMV §4.1): :math:`R = U^T` (times
      :math:`I \\otimes P` with :math:`P` from
      :func:`btfcore.capture.demultiplex.demultiplex_operator` when patterns are
      given).
    * ``'thresholded'`` (VMV §4.1): :math:`R = \\tilde U^\\dagger`, scattered
      to the kept rows (zero columns at the dropped ones); rows are dropped
      by :func:`threshold_rows`; directions :math:`\\tilde U` no longer determines
      (:data:`THRESHOLD_FALLBACK_MARGIN`) are taken from the projection.

    Log versus linear space is the caller's choice: multiplexed
    measurements must be fitted in linear space (paper 4, §4: "we cannot
    infer M log(B) from MB"), so ``'direct'`` goes with linear (ALS)
    bases; sparse single-light measurements may be mapped first (see
    ``docs/reconstruction.md``).
    """
    if method not in RECONSTRUCTION_METHODS:
        raise ValueError(f"unknown reconstruction method {method!r}; choose one of {RECONSTRUCTION_METHODS}")
    u = _as_basis(U)
    lam_v = _as_lam(lam, method)
    s = _as_sigma(sigma, u.shape[1]) if lam_v > 0 else None
    p = None if patterns is None else _as_patterns(patterns)
    kw: dict = {"method": method, "lam": lam_v}
    if method in ("pinv", "tikhonov"):
        return _sparse_operator(u, s, lam_v, p, rows, method, fused, dtype, kw, warn)
    if method == "direct":
        return _direct_operator(u, s, lam_v, p, rows, fused, dtype, kw, warn)
    return _denoising_operator(u, p, rows, method, variance, decile, fused, dtype, kw, warn)


def _sparse_operator(u: np.ndarray, s: np.ndarray | None, lam_v: float, p: np.ndarray | None, rows,
                     method: str, fused: bool | None, dtype, kw: dict, warn: bool) -> SolveOperator:
    """:func:`solve_operator` for ``'pinv'`` and ``'tikhonov'``: single-light rows of ``u`` (paper 1, eq. (3))."""
    hint = "measure at least k rows, pass fewer basis vectors, or use method='tikhonov' with lam > 0"
    if p is not None:
        raise ValueError(f"method={method!r} is for single-light (sparse) measurements; use method='direct' "
                         f"(paper 4, eq. 10) for multiplexed ones")
    r = _as_rows(rows, u.shape[0], "rows of U (light/view pairs)")
    A = u if r is None else u[r]                                      # eq. (3): M U, M a row selection
    R, cond = _regularised_solve(A, s, lam_v, "M U", hint, warn=warn)
    return _finish(R, u, fused, dtype, rows=r, condition=cond, **kw)


def _direct_operator(u: np.ndarray, s: np.ndarray | None, lam_v: float, p: np.ndarray | None, rows,
                     fused: bool | None, dtype, kw: dict, warn: bool) -> SolveOperator:
    """:func:`solve_operator` for ``'direct'``: the multiplexed rows fitted as they are (paper 4, eq. (10))."""
    if p is None:
        raise ValueError("method='direct' fits multiplexed measurements: pass patterns (n_p, n_lights); "
                         "for single-light sparse data use 'pinv' or 'tikhonov'")
    n_views = _views(u.shape[0], p)
    r = _as_rows(rows, n_views * p.shape[0], "multiplexed rows (view, pattern)")
    MU = _multiplex_rows(u, p)                                        # (I_views (x) M) U
    A = MU if r is None else MU[r]                                    # eq. (10): S M U
    hint_d = "measure at least k rows, pass fewer basis vectors, or regularise with lam > 0 (paper 4: 0.01)"
    try:
        R, cond = _regularised_solve(A, s, lam_v, "S M U", hint_d, warn=warn)
    except ValueError as err:
        rank_p = int(np.linalg.matrix_rank(p))
        if rank_p < p.shape[1]:
            raise ValueError(f"{err} (the patterns themselves have rank {rank_p} < {p.shape[1]} lights)") from None
        raise
    return _finish(R, u, fused, dtype, rows=r, condition=cond, **kw)


def _denoising_operator(u: np.ndarray, p: np.ndarray | None, rows, method: str, variance, decile: float,
                        fused: bool | None, dtype, kw: dict, warn: bool) -> SolveOperator:
    """:func:`solve_operator` for ``'projection'`` and ``'thresholded'`` (VMV §4.1), the demultiplexing
    folded in when patterns are given."""
    if rows is not None:
        raise ValueError(f"method={method!r} projects the whole demultiplexed BTF; it takes no rows "
                         f"(use method='direct' with rows for sparse multiplexed measurements)")
    n_lv, k = u.shape
    R, dropped, cond, n_fallback = _denoise_operator(u, method, variance, decile, warn=warn)
    if cond is not None:
        kw["condition"] = cond
    if n_fallback:
        kw["fallback"] = n_fallback
    if p is not None:                                                 # fold demultiplexing in: R (I (x) P)
        n_views = _views(n_lv, p)
        P = demultiplex_operator(p)                                   # (n_lights, n_p)
        R = np.matmul(R.reshape(k, n_views, p.shape[1]).transpose(1, 0, 2), P).transpose(1, 0, 2)
        R = R.reshape(k, n_views * p.shape[0])
    return _finish(R, u, fused, dtype, dropped=dropped, **kw)


# --------------------------------------------------------------------------- applying


def _as_chunk(measured, operator: SolveOperator) -> tuple[np.ndarray, tuple[int, ...]]:
    y = np.asarray(measured)
    if y.dtype.kind not in "iuf":
        raise ValueError(f"measured must hold real numbers, got dtype {y.dtype}")
    if y.ndim < 1 or y.shape[0] != operator.n_meas:
        raise ValueError(f"measured has shape {y.shape}: its first axis must be the operator's {operator.n_meas} "
                         f"measured rows (in the order of rows)")
    flat = y.reshape(y.shape[0], -1)
    check_finite(flat, "measured")
    return flat.astype(operator.dtype, copy=False), y.shape[1:]


def apply(operator: SolveOperator, measured: np.ndarray, *, out: np.ndarray | None = None,
          part_rows: int | None = None, on_rows: Callable[[slice], None] | None = None) -> np.ndarray:
    """Reconstruct a chunk of texels: :math:`\\hat B = U (R\\, y)`.

    Parameters
    ----------
    operator : SolveOperator
        From :func:`solve_operator` or :func:`abtf_operator`.
    measured : (n_meas, ...) array_like
        Measured rows of a chunk of texels (any trailing shape, e.g. texels x
        channels), in the operator's row order; finite.
    out : (n_out, m) ndarray, optional
        C-contiguous buffer of the operator's dtype for the result (``m`` =
        the product of the trailing shape); avoids an allocation per chunk.
    part_rows, on_rows : optional
        Compute the output ``part_rows`` rows at a time and call
        ``on_rows(rows)`` with each finished slice of rows, so that a caller
        can store one part while the next is computed (the same rows as one
        product, to rounding).

    Returns
    -------
    B : (n_out, ...) ndarray
        In the operator's dtype (the chunk is cast to it).

    Raises
    ------
    ValueError
        On a first axis other than ``n_meas``, NaN/Inf (names the index) or
        a wrong ``out``.

    Notes
    -----
    One GEMM :math:`F y` when the operator is fused, else
    :math:`U (R y)`. Applying chunk by chunk gives the whole-matrix result
    (column by column the products are the same).
    """
    y, trailing = _as_chunk(measured, operator)
    shape = (operator.n_out, y.shape[1])
    if out is not None and (out.shape != shape or out.dtype != operator.dtype or not out.flags.c_contiguous):
        raise ValueError(f"out must be a C-contiguous {operator.dtype} array of shape {shape}, got "
                         f"{out.dtype} {out.shape}")
    left, right = ((operator.fused, y) if operator.fused is not None          # B = (U R) y
                   else (operator.basis, operator.coefficients @ y))        # B = U (R y)
    if part_rows is None:
        res = np.matmul(left, right, out=out)
    else:
        res = np.empty(shape, operator.dtype) if out is None else out
        for r0 in range(0, operator.n_out, part_rows):
            rows = slice(r0, min(r0 + part_rows, operator.n_out))
            np.matmul(left[rows], right, out=res[rows])
            if on_rows is not None:
                on_rows(rows)
    return res.reshape((operator.n_out,) + trailing)


def coefficients(operator: SolveOperator, measured: np.ndarray) -> np.ndarray:
    """Basis coefficients :math:`C = R\\, y` of a measured chunk.

    Parameters
    ----------
    operator : SolveOperator
    measured : (n_meas, ...) array_like

    Returns
    -------
    C : (k, ...) ndarray
        In the operator's dtype; :math:`\\hat B = U C`.
    """
    y, trailing = _as_chunk(measured, operator)
    return (operator.coefficients @ y).reshape((operator.k,) + trailing)


def reconstruct(U: np.ndarray, measured: np.ndarray, sigma: np.ndarray | None = None, **kwargs) -> np.ndarray:
    """:func:`apply` ``(solve_operator(U, sigma, **kwargs), measured)`` in one call (for in-memory data).

    Parameters
    ----------
    U : (n_lv, k) array_like
    measured : (n_meas, ...) array_like
    sigma : (k,) array_like, optional
    **kwargs
        Keyword arguments of :func:`solve_operator` (``method``, ``rows``,
        ``patterns``, ``lam``, ...).

    Returns
    -------
    B : (n_lv, ...) ndarray
    """
    kwargs.setdefault("dtype", np.float32 if np.asarray(measured).dtype == np.float32 else np.float64)
    return apply(solve_operator(U, sigma, **kwargs), measured)


# --------------------------------------------------------------------------- measurements


def measurement_matrix(n_lv: int, rows: np.ndarray | None = None, patterns: np.ndarray | None = None) -> np.ndarray:
    """The measurement operator :math:`G = S (I_{n_{views}} \\otimes M)` as a dense matrix.

    Parameters
    ----------
    n_lv : int
        Rows of the BTF (``n_views * n_lights`` with patterns).
    rows : (n_sel,) array_like of int, optional
        Selected rows (of the multiplexed rows with patterns); None: all.
    patterns : (n_p, n_lights) array_like, optional
        Binary patterns applied to every view; None: single lights.

    Returns
    -------
    G : (n_meas, n_lv) ndarray of float64
        For tests and small problems; :func:`measure` applies it without
        forming it.

    Notes
    -----
    Rows of ``B`` are view-major with the light fastest, so the multiplexed
    rows are view-major with the pattern fastest and the block-diagonal
    multiplexing matrix of paper 4, eq. (4), is
    :math:`I_{n_{views}} \\otimes M` (one pattern sequence per view).
    """
    if patterns is None:
        G = np.eye(n_lv)
    else:
        p = _as_patterns(patterns)
        G = np.kron(np.eye(_views(n_lv, p)), p)                       # I_views (x) M
    r = _as_rows(rows, G.shape[0], "measurement rows")
    return G if r is None else G[r]                                   # S (I (x) M)


def measure(B: np.ndarray, rows: np.ndarray | None = None, patterns: np.ndarray | None = None) -> np.ndarray:
    """Simulate a sparse and/or multiplexed measurement :math:`G B` of a BTF (chunk).

    Parameters
    ----------
    B : (n_lv, ...) array_like
        BTF rows (view-major, light fastest), any trailing shape.
    rows, patterns
        As for :func:`measurement_matrix`.

    Returns
    -------
    measured : (n_meas, ...) ndarray
        float32 for float32 ``B``, float64 otherwise.
    """
    b = _as_float(B, "B")
    if b.ndim < 1:
        raise ValueError("B must have a first axis of light/view pairs")
    flat = b.reshape(b.shape[0], -1)
    if patterns is not None:
        flat = _multiplex_rows(flat, _as_patterns(patterns))          # (I_views (x) M) B
    r = _as_rows(rows, flat.shape[0], "measurement rows")
    if r is not None:
        flat = flat[r]                                                # S (...)
    return flat.reshape((flat.shape[0],) + b.shape[1:])


# --------------------------------------------------------------------------- thresholded de-noising


def texture_variance(B: np.ndarray | Iterable[np.ndarray]) -> np.ndarray:
    """Per-texture (per-row) variance of a BTF, over all its texels and channels.

    Parameters
    ----------
    B : (n_lv, ...) array_like, or an iterable of (n_lv, m_j) column blocks
        The demultiplexed BTF, unnormalised (VMV paper §4.1 found the 9th
        decile "of the latter", unnormalised data, best); blocks let the
        tasks layer stream texel chunks.

    Returns
    -------
    variance : (n_lv,) ndarray of float64
        Population variance (``ddof = 0``) of each row.

    Notes
    -----
    Blocks are combined with Chan, Golub and LeVeque's pairwise update of
    count, mean and :math:`M_2`, in float64, so the result does not depend
    on the chunking beyond rounding.
    """
    blocks = [B] if isinstance(B, np.ndarray) else B
    n, mean, m2 = 0, None, None
    for j, raw in enumerate(blocks):
        b = _as_float(raw, f"B block {j}")
        b = b.reshape(b.shape[0], -1).astype(np.float64, copy=False)
        if mean is not None and b.shape[0] != mean.shape[0]:
            raise ValueError(f"block {j} has {b.shape[0]} rows, the first had {mean.shape[0]}")
        nb = b.shape[1]
        if nb == 0:
            continue
        mb = b.mean(axis=1)
        m2b = np.sum((b - mb[:, None]) ** 2, axis=1)
        if mean is None:
            n, mean, m2 = nb, mb, m2b
            continue
        delta = mb - mean
        tot = n + nb
        mean = mean + delta * (nb / tot)
        m2 = m2 + m2b + delta**2 * (n * nb / tot)
        n = tot
    if mean is None:
        raise ValueError("B has no texels: pass a non-empty (n_lv, m) array or blocks")
    return m2 / n


def threshold_rows(variance: np.ndarray, decile: float = THRESHOLD_DECILE) -> tuple[np.ndarray, np.ndarray]:
    """Split rows into those kept and those dropped by the variance threshold.

    Parameters
    ----------
    variance : (n_lv,) array_like
        Per-texture variances (:func:`texture_variance`).
    decile : float
        In (0, 10]; the VMV paper uses the 9th.

    Returns
    -------
    kept, dropped : (n_kept,), (n_drop,) ndarray of int64
        ``dropped`` are the rows whose variance is strictly above the
        ``decile``-th decile ``np.quantile(variance, decile / 10)`` (linear
        interpolation), ``kept`` the others, both ascending.

    Notes
    -----
    VMV paper §4.1: "we compute per-texture variances and do not take the
    BTF's textures that correspond to some percentile of the variances into
    consideration during projection ... the 9th decile of [unnormalised
    data] to perform best": demultiplexing noise makes a few textures
    outliers of high variance, so those above the 9th decile (about a
    tenth) are left out.
    """
    v = _as_float(variance, "variance", ndim=(1,))
    d = float(decile)
    if not 0 < d <= 10:
        raise ValueError(f"decile must be in (0, 10], got {decile!r}")
    q = np.quantile(v.astype(np.float64), d / 10.0)
    return np.flatnonzero(v <= q).astype(np.int64), np.flatnonzero(v > q).astype(np.int64)


# --------------------------------------------------------------------------- ABTF patches


def abtf_operator(
    U: np.ndarray,
    rows: np.ndarray,
    *,
    p: int = 3,
    sigma: np.ndarray | None = None,
    method: str = "pinv",
    lam: float | None = None,
    dtype: DTypeLike = np.float32,
    warn: bool = True,
) -> SolveOperator:
    """Reconstruction operator of an ABTF patch basis (paper 1, §3.3, §4.1.2).

    Parameters
    ----------
    U : (p * p * n_lv, k) array_like
        Patch basis in the row order of :func:`btfcore.model.abtf.patch_matrix`
        (``p²`` blocks of ``n_lv`` rows, one per texel of the patch).
    rows : (n_s,) array_like of int
        Measured light/view pairs (into ``n_lv``), the same for every texel.
    p : int
        Patch size (paper 1: 3).
    sigma : (k,) array_like, optional
        Needed for ``'tikhonov'``.
    method : {'pinv', 'tikhonov'}
    lam : float, optional
        As for :func:`solve_operator`.
    dtype : float32 or float64
    warn : bool
        As for :func:`solve_operator`.

    Returns
    -------
    operator : SolveOperator
        Never fused (:math:`U R` would be ``(p² n_lv, p² n_s)``);
        :func:`reconstruct_abtf` applies it to measured textures.

    Raises
    ------
    ValueError
        As :func:`solve_operator`; also if ``U``'s rows are not a multiple
        of ``p²``.

    Notes
    -----
    The patch measurement is :math:`S_{patch} = I_{p^2} \\otimes S` (thesis
    ch. 2.1, the summary of paper 1; see :func:`btfcore.model.abtf.patch_matrix` on why the thesis'
    :math:`\\mathbf 1_{p^2}` is the identity): it selects rows
    ``d * n_lv + rows[j]`` of ``U`` for texel ``d`` of the patch, in the
    order ``(d, j)`` of ``patch_matrix`` applied to the measured texture, and

    .. math:: V_{patch}^t = (S_{patch} U_{patch})^\\dagger S_{patch} B_{patch}
    """
    if method not in ("pinv", "tikhonov"):
        raise ValueError(f"ABTF reconstruction supports method 'pinv' or 'tikhonov', got {method!r}")
    p = _patch_size(p)
    u = _as_basis(U)
    if u.shape[0] % (p * p):
        raise ValueError(f"U has {u.shape[0]} rows, not a multiple of p² = {p * p}: pass a patch basis "
                         f"(rows of btfcore.model.abtf.patch_matrix) or the right p")
    n_lv, k = u.shape[0] // (p * p), u.shape[1]
    lam_v = _as_lam(lam, method)
    s = _as_sigma(sigma, k) if lam_v > 0 else None
    r = _as_rows(rows, n_lv, "light/view pairs")
    if r is None:
        raise ValueError("rows are needed: the measured light/view pairs")
    idx = (np.arange(p * p)[:, None] * n_lv + r[None, :]).ravel()      # rows of I_{p²} (x) S, order (d, j)
    A = u[idx]                                                        # S_patch U_patch
    R, cond = _regularised_solve(A, s, lam_v, "S_patch U_patch",
                                 "measure more rows, pass fewer basis vectors, or use method='tikhonov'", warn=warn)
    return _finish(R, u, False, dtype, method=method, lam=lam_v, rows=r, condition=cond, patch_size=p)


def abtf_halo(start: int, stop: int, height: int, p: int = 3) -> slice:
    """Texture rows of the measurement that output texture rows ``start:stop`` need.

    Parameters
    ----------
    start, stop : int
        Output rows, ``0 <= start < stop <= height``.
    height : int
        Texture height ``h >= p``.
    p : int

    Returns
    -------
    rows : slice
        ``slice(max(0, start - p + 1), min(height, stop + p - 1))``: every
        patch that covers an output row lies inside it, so that
        :func:`reconstruct_abtf` on bands equals the whole-texture result.
    """
    p = _patch_size(p)
    if height < p:
        raise ValueError(f"height={height} is smaller than the patch size p={p}")
    if not 0 <= start < stop <= height:
        raise ValueError(f"output rows must satisfy 0 <= start < stop <= height={height}, got {start}:{stop}")
    return slice(max(0, start - p + 1), min(height, stop + p - 1))


def _cover_count(lo: int, n: int, size: int, p: int) -> np.ndarray:
    """Number of overlapping patches covering texels ``lo .. lo + n - 1`` of an axis of ``size`` texels."""
    t = np.arange(lo, lo + n)
    return np.minimum(t, size - p) - np.maximum(0, t - p + 1) + 1


def reconstruct_abtf(
    operator: SolveOperator,
    measured: np.ndarray,
    *,
    out_rows: tuple[int, int] | None = None,
    height: int | None = None,
) -> np.ndarray:
    """Reconstruct textures from measured ones through all overlapping ABTF patches.

    Parameters
    ----------
    operator : SolveOperator
        From :func:`abtf_operator`.
    measured : (n_s, h_b, w) or (n_s, h_b, w, C) array_like
        Measured textures in the order of the operator's rows: the whole
        texture (``out_rows=None``), or the rows
        ``abtf_halo(start, stop, height, p)`` of it.
    out_rows : (start, stop), optional
        Texture rows to reconstruct (a band); needs ``height``.
    height : int, optional
        Height of the whole texture when ``out_rows`` is given.

    Returns
    -------
    B : (n_lv, stop - start, w[, C]) ndarray
        In the operator's dtype; with ``out_rows=None`` the whole
        ``(n_lv, h, w[, C])``.

    Raises
    ------
    ValueError
        On an operator without a patch size, a wrong number of measured
        textures, a band whose height is not that of its halo, NaN/Inf.

    Notes
    -----
    Paper 1, §4.1.2: all overlapping p x p patches of the measurement
    (:func:`btfcore.model.abtf.patch_matrix` with ``overlap=True``) are solved for
    coefficients :math:`C = R P`, and texels are blended "all texels weighted
    equally" as :func:`btfcore.model.abtf.blend_patches` does. Instead of forming
    :math:`U C` (``p² n_lv`` rows per patch) the blend accumulates the
    ``p²`` blocks :math:`U_d C` one at a time, shifted to their texels, and
    divides by the number of covering patches (same values as
    ``blend_patches(U @ C, ...)`` to rounding, ``1/p²`` of its memory).
    """
    p = operator.patch_size
    if p is None:
        raise ValueError("operator is not an ABTF operator: build it with abtf_operator")
    m = _as_float(measured, "measured", ndim=(3, 4))
    m4 = m[..., None] if m.ndim == 3 else m
    n_s, hb, w, C = m4.shape
    if n_s * p * p != operator.n_meas:
        raise ValueError(f"measured has {n_s} textures; the operator measures {operator.n_meas // (p * p)} rows")
    if out_rows is None:
        start, stop, g0, H = 0, hb, 0, hb
    else:
        if height is None:
            raise ValueError("out_rows needs height, the number of rows of the whole texture")
        start, stop = (int(v) for v in out_rows)
        halo = abtf_halo(start, stop, int(height), p)
        if hb != halo.stop - halo.start:
            raise ValueError(f"measured has {hb} texture rows; output rows {start}:{stop} of a {height}-row texture "
                             f"need rows {halo.start}:{halo.stop} (abtf_halo), {halo.stop - halo.start} rows")
        g0, H = halo.start, int(height)
    ny, nx = patch_grid(hb, w, p, overlap=True)
    P = patch_matrix(m4.astype(operator.dtype, copy=False), p, overlap=True)   # (p² n_s, ny nx C)
    coef = operator.coefficients @ P                                  # paper 1: V = (S U)^+ S B, per patch
    n_lv = operator.n_out // (p * p)
    acc = np.zeros((n_lv, hb, w, C), operator.dtype)
    for dy in range(p):
        for dx in range(p):
            d = dy * p + dx
            block = (operator.basis[d * n_lv:(d + 1) * n_lv] @ coef).reshape(n_lv, ny, nx, C)
            acc[:, dy:dy + ny, dx:dx + nx] += block                   # texel (dy, dx) of every patch
    count = np.outer(_cover_count(g0, hb, H, p), _cover_count(0, w, w, p)).astype(operator.dtype)
    acc /= count[None, :, :, None]                                    # §4.1.2: all patches weighted equally
    res = acc[:, start - g0:stop - g0]
    return res[..., 0] if m.ndim == 3 else res
