"""Dong et al.'s regularised up-sampling of eigentextures: the baseline of the SR paper (§3.4, eqs. (3)-(4)).

Image formation (SR paper §3.4, eq. (3)): a low-resolution image ``y`` is
the high-resolution image ``x`` blurred by the camera's point spread function
``P``, down-sampled by ``D`` and disturbed by noise,
:math:`y = D P x + n`. Dong et al. recover

.. math:: \\hat x = \\arg\\min_x \\|D P x - y\\|_2^2 + \\alpha \\|L x\\|_2^2
   \\qquad\\text{(eq. (4), } \\phi(x) = \\|L x\\|^2\\text{)}

through the regularised normal equations
:math:`(P^T D^T D P + \\alpha L^T L)\\, x = P^T D^T y`, and apply it not to
every texture of a BTF but to the eigentextures of its truncated SVD
:math:`B \\approx U (S V^T)` (rows of :math:`S V^T`), keeping ``U``
(SR paper §3.4); the SR paper uses rank 300 and Dong et al.'s 9 x 9 Gaussian
PSF of sigma 1.5 (SR paper §5.2.1).

Operators (one image, ``f`` the factor):

* ``D``: the mean of each ``f x f`` block, exactly
  :func:`btfcore.superres.scaling.area_downsample` (pixel ``i`` covers
  high-resolution pixels ``f i .. f i + f - 1``);
* ``P``: a normalised, separable Gaussian of ``psf_sigma`` high-resolution
  pixels truncated to ``psf_size`` taps (:func:`gaussian_psf`); the identity
  at ``psf_sigma = 0``;
* ``L``: the 5-point 2-D Laplacian.

**Boundary condition: reflective** (half-sample symmetric, ``d c b a | a b c
d``, scipy.ndimage's ``mode='reflect'``, OpenCV's ``BORDER_REFLECT``) for
``P`` and ``L`` (for ``L`` this is the Neumann Laplacian). With it the
problem is the restriction of the same problem on the mirrored image of twice
the size with *periodic* boundaries (its unique solution is mirror-symmetric),
where every operator is diagonal in the Fourier domain except ``D^T D``,
which couples each frequency with its ``f^2`` aliases: the system is
block-diagonal in ``f x f``-aliased groups, each block a diagonal plus a rank
one, and Sherman-Morrison solves it in closed form (:func:`_spectrum`).
Since the DFT of a mirrored image is its DCT-II up to a phase, the solution
is a real transfer function between the low-resolution image's DCT-II
coefficients and the high-resolution image's (:func:`_transfer`): an
*exact* solve (to float64 rounding; the normal equations' residual is about
1e-15) costing one DCT and one inverse DCT per image, for a whole batch at
once (about 1 ms per 96 x 96 -> 192 x 192 image on one core).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
from scipy import fft

from btfcore.model._lowrank import RankError
from btfcore.model.truncated_svd import truncated_svd
from btfcore.superres.scaling import check_factor, check_stack

__all__ = ["DEFAULT_ALPHA", "alpha_errors", "choose_alpha", "dong_eigentextures", "dong_upsample", "gaussian_psf"]

#: Default weight ``alpha`` of the Laplacian prior (eq. (4)); the SR paper does not give one.
#: Measured with :func:`alpha_errors` on synthetic textures (see :func:`dong_upsample`, Notes).
DEFAULT_ALPHA = 1e-3

#: Images solved together (bounds the float64 temporaries, about 1 MB per 100 x 100 input image at f = 2).
_BATCH = 64


def gaussian_psf(sigma: float, size: int | None = None) -> np.ndarray:
    """The 1-D taps of the separable Gaussian PSF ``P``: ``(size,)`` float64, summing to 1.

    Parameters
    ----------
    sigma : float
        Standard deviation in high-resolution pixels, ``>= 0``; 0 gives the
        identity ``[1.0]``.
    size : int, optional
        Odd number of taps; default ``2 ceil(3 sigma) + 1``. Dong et al.'s
        kernel (SR paper §5.2.1) is ``sigma=1.5, size=9``.
    """
    if not np.isfinite(sigma) or sigma < 0:
        raise ValueError(f"psf_sigma must be finite and >= 0, got {sigma!r}")
    if size is None:
        size = 2 * int(np.ceil(3 * sigma)) + 1
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1 or size % 2 == 0:
        raise ValueError(f"psf_size must be an odd integer >= 1, got {size!r}")
    if sigma == 0:
        return np.eye(1, int(size), (int(size) - 1) // 2)[0] if size > 1 else np.ones(1)
    t = np.arange(size) - (size - 1) / 2
    g = np.exp(-0.5 * (t / sigma) ** 2)
    return g / g.sum()


def _axis_response(n_hr: int, f: int, psf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis Fourier responses on a periodic grid of ``n_hr`` samples: of ``D``'s box times ``P``, and of ``L``.

    ``(D P x)[i] = (1/f) sum_u (P x)[f i + u]``, a correlation with offsets
    ``0 .. f - 1`` sampled at ``f i``; with numpy's forward FFT convention a
    correlation with taps ``g[t]`` at offsets ``t`` has response
    ``sum_t g[t] exp(+2 pi i k t / n_hr)``.
    """
    k = np.arange(n_hr)
    r = (psf.size - 1) // 2
    box = np.exp(2j * np.pi * np.outer(k, np.arange(f)) / n_hr).mean(axis=1)
    blur = np.exp(2j * np.pi * np.outer(k, np.arange(-r, r + 1)) / n_hr) @ psf
    laplacian = 2 * np.cos(2 * np.pi * k / n_hr) - 2
    return box * blur, laplacian


