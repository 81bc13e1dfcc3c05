"""Least-squares demultiplexing of illumination-multiplexed captures.

A multiplexed capture lights the sample with *patterns* of LEDs instead of
single LEDs. Light superposes, so with ``M`` the binary ``(n_illum, n_leds)``
pattern matrix (rows = patterns, columns = LEDs) and ``B`` the single-light
BTF of one view (rows = LEDs, columns = pixels x channels),

.. math:: B_{multiplexed} = M B

(thesis §3.1; App. "Multiplexed acquisition", 3.3). Demultiplexing solves
this per pixel in the least-squares sense. The solve operator
:math:`P = (M^T M)^{-1} M^T` is precomputed once and applied to a whole chunk
of pixels as one matrix product; for (truncated) S-matrices it has a closed
form, otherwise it is the Moore-Penrose pseudo-inverse.

The module also predicts the noise of the result: the thesis' SNR gain of
multiplexing for signal-independent noise (:func:`snr_gain`) and its
degradation under photon noise (:func:`demultiplexed_noise_std`,
:func:`noise_gain`).

References
----------
.. [1] The thesis, ch. 3.1 (summary of papers 2 and 3): the SNR ratio and
   photon noise; App. "Multiplexed acquisition" (paper 2, SPIE 9398) §3.3 and
   the VMV paper §3.2 (S-matrices, the quadratic residue construction,
   truncation and least squares).
.. [2] M. Harwit and N. J. A. Sloane, *Hadamard Transform Optics*, Academic
   Press, 1979, ch. 2-3.
.. [3] Y. Y. Schechner, S. K. Nayar and P. N. Belhumeur, "Multiplexing for
   optimal lighting", IEEE TPAMI 29(8), 2007.
"""

from __future__ import annotations

import numpy as np

from btfcore import warn_ill_conditioned
from btfcore.acquisition.hadamard import is_s_matrix_order

__all__ = [
    "DEMULTIPLEX_METHODS",
    "demultiplex",
    "demultiplex_operator",
    "demultiplexed_noise_std",
    "noise_gain",
    "s_matrix_inverse",
    "snr_gain",
]

#: Methods of :func:`demultiplex` and :func:`demultiplex_operator`.
DEMULTIPLEX_METHODS: tuple[str, ...] = ("lstsq", "pinv")


# --------------------------------------------------------------------------- validation


def _as_patterns(patterns, name: str = "patterns") -> np.ndarray:
    """Validate a binary ``(n_illum, n_leds)`` matrix; return it as float64."""
    p = np.asarray(patterns)
    if p.ndim != 2 or p.shape[0] == 0 or p.shape[1] == 0:
        raise ValueError(f"{name} must be a non-empty (n_illum, n_leds) matrix, got shape {p.shape}")
    if not (np.issubdtype(p.dtype, np.number) or p.dtype == np.bool_):
        raise ValueError(f"{name} must be numeric or boolean, got dtype {p.dtype}")
    if np.iscomplexobj(p):
        raise ValueError(f"{name} must be real, got dtype {p.dtype}")
    p = p.astype(np.float64)
    bad = np.argwhere(~((p == 0.0) | (p == 1.0)))              # NaN fails both tests
    if bad.size:
        i, j = (int(v) for v in bad[0])
        raise ValueError(
            f"{name} must be binary (LEDs on/off): {name}[{i}, {j}] = {float(p[i, j])!r} "
            f"({len(bad)} non-binary entries in all); pass 0/1 patterns"
        )
    return p


def _s_matrix_gram_ok(p: np.ndarray) -> bool:
    """Whether ``p`` holds columns of an S-matrix of order ``n_illum``: ``p^T p = ((n+1)/4)(I + J)``."""
    n, k = p.shape
    if k > n or not is_s_matrix_order(n):
        return False
    want = (n + 1) // 4 * (np.eye(k) + 1.0)
    return bool(np.array_equal(p.T @ p, want))                    # 0/1 products: exact in float64 (BLAS)


