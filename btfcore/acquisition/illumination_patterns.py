"""Basis-aware binary illumination patterns: few on/off LED patterns that minimise the expected error.

The thesis measures with the full S-matrix (``n + 1`` patterns of ``(n + 1) / 2``
LEDs each, VMV §3.2) and reconstructs the class basis from them in one solve
(paper 4, eq. 10, which takes any measurement matrix). Under photon noise and
saturation the S-matrix is not the best binary design (Ratner and Schechner,
2007), and a design that knows the basis needs far fewer patterns (Kang et
al., 2018, learn 16-32 light-stage patterns for reflectance). This module
chooses ``m`` binary patterns (``m`` much smaller than the LED count ``n``)
that minimise the expected reconstruction error of a basis ``U``, ``sigma``
under the sensor's photon and read noise at each pattern's own exposure and
the material's error outside the basis, and builds the one-solve
reconstruction operator for them.

Model (every view ``v`` of ``n_views`` sees the same ``m`` patterns; rows of
``U`` are view-major with the light fastest, ``n_lv = n_views * n_leds``):

* **prior**: the coefficients of a texel's ABRDF :math:`b = U c` are
  :math:`c \\sim \\mathcal N(0, P)`, :math:`P = s\\,\\Sigma^2`: the Tikhonov
  prior :math:`\\lambda \\Sigma^{-1}` of paper 4 eq. (10) read as a Gaussian
  (Nielsen et al., 2015), with ``s = prior_scale`` and the singular values
  floored at ``prior_floor`` of the first (a class basis underestimates a new
  material's weak directions);
* **brightness**: LED ``l`` lights a typical texel in view ``v`` with the prior's
  rms radiance :math:`r_{vl} = (\\sum_j U_{vl,j}^2 P_{jj})^{1/2}`, a pattern
  ``p`` with :math:`x_{vp} = \\sum_{l \\in p} r_{vl}` and its brightest texel
  with ``peak_factor`` times that;
* **exposure and noise** (:mod:`btfcore.acquisition.noise`): each image is
  exposed at the chosen shutter time, or shorter where its brightest texel
  would pass ``fill`` of the full well
  (:func:`~btfcore.acquisition.noise.exposure_gain`; without a chosen shutter
  every image is exposed to ``fill``, the evaluation's auto exposure): a
  pattern with more LEDs on saturates sooner, its exposure shrinks, and its
  variance in radiance units
  :math:`d_{vp} = x/g + \\sigma_r^2/g^2`
  (:func:`~btfcore.acquisition.noise.noise_moments`) grows. With one exposure per
  view (``single_exposure``, the ``realistic`` dome's multiplexed capture) every
  pattern of a view gets the gain metered on the view's median pattern
  (:func:`btfcore.simulate.nonideal.metered_maximum`): a dimmer pattern gets
  less light, and one brighter than ``1 / fill`` times the median saturates at
  its brightest texels, which the objective charges as the squared radiance
  clipped off its brightest texel (a penalty that keeps the design below
  saturation, not a model of the clipped texels' error);
* **model error**: the ABRDF is :math:`b = U c + e` with a part outside
  the basis (truncation, class mismatch), :math:`e_{vl} \\sim \\mathcal N(0,
  \\varepsilon^2 r_{vl}^2)` independent per light/view pair
  (``model_error``): it is not common to all designs, since it leaks into
  the coefficients through the measured rows, most through few repeated
  LEDs. In view ``v`` the images' covariance is
  :math:`\\Omega_v = D_v + \\varepsilon^2 M R_v^2 M^T` (:math:`R_v = \\operatorname{diag}(r_v)`);
* **solve**: the MAP (generalised least-squares) estimate of paper 4
  eq. (10) on the whitened measurement, :math:`C = F^{-1} A^T \\Omega^{-1} y`
  with :math:`A = (I_{n_{views}} \\otimes M) U`, :math:`\\Omega` block
  diagonal and :math:`F = A^T \\Omega^{-1} A + P^{-1}` (:func:`pattern_operator`);
* **objective**: its expected squared error per texel in the span of the
  basis, :math:`J = \\operatorname{tr}(U F^{-1} U^T)` (the posterior error
  covariance of the coefficients mapped to the BTF rows: noise and model
  error leaked into the coefficients), and the predicted relative error
  :math:`\\sqrt{J / \\operatorname{tr}(U P U^T)}`; the model error itself,
  relative :math:`\\varepsilon`, comes on top for every design.

Every quantity scales with ``prior_scale`` alike, so ``J / tr(U P U^T)``,
the designs and the operator do not depend on it.

The optimiser (:func:`design_patterns`) starts from given patterns (the
evaluation and ``btf plan`` start from the ``m`` S-matrix rows that
:func:`select_rows` picks: spread-out LEDs are robust to what the model
misses) or adds patterns greedily, each grown from the best single LED by
bit flips, then refines every pattern by bit flips (coordinate descent) in a
seeded random order; a pattern's every candidate flip is scored at once by a
rank-``n_views`` update of :math:`F^{-1}` (Woodbury, conditioned on the other
patterns' images). :func:`select_rows` picks ``m`` rows of a given pattern
set (e.g. the S-matrix subsampled) greedily on the same objective.

References
----------
.. [1] N. Ratner and Y. Y. Schechner, "Illumination multiplexing within
   fundamental limits", CVPR 2007 (optimised binary codes beat Hadamard /
   S-matrix codes under photon noise and saturation).
.. [2] K. Kang, Z. Chen, J. Wang, K. Zhou and H. Wu, "Efficient reflectance
   capture using an autoencoder", ACM TOG 37(4), 2018 (learned lighting
   patterns for a reflectance basis).
.. [3] The thesis, App. paper 4, §4.3-4.4, eq. (10) (one solve from a general
   measurement matrix, regulariser :math:`\\lambda\\Sigma^{-1}`); VMV paper
   §3.2, §5.1 (S-matrices, shutter times of multiplexed patterns).
.. [4] J. B. Nielsen, H. W. Jensen and R. Ramamoorthi, "On optimal, minimal
   BRDF sampling for reflectance acquisition", ACM TOG 34(6), 2015.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import DTypeLike

from btfcore.acquisition.noise import SensorNoise, exposure_gain, noise_moments
from btfcore.acquisition.reconstruct import SolveOperator, solve_operator
from btfcore.simulate.nonideal import metered_maximum

__all__ = ["MODEL_ERROR", "PEAK_FACTOR", "PRIOR_FLOOR", "PatternDesign", "PatternModel", "design_patterns",
           "expected_error", "pattern_operator", "random_patterns", "select_rows"]

#: Brightest over typical (rms) radiance of an image, the exposure's headroom for the texture's contrast.
PEAK_FACTOR = 3.0
#: Relative RMS error of a material's ABRDFs outside its class basis (the basis' truncation and class mismatch),
#: per light/view pair: the order of the evaluation's held-out linear errors (docs/evaluation.md).
MODEL_ERROR = 0.3
#: Least prior standard deviation of a coefficient, as a fraction of the first one's: a class basis (in the
#: leave-one-out evaluation, of one other material) underestimates a new material's energy in its weak
#: directions (measured: up to 20x), and a design that trusts the tail of the prior leaves them unmeasured.
PRIOR_FLOOR = 0.2


@dataclass(frozen=True)
class PatternModel:
    """The basis, prior and noise model a design is scored under.

    Attributes
    ----------
    U : (n_lv, k) ndarray
        Basis, rows view-major (light fastest).
    sigma : (k,) ndarray
        Its singular values (> 0).
    n_leds : int
        LEDs per view; ``n_lv = n_views * n_leds``.
    noise : SensorNoise
    peak_factor : float
        Brightest over typical radiance of an image (:data:`PEAK_FACTOR`).
    prior_scale : float
        ``s`` of the prior :math:`P = s \\Sigma^2` (cancels in the relative error).
    prior_floor : float
        The prior's standard deviations are :math:`\\sqrt{s}\\max(\\sigma_i, f \\sigma_1)`
        (:data:`PRIOR_FLOOR`; 0: the singular values as they are).
    model_error : float
        :math:`\\varepsilon`, the relative RMS error of an ABRDF outside the basis
        (:data:`MODEL_ERROR`), independent per light/view pair.
    shutter_fill : float, optional
        The chosen shutter time, as the fraction of the full well that the
        brightest texel of a typical single-LED image (mean radiance over the
        views and LEDs) reaches in it. An image is exposed at most that long and
        shorter where it would saturate (above ``noise.fill``). None: every image
        is exposed to ``noise.fill`` (ideal auto exposure, the evaluation's model).
    single_exposure : bool
        Every pattern of a view shares one exposure, metered on the view's median
        pattern (module docstring); False: each image is exposed on its own.
    """

    U: np.ndarray
    sigma: np.ndarray
    n_leds: int
    noise: SensorNoise = SensorNoise()
    peak_factor: float = PEAK_FACTOR
    prior_scale: float = 1.0
    prior_floor: float = PRIOR_FLOOR
    model_error: float = MODEL_ERROR
    shutter_fill: float | None = None
    single_exposure: bool = False

    def __post_init__(self) -> None:
        U = np.asarray(self.U, dtype=np.float64)
        s = np.asarray(self.sigma, dtype=np.float64)
        if U.ndim != 2 or 0 in U.shape or not np.isfinite(U).all():
            raise ValueError(f"U must be a finite, non-empty (n_lv, k) basis, got shape {U.shape}")
        if s.shape != (U.shape[1],) or not (s > 0).all():
            raise ValueError(f"sigma must hold the k={U.shape[1]} positive singular values of U, got {s.shape}")
        if int(self.n_leds) < 1 or U.shape[0] % int(self.n_leds):
            raise ValueError(f"U has {U.shape[0]} rows, not a multiple of n_leds={self.n_leds}: rows must be "
                             "(view, LED) pairs, view-major with the LED fastest")
        if not (np.isfinite(self.peak_factor) and self.peak_factor >= 1):
            raise ValueError(f"peak_factor must be >= 1 (brightest over typical radiance), got {self.peak_factor}")
        if not (np.isfinite(self.prior_scale) and self.prior_scale > 0):
            raise ValueError(f"prior_scale must be > 0, got {self.prior_scale}")
        if not (np.isfinite(self.prior_floor) and 0 <= self.prior_floor <= 1):
            raise ValueError(f"prior_floor must lie in [0, 1] (a fraction of sigma_1), got {self.prior_floor}")
        if not (np.isfinite(self.model_error) and self.model_error >= 0):
            raise ValueError(f"model_error must be >= 0 (a relative RMS error), got {self.model_error}")
        if self.shutter_fill is not None and not (np.isfinite(self.shutter_fill) and self.shutter_fill > 0):
            raise ValueError(f"shutter_fill must be > 0 (a fraction of the full well), got {self.shutter_fill}")
        object.__setattr__(self, "U", U)
        object.__setattr__(self, "sigma", s)
        object.__setattr__(self, "n_leds", int(self.n_leds))

    @property
    def n_views(self) -> int:
        return self.U.shape[0] // self.n_leds

    @property
    def k(self) -> int:
        return int(self.U.shape[1])

    @cached_property
    def prior(self) -> np.ndarray:
        """Diagonal of :math:`P = s \\Sigma^2` (``sigma`` floored at ``prior_floor * sigma[0]``), ``(k,)``."""
        return self.prior_scale * np.maximum(self.sigma, self.prior_floor * self.sigma.max()) ** 2

    @cached_property
    def blocks(self) -> np.ndarray:
        """``U`` as ``(n_views, n_leds, k)``."""
        return self.U.reshape(self.n_views, self.n_leds, self.k)

    @cached_property
    def gram(self) -> np.ndarray:
        """:math:`U^T U`, ``(k, k)``."""
        return self.U.T @ self.U

    @cached_property
    def radiance(self) -> np.ndarray:
        """Typical radiance :math:`r_{vl}` of a texel under LED ``l`` in view ``v``, ``(n_views, n_leds)``."""
        return np.sqrt(self.blocks ** 2 @ self.prior)

    @cached_property
    def signal_energy(self) -> float:
        """:math:`E\\|b\\|^2 = \\operatorname{tr}(U P U^T)` per texel."""
        return float(np.einsum("kk,k->", self.gram, self.prior))

    def meter(self, x: np.ndarray, axis: int) -> np.ndarray | None:
        """The typical radiance each view's one exposure is metered on: the median of its patterns' ``x``
        over ``axis`` (kept), or None where every image is exposed on its own (``single_exposure`` False)."""
        return metered_maximum(x, axis=axis) if self.single_exposure and np.shape(x)[axis] else None

    def variance(self, x: np.ndarray, meter: np.ndarray | None = None) -> np.ndarray:
        """Noise variance (radiance units) of images of typical radiance ``x`` (any shape, > 0), each exposed
        on its own, or, with ``meter`` (broadcast against ``x``, :meth:`meter`), all at the gain of ``meter``,
        plus the squared radiance clipped off the brightest texel where that saturates."""
        x = np.asarray(x, dtype=np.float64)
        ref = x if meter is None else np.broadcast_to(np.asarray(meter, dtype=np.float64), x.shape)
        g = exposure_gain(self.peak_factor * ref.ravel(), self.noise)                   # exposed to its peak
        if self.shutter_fill is not None:                                               # ... or the chosen shutter
            g_t = self.shutter_fill * self.noise.full_well_e / (self.peak_factor * float(self.radiance.mean()))
            g = np.minimum(g, g_t)
        d = noise_moments(x.ravel(), g, self.noise)[1]                                  # x/g + sigma_r^2/g^2
        if meter is not None:
            d = d + np.maximum(self.peak_factor * x.ravel() - self.noise.full_well_e / g, 0.0) ** 2   # clipped
        return d.reshape(x.shape)


@dataclass(frozen=True)
class PatternDesign:
    """A set of binary patterns and its predicted error.

    Attributes
    ----------
    patterns : (m, n_leds) ndarray of uint8
        1 = LED on.
    objective : float
        :math:`J`, the expected squared error per texel (radiance², with the prior's scale).
    relative_error : float
        :math:`\\sqrt{J / \\operatorname{tr}(U P U^T)}`, the predicted relative RMS error of the design
        (noise and leaked model error; the model error itself comes on top).
    history : (n_steps,) ndarray
        Objective after each added pattern and each refinement sweep.
    method : str
        ``'greedy'``, ``'select'``, ``'random'`` or ``'given'``.
    """

    patterns: np.ndarray
    objective: float
    relative_error: float
    history: np.ndarray
    method: str

    @property
    def m(self) -> int:
        return int(self.patterns.shape[0])

    @property
    def leds_on(self) -> np.ndarray:
        """LEDs on per pattern, ``(m,)``."""
        return self.patterns.sum(axis=1).astype(np.int64)

    def summary(self) -> dict[str, Any]:
        """JSON-able figures (not the patterns)."""
        on = self.leds_on
        return {"m": self.m, "method": self.method, "objective": self.objective,
                "predicted_relative_error": self.relative_error,
                "leds_on": {"min": int(on.min()), "mean": float(on.mean()), "max": int(on.max())}}


# --------------------------------------------------------------------------- the objective


def _as_binary(patterns: Any, n_leds: int) -> np.ndarray:
    p = np.asarray(patterns)
    if p.ndim != 2 or p.shape[1] != n_leds or p.shape[0] == 0:
        raise ValueError(f"patterns must be (m, {n_leds}) on/off values, got shape {p.shape}")
    if not np.isin(p, (0, 1)).all():
        raise ValueError("patterns must be binary (0 = LED off, 1 = on)")
    empty = np.flatnonzero(p.sum(axis=1) == 0)
    if empty.size:
        raise ValueError(f"pattern {int(empty[0])} switches no LED on: an all-dark image cannot be exposed; drop it")
    return p.astype(np.uint8)


def _rows(model: PatternModel, patterns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Measurement rows ``(n_views, m, k)`` of :math:`(I \\otimes M) U` and their covariances ``(n_views, m, m)``."""
    p = patterns.astype(np.float64)
    A = np.matmul(p, model.blocks)                                         # (I_views (x) M) U, (V, m, k)
    x = model.radiance @ p.T                                               # x_vp = sum_{l in p} r_vl
    omega = model.model_error ** 2 * np.matmul(p * (model.radiance ** 2)[:, None, :], p.T)   # eps^2 M R_v^2 M^T
    idx = np.arange(p.shape[0])
    omega[:, idx, idx] += model.variance(x, model.meter(x, axis=1))        # + D_v (photon + read noise)
    return A, omega


def _information(model: PatternModel, patterns: np.ndarray | None) -> np.ndarray:
    """:math:`F = P^{-1} + \\sum_v A_v^T \\Omega_v^{-1} A_v`, ``(k, k)``."""
    F = np.diag(1.0 / model.prior)
    if patterns is not None and len(patterns):
        A, omega = _rows(model, patterns)
        F += np.tensordot(A, np.linalg.solve(omega, A), axes=([0, 1], [0, 1]))   # sum_v A_v^T Omega_v^-1 A_v
    return F


def _design(model: PatternModel, patterns: np.ndarray, method: str, history: list[float]) -> PatternDesign:
    J = float(np.trace(model.gram @ np.linalg.inv(_information(model, patterns))))
    return PatternDesign(patterns.astype(np.uint8), J, float(np.sqrt(J / model.signal_energy)),
                         np.asarray(history + [J]), method)


def expected_error(model: PatternModel, patterns: np.ndarray) -> PatternDesign:
    """The predicted error of given binary patterns (:func:`pattern_operator`'s solve).

    Parameters
    ----------
    model : PatternModel
    patterns : (m, n_leds) array_like of 0/1
        Every pattern switches at least one LED on.

    Returns
    -------
    design : PatternDesign
        ``method='given'``; ``objective`` is :math:`J = \\operatorname{tr}(U F^{-1} U^T)`
        with :math:`F = P^{-1} + \\sum_v A_v^T \\Omega_v^{-1} A_v` (module docstring): the
        trace of the posterior error covariance of the solve mapped to the BTF rows,
        which is its expected squared error per texel in the basis' span.
    """
    return _design(model, _as_binary(patterns, model.n_leds), "given", [])


def _gains(Q: np.ndarray, G: np.ndarray, A: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Decrease of :math:`\\operatorname{tr}(G F^{-1})` when candidate rows are added to :math:`F`.

    ``Q`` = :math:`F^{-1}` ``(k, k)``, ``A`` the candidates' rows ``(n_c, n_views, k)``, ``d`` their variances
    ``(n_c, n_views)`` (uncorrelated rows). By Woodbury, :math:`\\operatorname{tr}(G (F + A^T D^{-1} A)^{-1}) =
    \\operatorname{tr}(G Q) - \\operatorname{tr}((D + A Q A^T)^{-1} A Q G Q A^T)`."""
    AQ = A @ Q                                                             # (n_c, V, k)
    S = AQ @ A.transpose(0, 2, 1)                                          # A Q A^T
    idx = np.arange(S.shape[1])
    S[:, idx, idx] += d
    T = AQ @ G @ AQ.transpose(0, 2, 1)                                     # A Q G Q A^T
    return _trace_solve(S, T)


def _trace_solve(S: np.ndarray, T: np.ndarray) -> np.ndarray:
    """:math:`\\operatorname{tr}(S_i^{-1} T_i)` of a stack ``(n, V, V)``, by LU as ``numpy.linalg.solve``; torch's
    batched solve takes half numpy's time for the evaluation's 198 systems of 11 x 11 (its LAPACK call per
    system has less around it)."""
    import torch

    out = torch.linalg.solve(torch.from_numpy(np.ascontiguousarray(S)), torch.from_numpy(np.ascontiguousarray(T)))
    return out.diagonal(dim1=1, dim2=2).sum(1).numpy()


@dataclass(frozen=True)
class _Others:
    """What adding one pattern ``p`` to fixed others costs to score (per view ``v``, ``O`` the others).

    The new image is correlated with the others' through the shared LEDs' model error; conditioned on them
    it adds the rank-one term :math:`\\tilde a_v \\tilde a_v^T / s_v` to :math:`F` with
    :math:`\\tilde a_v = E_v p`, :math:`E_v = U_v^T - A_{O,v}^T K_v W_v`, and
    :math:`s_v = d_v(p) + \\varepsilon^2 \\sum_{l \\in p} r_{vl}^2 - (W_v p)^T K_v (W_v p)`, where
    :math:`W_v = \\varepsilon^2 M_O R_v^2` and :math:`K_v = \\Omega_{O,v}^{-1}` (a Schur complement)."""

    Q: np.ndarray     # (k, k) F_O^-1
    E: np.ndarray     # (V, k, n)
    W: np.ndarray     # (V, m_o, n)
    K: np.ndarray     # (V, m_o, m_o)
    meter: np.ndarray | None = None    # (1, V): the others' metered radiance (single exposure), held for p


def _others(model: PatternModel, others: np.ndarray) -> _Others:
    U_t = model.blocks.transpose(0, 2, 1)                                  # (V, k, n): U_v^T
    V, n = model.n_views, model.n_leds
    if not len(others):
        return _Others(_inverse(_information(model, None)), U_t, np.zeros((V, 0, n)), np.zeros((V, 0, 0)))
    A, omega = _rows(model, others)
    K = np.linalg.inv(omega)
    K = 0.5 * (K + K.transpose(0, 2, 1))
    W = model.model_error ** 2 * others.astype(np.float64)[None] * (model.radiance ** 2)[:, None, :]
    E = U_t - np.matmul(A.transpose(0, 2, 1), np.matmul(K, W))            # U_v^T - A_v^T K_v W_v
    F = np.diag(1.0 / model.prior) + np.tensordot(A, np.matmul(K, A), axes=([0, 1], [0, 1]))
    meter = model.meter(model.radiance @ others.T.astype(np.float64), axis=1)
    return _Others(_inverse(F), E, W, K, None if meter is None else meter.T)


def _score(model: PatternModel, o: _Others, G: np.ndarray, Ep: np.ndarray, Wp: np.ndarray, x: np.ndarray,
           rr: np.ndarray) -> np.ndarray:
    """Gains of candidates given ``E p`` ``(n_c, V, k)``, ``W p`` ``(n_c, V, m_o)``, typical radiance ``x`` and
    :math:`\\sum_{l \\in p} r_{vl}^2` ``rr`` ``(n_c, V)``."""
    Wv = Wp.transpose(1, 0, 2)                                             # (V, n_c, m_o)
    s = model.variance(x, o.meter) + model.model_error ** 2 * rr - np.sum(np.matmul(Wv, o.K) * Wv, axis=2).T
    return _gains(o.Q, G, Ep, s)


def _candidate_gains(model: PatternModel, o: _Others, G: np.ndarray, cand: np.ndarray) -> np.ndarray:
    c = cand.astype(np.float64)
    return _score(model, o, G, np.matmul(o.E, c.T).transpose(2, 0, 1), np.matmul(o.W, c.T).transpose(2, 0, 1),
                  c @ model.radiance.T, c @ (model.radiance ** 2).T)


@dataclass(frozen=True)
class _FlipTerms:
    """What every flip scan against the same others shares (:func:`_flip_terms`).

    A candidate ``p ± e_l`` has rows :math:`a \\pm E_l` per view (``a = E p``, :math:`E_l` the ``l``-th
    columns of :class:`_Others` ``E``), so its :math:`S = A Q A^T` and :math:`T = A H A^T` (:math:`H = Q G Q`)
    of :func:`_gains` are :math:`a Q a^T \\pm (X_l + X_l^T) + E_l Q E_l^T` with :math:`X_l = E_l Q a^T`, and
    the same with ``H``: the terms without ``a`` are formed once, and a scan costs
    :math:`O(n_{leds}\\, n_{views}^2\\, k)` instead of :math:`O(n_{leds}\\, n_{views}\\, k^2)`."""

    H: np.ndarray      # (k, k) Q G Q
    EQ: np.ndarray     # (n, V, k) E_l^T Q
    EH: np.ndarray     # (n, V, k) E_l^T H
    C1: np.ndarray     # (n, V, V) E_l^T Q E_l
    C2: np.ndarray     # (n, V, V) E_l^T H E_l
    WKW: np.ndarray    # (n, V) W_l^T K W_l


def _flip_terms(o: _Others, G: np.ndarray) -> _FlipTerms:
    V, k, n = o.E.shape
    H = o.Q @ G @ o.Q
    El = np.ascontiguousarray(o.E.transpose(2, 0, 1))                      # (n, V, k)
    EQ = (El.reshape(n * V, k) @ o.Q).reshape(n, V, k)
    EH = (El.reshape(n * V, k) @ H).reshape(n, V, k)
    return _FlipTerms(H, EQ, EH, np.matmul(EQ, El.transpose(0, 2, 1)), np.matmul(EH, El.transpose(0, 2, 1)),
                      np.sum(o.W * np.matmul(o.K, o.W), axis=1).T)


def _flip_scan(model: PatternModel, o: _Others, G: np.ndarray, pattern: np.ndarray,
               terms: _FlipTerms | None = None) -> np.ndarray:
    """Gain of the pattern with each one bit flipped (``(n_leds,)``; -inf where the flip empties it).

    The same gains as :func:`_score` of every flipped pattern, from the terms every scan against ``o`` shares
    (:class:`_FlipTerms`; formed here when not given)."""
    t = _flip_terms(o, G) if terms is None else terms
    ok = (pattern.sum() > 1) | (pattern == 0)                              # never switch the last LED off
    out = np.full(pattern.size, -np.inf)
    if not ok.any():
        return out
    n, V, k = t.EQ.shape
    r = model.radiance
    ok = slice(None) if ok.all() else ok                                   # a view, not a copy, where all flip
    sign = np.where(pattern > 0, -1.0, 1.0)[ok][:, None, None]            # flip: on -> off, off -> on
    p = pattern.astype(np.float64)
    a = o.E @ p                                                            # (V, k): the rows of p
    X = (t.EQ.reshape(n * V, k) @ a.T).reshape(n, V, V)[ok]               # E_l^T Q a^T
    Y = (t.EH.reshape(n * V, k) @ a.T).reshape(n, V, V)[ok]
    S = (a @ o.Q @ a.T)[None] + sign * (X + X.transpose(0, 2, 1)) + t.C1[ok]
    T = (a @ t.H @ a.T)[None] + sign * (Y + Y.transpose(0, 2, 1)) + t.C2[ok]
    Wp = o.W @ p                                                           # (V, m_o)
    KWp = np.matmul(o.K, Wp[..., None])[..., 0]                           # (V, m_o)
    s1 = sign[:, :, 0]
    quad = (np.einsum("vm,vm->v", Wp, KWp)[None] + 2.0 * s1 * np.einsum("vml,vm->lv", o.W, KWp)[ok]
            + t.WKW[ok])                                                   # (W p')^T K (W p') of each flip
    x = (r @ p)[None] + s1 * r.T[ok]
    rr = (r ** 2 @ p)[None] + s1 * (r ** 2).T[ok]
    idx = np.arange(V)
    S[:, idx, idx] += model.variance(x, o.meter) + model.model_error ** 2 * rr - quad
    out[ok] = _trace_solve(S, T)
    return out


def _improve(model: PatternModel, o: _Others, G: np.ndarray, pattern: np.ndarray, max_flips: int,
             tol: float) -> np.ndarray:
    """Bit flips while one raises the pattern's gain by more than ``tol`` (relative): per scan the improving
    flips, best first, up to a quarter of them at once where that beats the best single flip, else the best."""
    pattern = pattern.copy()
    gain = float(_candidate_gains(model, o, G, pattern[None])[0])
    terms = _flip_terms(o, G)
    flips = 0
    while flips < max_flips:
        scan = _flip_scan(model, o, G, pattern, terms)
        better = np.flatnonzero(scan > gain + tol * abs(gain))
        if not better.size:
            break
        order = better[np.argsort(-scan[better])]
        many = pattern.copy()
        many[order[:max(1, min(len(order) // 4, max_flips - flips))]] ^= 1
        g_many = float(_candidate_gains(model, o, G, many[None])[0]) if many.any() else -np.inf
        if g_many > scan[order[0]]:
            flips += int(np.sum(many != pattern))
            pattern, gain = many, g_many
        else:
            pattern[order[0]] ^= 1
            flips += 1
            gain = float(scan[order[0]])
    return pattern


def _inverse(F: np.ndarray) -> np.ndarray:
    Q = np.linalg.inv(F)
    return 0.5 * (Q + Q.T)


def _objective(model: PatternModel, patterns: np.ndarray) -> float:
    return float(np.trace(model.gram @ _inverse(_information(model, patterns))))


def design_patterns(model: PatternModel, m: int, *, seed: int = 0, sweeps: int = 1, max_flips: int | None = None,
                    tol: float = 1e-6, start: np.ndarray | None = None) -> PatternDesign:
    """``m`` binary patterns that minimise the expected error :math:`J` (module docstring).

    Parameters
    ----------
    model : PatternModel
    m : int
        Number of patterns (>= 1).
    seed : int
        Seeds the order in which the refinement visits the patterns.
    sweeps : int
        Refinement sweeps over all patterns after the greedy start (0: none).
    max_flips : int, optional
        Most bit flips per pattern and visit (default ``n_leds``).
    tol : float
        A flip is taken when it raises the pattern's contribution by more than this fraction.
    start : (m, n_leds) array_like of 0/1, optional
        Patterns to refine instead of the greedy start (e.g. :func:`select_rows` of the S-matrix).

    Returns
    -------
    design : PatternDesign
        ``method='greedy'``; ``history`` holds :math:`J` after each added
        pattern and each sweep (non-increasing).

    Notes
    -----
    Greedy start: pattern ``j`` begins as the single LED that lowers :math:`J`
    most given patterns ``0 .. j-1`` and grows or shrinks by the best bit flip
    while one helps. Refinement: each pattern in turn is taken out and improved
    by bit flips against the others. A pattern's contribution given the others
    is a rank-``n_views`` update of :math:`F` (:class:`_Others`, a Schur complement
    for the model error shared with the others), so every candidate flip is
    scored at once by Woodbury (:func:`_gains`); the terms every scan against the same
    others shares are formed once (:class:`_FlipTerms`), so a scan costs
    :math:`O(n_{leds}\\, n_{views}\\, (n_{views} k + m))`. Same inputs and seed give the same patterns.
    """
    m = int(m)
    if m < 1:
        raise ValueError(f"m must be >= 1 pattern, got {m}")
    n = model.n_leds
    max_flips = n if max_flips is None else int(max_flips)
    G = model.gram
    patterns = np.zeros((m, n), dtype=np.uint8)
    history: list[float] = []
    zero = np.zeros(n, dtype=np.uint8)
    if start is not None:
        patterns = _as_binary(start, n).copy()
        if patterns.shape[0] != m:
            raise ValueError(f"start has {patterns.shape[0]} patterns, not m={m}")
        history.append(_objective(model, patterns))
    for j in range(m if start is None else 0):                             # greedy: add one pattern at a time
        o = _others(model, patterns[:j])
        start = zero.copy()
        start[int(np.argmax(_flip_scan(model, o, G, zero)))] = 1           # the best single LED
        patterns[j] = _improve(model, o, G, start, max_flips, tol)
        history.append(_objective(model, patterns[:j + 1]))
    rng = np.random.default_rng(seed)
    current = history[-1]                                                  # J of the m patterns (m >= 1)
    for _ in range(int(sweeps)):                                           # coordinate descent on the bits
        for j in rng.permutation(m):
            o = _others(model, np.delete(patterns, j, axis=0))
            new = _improve(model, o, G, patterns[j], max_flips, tol)
            if model.single_exposure:                  # scored with the others' meter held: keep it if J falls
                trial = patterns.copy()
                trial[j] = new
                value = _objective(model, trial)
                if value > current:
                    continue
                current = value
            patterns[j] = new
        current = current if model.single_exposure else _objective(model, patterns)
        history.append(current)
    return _design(model, patterns, "greedy", history[:-1])


def select_rows(model: PatternModel, candidates: np.ndarray, m: int) -> tuple[np.ndarray, PatternDesign]:
    """``m`` of the candidate patterns (e.g. the S-matrix rows), chosen greedily on :math:`J`.

    Parameters
    ----------
    model : PatternModel
    candidates : (n_c, n_leds) array_like of 0/1
    m : int
        ``1 <= m <= n_c``.

    Returns
    -------
    rows : (m,) ndarray of int64
        Indices of the chosen candidates, in the order chosen.
    design : PatternDesign
        ``method='select'``, the chosen patterns in that order.
    """
    cand = _as_binary(candidates, model.n_leds)
    m = int(m)
    if not 1 <= m <= cand.shape[0]:
        raise ValueError(f"m must lie in 1..{cand.shape[0]} (the candidates), got {m}")
    G = model.gram
    chosen: list[int] = []
    history: list[float] = []
    free = np.ones(cand.shape[0], dtype=bool)
    for _ in range(m):
        o = _others(model, cand[chosen])
        g = np.full(cand.shape[0], -np.inf)
        g[free] = _candidate_gains(model, o, G, cand[free])
        best = int(np.argmax(g))
        chosen.append(best)
        free[best] = False
        history.append(_objective(model, cand[chosen]))
    rows = np.asarray(chosen, dtype=np.int64)
    return rows, _design(model, cand[rows], "select", history[:-1])


def random_patterns(n_leds: int, m: int, seed: int = 0, p_on: float = 0.5) -> np.ndarray:
    """``m`` random binary patterns (each LED on with probability ``p_on``; none empty), ``(m, n_leds)`` uint8."""
    rng = np.random.default_rng(seed)
    p = (rng.random((int(m), int(n_leds))) < p_on).astype(np.uint8)
    for i in np.flatnonzero(p.sum(axis=1) == 0):
        p[i, rng.integers(n_leds)] = 1
    return p


# --------------------------------------------------------------------------- the solve


def pattern_operator(model: PatternModel, patterns: np.ndarray, *, dtype: DTypeLike = np.float32) -> SolveOperator:
    """The one-solve reconstruction operator of binary patterns (paper 4, eq. (10), noise-whitened).

    Parameters
    ----------
    model : PatternModel
    patterns : (m, n_leds) array_like of 0/1
    dtype : float32 or float64

    Returns
    -------
    operator : SolveOperator
        :func:`btfcore.acquisition.reconstruct.apply` maps the measured images
        ``(n_views * m, n_tx)`` (view-major, pattern fastest: the order of
        :func:`btfcore.acquisition.reconstruct.measure` with ``patterns``) to
        ``(n_lv, n_tx)``. ``method='direct'``.

    Notes
    -----
    With :math:`W = \\operatorname{blockdiag}(L_v^{-1})`, :math:`\\Omega_v = L_v L_v^T`
    the predicted covariance of view ``v``'s images (noise and model error,
    :class:`PatternModel`), paper 4's eq. (10) on the whitened system
    :math:`W A` with :math:`R = \\Sigma'^{-1}`, :math:`\\Sigma' = \\sqrt{s}\\,\\Sigma`
    (λ = 1 in whitened units) is the MAP estimate

    .. math:: C = (A^T \\Omega^{-1} A + P^{-1})^{-1} A^T \\Omega^{-1} y,

    whose error covariance is the :math:`F^{-1}` of :func:`expected_error`. It is
    built by :func:`btfcore.acquisition.reconstruct.solve_operator` (``'tikhonov'``
    on the whitened rows), then applied to :math:`W y`.
    """
    p = _as_binary(patterns, model.n_leds)
    A, omega = _rows(model, p)
    L_inv = np.linalg.inv(np.linalg.cholesky(omega))                       # (V, m, m): Omega_v = L L^T
    Aw = np.matmul(L_inv, A).reshape(-1, model.k)                          # W (I (x) M) U, W = blockdiag(L_v^-1)
    op = solve_operator(Aw, np.sqrt(model.prior), method="tikhonov", lam=1.0, fused=False, dtype=np.float64)
    Rw = op.coefficients.reshape(model.k, model.n_views, p.shape[0])
    R = np.matmul(Rw.transpose(1, 0, 2), L_inv).transpose(1, 0, 2).reshape(model.k, -1)   # eq. (10) on W y
    dt = np.dtype(dtype)
    return dataclasses.replace(op, coefficients=R.astype(dt), basis=model.U.astype(dt), fused=None,
                               method="direct", rows=None)