def _spectrum(h: int, w: int, f: int, alpha: float, psf_sigma: float, psf_size: int | None) -> np.ndarray:
    """The solution's transfer function ``G`` on the mirrored, periodic ``(2 f h, 2 f w)`` frequency grid.

    On the periodic grid, with ``c`` the response of ``D``'s box times ``P``
    and ``l`` that of ``L``, the normal equations at the ``f^2`` aliases
    ``k_a`` of a low-resolution frequency ``k0`` read
    :math:`(\\mathrm{diag}(d) + f^{-2} \\bar c c^T)\\, X = \\bar c\\, Y(k_0)`,
    :math:`d = \\alpha |l|^2` (``D^T D`` keeps every ``f``-th sample, which
    averages the aliases). Sherman-Morrison gives
    :math:`X_a = G_a Y(k_0)`,
    :math:`G_a = f^2 \\bar c_a / (d_a (f^2 + \\sum_b |c_b|^2 / d_b))`;
    at the constant frequency (``d = 0``) the solution is
    :math:`G_0 = f^2 / c_0` and zero at its aliases (exact: it solves that
    group's system, which is non-singular for ``alpha > 0``).
    """
    psf = gaussian_psf(psf_sigma, psf_size)
    n_hr, m_hr = 2 * f * h, 2 * f * w
    if (psf.size - 1) // 2 >= min(f * h, f * w):
        raise ValueError(f"psf_size {psf.size} is too large for images of {f * h} x {f * w} high-resolution "
                         "pixels; the kernel's radius must be smaller than each side")
    c_row, l_row = _axis_response(n_hr, f, psf)
    c_col, l_col = _axis_response(m_hr, f, psf)
    c = np.outer(c_row, c_col)
    d = alpha * np.add.outer(l_row, l_col) ** 2
    d[0, 0] = 1.0                                                            # set apart below
    ratio = np.abs(c) ** 2 / d
    ratio[0, 0] = 0.0
    alias_sum = ratio.reshape(f, n_hr // f, f, m_hr // f).sum(axis=(0, 2))  # sum over each group's aliases
    G = f * f * np.conj(c) / (d * (f * f + np.tile(alias_sum, (f, f))))
    G[::n_hr // f, ::m_hr // f] = 0.0                                       # the constant frequency's group
    G[0, 0] = f * f / c[0, 0]
    return G


def _fold(n_lr: int, n_hr: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per axis, the DCT-II coefficient of the low-resolution image that the mirrored spectrum holds at each
    high-resolution frequency ``k < n_hr``: its index, its sign (0 where it is zero) and the phase
    :math:`e^{i \\pi r / (2 n_{lr})} e^{-i \\pi k / (2 n_{hr})}` of the two DFT-DCT relations.

    The DFT of the half-sample mirrored sequence (period ``2 L``) is
    :math:`e^{i \\pi k / (2 L)}\\, \\mathrm{dct}(x)[k]` for ``k < L``, zero at
    ``L`` and conjugate-symmetric, so at ``r = k mod 2 n_lr > n_lr`` it is
    :math:`-e^{i \\pi r / (2 n_{lr})}\\, \\mathrm{dct}(y)[2 n_{lr} - r]`.
    """
    k = np.arange(n_hr)
    r = k % (2 * n_lr)
    index = np.where(r < n_lr, r, (2 * n_lr - r) % (2 * n_lr))
    sign = np.select([r < n_lr, r > n_lr], [1.0, -1.0], 0.0)
    phase = np.exp(1j * np.pi * (r / (2 * n_lr) - k / (2 * n_hr)))
    return np.minimum(index, n_lr - 1), sign, phase


@functools.lru_cache(maxsize=8)
def _transfer(h: int, w: int, f: int, alpha: float, psf_sigma: float, psf_size: int | None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. (4)'s solution as a real transfer between DCT-II coefficients: ``(T, rows, cols)``.

    The solution is ``idctn(T * dctn(y)[rows][:, cols])``, ``T`` of shape
    ``(f h, f w)``: :func:`_spectrum`'s ``G`` seen through the DFT-DCT
    relation of the mirrored images (:func:`_fold`). ``T`` is real because
    the solution of mirrored data is mirror-symmetric.
    """
    G = _spectrum(h, w, f, alpha, psf_sigma, psf_size)[:f * h, :f * w]
    rows, sign_r, phase_r = _fold(h, f * h)
    cols, sign_c, phase_c = _fold(w, f * w)
    T = (G * np.outer(sign_r * phase_r, sign_c * phase_c)).real
    for a in (T, rows, cols):
        a.setflags(write=False)                                              # shared through the cache
    return T, rows, cols


def _solve(images: np.ndarray, f: int, alpha: float, psf_sigma: float, psf_size: int | None) -> np.ndarray:
    """Eq. (4) for a float64 batch ``(b, h, w)``: ``(b, f h, f w)`` float64, reflective boundaries."""
    T, rows, cols = _transfer(images.shape[1], images.shape[2], f, alpha, psf_sigma, psf_size)
    coefficients = fft.dctn(images, type=2, axes=(1, 2))
    return fft.idctn(T * coefficients[:, rows][:, :, cols], type=2, axes=(1, 2))   # eq. (4)


def _check_alpha(alpha: float) -> float:
    if isinstance(alpha, bool) or not isinstance(alpha, (int, float, np.floating, np.integer)) \
            or not np.isfinite(alpha) or alpha <= 0:
        raise ValueError(f"alpha must be a finite number > 0, got {alpha!r}")
    return float(alpha)


def _check_finite(a: np.ndarray, name: str) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        raise ValueError(f"{name} holds {int(bad.sum())} NaN or infinite values (first at index "
                         f"{tuple(int(i) for i in np.argwhere(bad)[0])}); fix or mask them first")


def _upsample64(images: np.ndarray, f: int, alpha: float, psf_sigma: float, psf_size: int | None) -> np.ndarray:
    """:func:`dong_upsample` on validated input, batched, in float64."""
    n, h, w = images.shape
    out = np.empty((n, f * h, f * w))
    for start in range(0, n, _BATCH):
        out[start:start + _BATCH] = _solve(images[start:start + _BATCH].astype(np.float64), f, alpha,
                                           psf_sigma, psf_size)
    return out


def dong_upsample(images: np.ndarray, *, factor: int = 2, alpha: float = DEFAULT_ALPHA, psf_sigma: float = 0.0,
                  psf_size: int | None = None) -> np.ndarray:
    """Up-sample each image by Dong et al.'s regularised deconvolution, SR paper §3.4, eq. (4).

    Parameters
    ----------
    images : (n, h, w) array_like of real numbers
        Low-resolution images ``y`` (any scale and sign: eigentextures
        too).
    factor : int
        The scale factor ``f >= 1``.
    alpha : float
        Weight of the Laplacian prior, ``> 0`` (scale-free: the solution is
        linear in ``y``). The default, :data:`DEFAULT_ALPHA`, is the best of
        :func:`choose_alpha` on synthetic textures made by area
        down-sampling without a PSF (see Notes); choose it on the caller's
        validation split where the data or the PSF differ.
    psf_sigma : float
        Standard deviation of the Gaussian PSF ``P`` in high-resolution
        pixels; 0 (default) is the identity.
    psf_size : int, optional
        Odd number of PSF taps (default ``2 ceil(3 sigma) + 1``; SR paper
        §5.2.1 uses 9 with sigma 1.5).

    Returns
    -------
    (n, f h, f w) ndarray of float32
        :math:`\\hat x = (P^T D^T D P + \\alpha L^T L)^{-1} P^T D^T y` per
        image, with reflective boundaries (see the module docstring), solved
        exactly in float64.

    Raises
    ------
    ValueError
        ``images`` not a non-empty ``(n, h, w)`` stack or holding NaN or
        infinities, ``alpha <= 0``, a bad ``factor``, ``psf_sigma`` or
        ``psf_size``.

    Notes
    -----
    The default alpha: mean relative L2 errors (:func:`alpha_errors`,
    f = 2) on 24 seeded synthetic textures (0.5 + 0.2 x unit-variance
    Gaussian-filtered noise of 1-4 px correlation length, 96 x 96), their
    area down-sampled images plus Gaussian noise of 0-2 % of the mean:

    ============================  ======  ======  ======  ======  ======  =======
    alpha                          1e-5    1e-4    3e-4    1e-3    3e-3    1e-2
    ============================  ======  ======  ======  ======  ======  =======
    no PSF, no noise               3.56 %  3.56 %  3.56 %  3.58 %  3.62 %  3.84 %
    no PSF, 1 % noise              3.89 %  3.89 %  3.89 %  3.90 %  3.93 %  4.10 %
    PSF 9 x 9, sigma 1.5, 0 %      3.02 %  3.44 %  3.96 %  4.89 %  6.02 %  7.55 %
    PSF 9 x 9, sigma 1.5, 0.5 %    7.19 %  5.27 %  5.06 %  5.44 %  6.29 %  7.67 %
    PSF 9 x 9, sigma 1.5, 1 %     12.6 %   7.88 %  6.70 %  6.34 %  6.78 %  7.91 %
    PSF 9 x 9, sigma 1.5, 2 %     24.2 %  13.7 %  10.5 %   8.48 %  7.98 %  8.52 %
    ============================  ======  ======  ======  ======  ======  =======

    (bicubic: 4.90 % without PSF and noise, 13.3 % with the PSF.) Without a
    PSF, ``D`` alone is well posed and any alpha up to 1e-3 is within 0.02
    percentage points of the best; with the SR paper's PSF (§5.2.1) the best alpha grows with
    the noise, and 1e-3 is the best at 1 %. Hence ``DEFAULT_ALPHA = 1e-3``.
    """
    f = check_factor(factor)
    a = check_stack(images)
    if a.ndim != 3:
        raise ValueError(f"images must be a stack (n, h, w) of single-channel images, got shape {a.shape}")
    _check_finite(a, "images")
    alpha = _check_alpha(alpha)
    gaussian_psf(psf_sigma, psf_size)
    return _upsample64(a, f, alpha, float(psf_sigma), psf_size).astype(np.float32)


def _relative_errors(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per-image :math:`\\|x - t\\|_2 / \\|t\\|_2` of ``(n, ...)`` stacks (images of zero norm skipped)."""
    d = np.sqrt(((estimate - truth) ** 2).reshape(len(truth), -1).sum(axis=1))
    t = np.sqrt((truth.astype(np.float64) ** 2).reshape(len(truth), -1).sum(axis=1))
    return d[t > 0] / t[t > 0]


def alpha_errors(low: np.ndarray, high: np.ndarray, alphas: Sequence[float], *, factor: int = 2,
                 psf_sigma: float = 0.0, psf_size: int | None = None) -> np.ndarray:
    """Mean relative L2 error of :func:`dong_upsample` of ``low`` against ``high``, for each alpha.

    Parameters
    ----------
    low : (n, h, w) array_like
        Low-resolution images.
    high : (n, f h, f w) array_like
        Their high-resolution truth.
    alphas : sequence of float
        Candidate weights, each ``> 0``.
    factor, psf_sigma, psf_size :
        As :func:`dong_upsample`.

    Returns
    -------
    (len(alphas),) ndarray of float64
        :math:`\\frac1n \\sum_i \\|\\hat x_i - x_i\\|_2 / \\|x_i\\|_2` per
        alpha (images whose truth is zero are left out).
    """
    f = check_factor(factor)
    lo = check_stack(low, "low")
    hi = check_stack(high, "high")
    if lo.ndim != 3 or hi.shape != (lo.shape[0], f * lo.shape[1], f * lo.shape[2]):
        raise ValueError(f"high must be (n, f h, f w) = {(lo.shape[0], f * lo.shape[1], f * lo.shape[2])} for "
                         f"low {lo.shape} and factor {f}, got {hi.shape}")
    _check_finite(lo, "low")
    _check_finite(hi, "high")
    checked = [_check_alpha(a) for a in alphas]
    if not checked:
        raise ValueError("alphas is empty; give at least one candidate")
    if not (hi != 0).any():
        raise ValueError("high is all zero: no relative error to measure")
    gaussian_psf(psf_sigma, psf_size)
    return np.array([_relative_errors(_upsample64(lo, f, a, float(psf_sigma), psf_size), hi).mean()
                     for a in checked])


def choose_alpha(low: np.ndarray, high: np.ndarray, alphas: Sequence[float], *, factor: int = 2,
                 psf_sigma: float = 0.0, psf_size: int | None = None) -> float:
    """The alpha of ``alphas`` with the least mean relative L2 error of :func:`dong_upsample` (:func:`alpha_errors`).

    Meant for the caller's validation split: ``low`` (n, h, w) and its truth
    ``high`` (n, f h, f w), made as the data to be up-sampled is made (for
    the SR paper's Dong protocol, with the PSF blur before the down-sampling,
    §5.2.1). Ties go to the first.
    """
    errors = alpha_errors(low, high, alphas, factor=factor, psf_sigma=psf_sigma, psf_size=psf_size)
    return float(list(alphas)[int(np.argmin(errors))])


def dong_eigentextures(B: np.ndarray, *, rank: int = 300, factor: int = 2, alpha: float = DEFAULT_ALPHA,
                       psf_sigma: float = 0.0, psf_size: int | None = None) -> np.ndarray:
    """Up-sample a BTF by Dong et al.'s method on its eigentextures (SR paper §3.4; rank 300 in §5.2.1).

    Parameters
    ----------
    B : (n_lv, h, w, C) array_like of real numbers
        The low-resolution BTF, rows light/view pairs (docs/architecture.md,
        "Matrix convention"), linear values (``f = id`` of SR paper §3.2: no
        log).
    rank : int
        Eigentextures kept, ``>= 1``; clipped to ``min(n_lv, h w C)`` and to
        the numerical rank of ``B`` (directions beyond it hold no data).
    factor, alpha, psf_sigma, psf_size :
        As :func:`dong_upsample`.

    Returns
    -------
    (n_lv, f h, f w, C) ndarray of float32
        :math:`U\\, \\mathrm{up}(U^T B)`: ``B`` as the ``(n_lv, h w C)``
        matrix, ``U`` its leading ``k`` left singular vectors
        (:func:`btfcore.model.truncated_svd.truncated_svd`, ``'auto'``: the
        float64 Gram route, randomized when large), the eigentextures
        :math:`U^T B = S V^T` reshaped ``(k, h, w, C)`` and up-sampled per
        channel with :func:`dong_upsample`, recombined with ``U``. By
        linearity this equals up-sampling every texture of the rank-``k``
        approximation :math:`U U^T B`.

    Raises
    ------
    ValueError
        ``B`` not 4-D, empty or holding NaN or infinities, ``rank < 1``, or
        a bad ``factor``, ``alpha``, ``psf_sigma`` or ``psf_size``.
    """
    f = check_factor(factor)
    b = np.asarray(B)
    if b.ndim != 4:
        raise ValueError(f"B must be a BTF (n_lv, h, w, C), got shape {b.shape}")
    check_stack(b, "B")
    _check_finite(b, "B")
    if isinstance(rank, bool) or not isinstance(rank, (int, np.integer)) or rank < 1:
        raise ValueError(f"rank must be an integer >= 1, got {rank!r}")
    alpha = _check_alpha(alpha)
    gaussian_psf(psf_sigma, psf_size)
    n_lv, h, w, C = b.shape
    M = b.reshape(n_lv, -1)
    k = min(int(rank), n_lv, M.shape[1])
    if not M.any():
        return np.zeros((n_lv, f * h, f * w, C), np.float32)
    try:
        U = truncated_svd(M, n_lv, k).U
    except RankError as err:
        U = truncated_svd(M, n_lv, err.rank).U
    eigentextures = (U.T @ M).reshape(-1, h, w, C)                          # rows of S V^T, (k, h, w, C)
    planes = np.moveaxis(eigentextures, 3, 1).reshape(-1, h, w)             # (k C, h, w)
    up = _upsample64(planes, f, alpha, float(psf_sigma), psf_size)
    up = np.moveaxis(up.reshape(-1, C, f * h, f * w), 1, 3).reshape(U.shape[1], -1)
    return (U @ up).reshape(n_lv, f * h, f * w, C).astype(np.float32)