# --------------------------------------------------------------------------- operators


def s_matrix_inverse(S: np.ndarray) -> np.ndarray:
    """Closed-form inverse of an S-matrix.

    Parameters
    ----------
    S : (n, n) array_like
        Binary S-matrix of a valid order ``n`` (prime, ``n % 4 == 3``), e.g.
        :func:`btfcore.acquisition.hadamard.s_matrix` or a row/column permutation of it.

    Returns
    -------
    S_inv : (n, n) ndarray of float64
        :math:`S^{-1}`.

    Raises
    ------
    ValueError
        If ``S`` is not square or not binary (the message names the first bad
        index), if ``n`` is not a valid S-matrix order, or if ``S`` does not
        satisfy :math:`S^T S = \\tfrac{n+1}{4}(I + J)`.

    Notes
    -----
    Because :math:`S^T S = \\tfrac{n+1}{4}(I + J)` and every row of ``S`` has
    :math:`(n+1)/2` ones,

    .. math:: S^{-1} = \\frac{2}{n+1} \\left(2 S^T - J\\right),

    with :math:`J` the all-ones matrix (Harwit & Sloane 1979, ch. 3; thesis
    App. "Multiplexed acquisition", 3.3). Every entry is :math:`\\pm 2/(n+1)`.
    """
    p = _as_patterns(S, "S")
    n, k = p.shape
    if n != k:
        raise ValueError(f"S must be square, got shape {p.shape}")
    if not is_s_matrix_order(n):
        raise ValueError(
            f"no S-matrix of order {n} exists for the quadratic residue construction: the order must "
            f"be a prime with n % 4 == 3 (3, 7, 11, 19, 23, ...)"
        )
    if not _s_matrix_gram_ok(p):
        raise ValueError(f"S is not an S-matrix of order {n}: S^T S != ((n+1)/4) (I + J)")
    return (2.0 / (n + 1)) * (2.0 * p.T - 1.0)                 # eq. S^-1 = 2/(n+1) (2 S^T - J)  (App. 3.3)


def demultiplex_operator(patterns: np.ndarray, *, method: str = "lstsq") -> np.ndarray:
    """Least-squares solve operator of a pattern matrix.

    Parameters
    ----------
    patterns : (n_illum, n_leds) array_like
        Binary illumination patterns, row ``i`` = pattern ``i``, column
        ``j`` = LED ``j`` (e.g. :func:`btfcore.acquisition.hadamard.multiplexing_patterns`).
    method : {'lstsq', 'pinv'}
        ``'lstsq'`` uses the closed form when ``patterns`` are single-LED
        (a permutation matrix, whose inverse is its transpose) or (the
        leading columns of) an S-matrix of order ``n_illum``, and the SVD
        pseudo-inverse otherwise; ``'pinv'`` always uses the SVD.

    Returns
    -------
    P : (n_leds, n_illum) ndarray of float64
        :math:`P = (M^T M)^{-1} M^T`, so that :math:`\\hat B = P\\, B_{multiplexed}`.

    Raises
    ------
    ValueError
        If the patterns are not binary (names the index), or have rank below
        ``n_leds`` (names the rank): the LEDs cannot be separated.

    Warns
    -----
    btfcore.IllConditionedWarning
        When the SVD path meets patterns whose condition number exceeds
        :data:`btfcore.ILL_CONDITIONED_SOLVE` (the message gives it and the fix).

    Notes
    -----
    For ``k`` columns of an S-matrix of order ``n``,
    :math:`M^T M = \\tfrac{n+1}{4}(I_k + J_k)`, whose inverse is
    :math:`\\tfrac{4}{n+1}(I_k - J_k/(k+1))`, hence

    .. math:: P = \\frac{4}{n+1}\\left(I_k - \\frac{J_k}{k+1}\\right) M^T,

    which for ``k = n`` is :math:`S^{-1} = \\tfrac{2}{n+1}(2S^T - J)`. The
    thesis solves the truncated system "in the least-squares sense" (App.
    "Multiplexed acquisition" §3.3; VMV paper §3.2).
    """
    if method not in DEMULTIPLEX_METHODS:
        raise ValueError(f"unknown demultiplexing method {method!r}; choose one of {DEMULTIPLEX_METHODS}")
    p = _as_patterns(patterns)
    n, k = p.shape
    if k > n:
        raise ValueError(
            f"patterns have rank at most {n} (n_illum = {n}) for {k} LEDs: need at least as many "
            f"linearly independent patterns as LEDs"
        )
    if method == "lstsq" and n == k and np.array_equal(p.sum(axis=0), np.ones(k)) \
            and np.array_equal(p.sum(axis=1), np.ones(n)):
        return p.T.copy()                                         # single-LED patterns: M^-1 = M^T
    if method == "lstsq" and _s_matrix_gram_ok(p):
        if k == n:
            return s_matrix_inverse(p)
        gram_inv = (4.0 / (n + 1)) * (np.eye(k) - 1.0 / (k + 1))  # eq. (M^T M)^-1 = 4/(n+1) (I - J/(k+1))
        return gram_inv @ p.T                                     # eq. P = (M^T M)^-1 M^T
    U, s, Vt = np.linalg.svd(p, full_matrices=False)
    tol = max(p.shape) * np.finfo(np.float64).eps * s[0]
    rank = int(np.sum(s > tol))
    if rank < k:
        raise ValueError(
            f"patterns are rank-deficient: rank {rank} < {k} LEDs (smallest singular value "
            f"{s[-1]:.3g}); the LEDs cannot be separated, use e.g. an S-matrix "
            f"(btfcore.acquisition.hadamard.multiplexing_patterns)"
        )
    warn_ill_conditioned(float(s[0] / s[-1]), f"the ({n}, {k}) illumination patterns (demultiplexing)",
                         "use an S-matrix (btfcore.acquisition.hadamard.multiplexing_patterns) or add patterns "
                         "that separate the LEDs better")
    return (Vt.T / s) @ U.T                                       # eq. P = V S^-1 U^T = M^+


# --------------------------------------------------------------------------- demultiplexing


def _first_nonfinite(x: np.ndarray, name: str) -> None:
    finite = np.isfinite(x)
    if not finite.all():
        idx = tuple(int(v) for v in np.unravel_index(int(np.argmin(finite)), x.shape))
        raise ValueError(
            f"{name} contains NaN or Inf: {name}{list(idx)} = {float(x[idx])!r} "
            f"({int(x.size - finite.sum())} non-finite values in all); fix or mask them before demultiplexing"
        )


def demultiplex(measured: np.ndarray, patterns: np.ndarray, *, method: str = "lstsq") -> np.ndarray:
    """Recover single-LED images from multiplexed ones by least squares per pixel.

    Parameters
    ----------
    measured : (n_illum, ...) ndarray of float
        One image (any trailing shape: pixels, channels) per pattern, in the
        order of the rows of ``patterns``; linear radiance, finite.
    patterns : (n_illum, n_leds) array_like
        Binary illumination patterns.
    method : {'lstsq', 'pinv'}
        See :func:`demultiplex_operator`.

    Returns
    -------
    single : (n_leds, ...) ndarray
        The least-squares single-LED images, float32 for float32 input and
        float64 otherwise.

    Raises
    ------
    ValueError
        On non-binary or rank-deficient patterns, a first axis that does not
        match ``n_illum``, or NaN/Inf in ``measured`` (names the index).

    Notes
    -----
    With :math:`Y` the measurements flattened to ``(n_illum, n_px)`` and
    :math:`P` from :func:`demultiplex_operator`,

    .. math:: \\hat B = \\arg\\min_B \\|M B - Y\\|_F^2 = P\\, Y,

    computed as one matrix product over all pixels of the chunk (thesis
    §3.1, :math:`B_{multiplexed} = M B`). Noise-free data of a full-rank
    ``M`` is recovered exactly (to rounding).
    """
    x = np.asarray(measured)
    if not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)):
        raise ValueError(f"measured must be real numbers, got dtype {x.dtype}")
    P = demultiplex_operator(patterns, method=method)
    n_leds, n_illum = P.shape
    if x.ndim < 1 or x.shape[0] != n_illum:
        raise ValueError(
            f"measured has shape {x.shape}: its first axis must be the {n_illum} patterns "
            f"(rows of patterns)"
        )
    _first_nonfinite(x, "measured")
    dtype = np.float32 if x.dtype == np.float32 else np.float64
    flat = x.reshape(n_illum, -1)
    out = P.astype(dtype) @ flat.astype(dtype, copy=False)        # eq. B = P B_multiplexed  (§3.1)
    return out.reshape((n_leds,) + x.shape[1:])


# --------------------------------------------------------------------------- noise


def snr_gain(patterns: np.ndarray) -> float:
    """Multiplexing SNR gain for signal-independent noise (thesis §3.1).

    Parameters
    ----------
    patterns : (n_illum, n_leds) array_like
        Binary, full column rank.

    Returns
    -------
    gain : float
        Ratio of the r.m.s. noise of a single-light acquisition to the r.m.s.
        noise of the demultiplexed result, for the same per-image noise
        (equal exposure, signal-independent noise): > 1 means multiplexing
        wins.

    Notes
    -----
    Thesis ch. 3.1 (the SNR ratio), after Harwit & Sloane:

    .. math:: \\sqrt{\\frac{\\mathrm{MSE}}{\\mathrm{MSE}_{demultiplexed}}}
              = \\sqrt{\\frac{n_i}{\\operatorname{tr}\\left[(M^T M)^{-1}\\right]}}

    with :math:`n_i` the number of LEDs (columns of ``M``). The identity
    (single-light) design gives 1. An S-matrix of order ``n`` has
    :math:`\\operatorname{tr}[(S^T S)^{-1}] = 4n^2/(n+1)^2`, so the gain is
    :math:`(n+1)/(2\\sqrt n) \\approx \\sqrt n / 2` (App. "Multiplexed acquisition" §3.3;
    VMV paper §3.2).
    The trace is computed as :math:`\\|P\\|_F^2`, since
    :math:`P P^T = (M^T M)^{-1}`.
    """
    P = demultiplex_operator(patterns)
    n_i = P.shape[0]
    trace = float(np.sum(P * P))                                  # tr[(M^T M)^-1] = ||P||_F^2
    return float(np.sqrt(n_i / trace))                            # eq. (§3.1) sqrt(n_i / tr[(M^T M)^-1])


def demultiplexed_noise_std(
    patterns: np.ndarray,
    signal: np.ndarray | None = None,
    *,
    read_noise: float = 1.0,
) -> np.ndarray:
    """Predicted noise standard deviation of each demultiplexed LED image.

    Parameters
    ----------
    patterns : (n_illum, n_leds) array_like
        Binary, full column rank.
    signal : (n_leds, ...) array_like, optional
        Mean single-LED signal in photo-electrons (Poisson: variance = mean).
        ``None`` for signal-independent noise only.
    read_noise : float
        Standard deviation of the signal-independent (read) noise of every
        captured image, electrons.

    Returns
    -------
    std : (n_leds, ...) ndarray of float64
        Noise standard deviation of :func:`demultiplex`'s output, per LED
        (and per pixel when ``signal`` has trailing axes; ``(n_leds,)``
        when ``signal`` is None).

    Notes
    -----
    Pattern ``i`` collects :math:`(M x)_i` electrons, so its variance is
    :math:`\\sigma_i^2 = \\sigma_r^2 + (M x)_i` (light superposes before the
    sensor adds noise). The demultiplexed image :math:`P y` then has

    .. math:: \\operatorname{Var}(\\hat x_l) = \\sum_i P_{li}^2
              \\left(\\sigma_r^2 + (M x)_i\\right).

    A multiplexed image holds the light of :math:`(n+1)/2` LEDs, so its
    photon noise is about :math:`\\sqrt{(n+1)/2}` times that of a single-LED
    image: the photon-noise term eats up the multiplexing advantage (thesis
    §3.1, the SNR-gain formula and the remark on photon noise that follows it).
    """
    P = demultiplex_operator(patterns)
    M = _as_patterns(patterns)
    read_noise = float(read_noise)
    if not np.isfinite(read_noise) or read_noise < 0:
        raise ValueError(f"read_noise must be finite and >= 0, got {read_noise!r}")
    P2 = P * P
    if signal is None:
        return np.sqrt(P2.sum(axis=1)) * read_noise               # eq. sigma_r sqrt(sum_i P_li^2)
    x = np.asarray(signal, dtype=np.float64)
    if x.ndim < 1 or x.shape[0] != M.shape[1]:
        raise ValueError(f"signal has shape {x.shape}: its first axis must be the {M.shape[1]} LEDs")
    _first_nonfinite(x, "signal")
    if np.any(x < 0):
        raise ValueError("signal (mean photo-electrons) must be >= 0")
    flat = x.reshape(x.shape[0], -1)
    var_meas = read_noise**2 + M @ flat                           # eq. sigma_i^2 = sigma_r^2 + (M x)_i
    var = P2 @ var_meas                                           # eq. Var(x_l) = sum_i P_li^2 sigma_i^2
    return np.sqrt(var).reshape(x.shape)


def noise_gain(patterns: np.ndarray, signal: np.ndarray | None = None, *, read_noise: float = 1.0) -> float:
    """Predicted r.m.s. noise ratio single-light / demultiplexed, with photon noise.

    Parameters
    ----------
    patterns : (n_illum, n_leds) array_like
        Binary, full column rank.
    signal : (n_leds, ...) array_like, optional
        Mean single-LED signal in photo-electrons; ``None`` gives
        :func:`snr_gain`.
    read_noise : float
        Read-noise standard deviation, electrons (the same exposure and
        sensor for the single-light and the multiplexed capture).

    Returns
    -------
    gain : float
        :math:`\\sqrt{\\overline{\\sigma_{single}^2} / \\overline{\\operatorname{Var}(\\hat x)}}`
        averaged over LEDs and pixels; > 1 means multiplexing wins.

    Notes
    -----
    A single-light image of LED ``l`` has variance
    :math:`\\sigma_r^2 + x_l`; the demultiplexed one has the variance of
    :func:`demultiplexed_noise_std`. For an S-matrix of order ``n`` and equal
    signals :math:`x`,

    .. math:: g^2 = \\frac{(n+1)^2}{4n} \\cdot
              \\frac{\\sigma_r^2 + x}{\\sigma_r^2 + \\tfrac{n+1}{2} x},

    which is :func:`snr_gain` squared for :math:`x \\ll \\sigma_r^2` and
    tends to :math:`(n+1)/(2n) \\approx 1/2` when photon noise dominates:
    the "degradation of signal-to-signal-dependent-noise ratio ... by
    :math:`1/\\sqrt 2` in the worst case" of thesis ch. 3.1.
    """
    M = _as_patterns(patterns)
    if signal is None:
        x = np.zeros((M.shape[1], 1))
    else:
        x = np.asarray(signal, dtype=np.float64)
    var_demux = demultiplexed_noise_std(M, x, read_noise=read_noise) ** 2
    var_single = float(read_noise) ** 2 + x                       # eq. sigma_single^2 = sigma_r^2 + x_l
    mean_demux = float(np.mean(var_demux))
    if mean_demux <= 0:
        raise ValueError("no noise at all (read_noise = 0 and zero signal): the gain is undefined")
    return float(np.sqrt(np.mean(var_single) / mean_demux))
