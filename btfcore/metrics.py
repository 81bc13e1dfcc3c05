"""Error measures of reconstructed BTFs and images.

* :func:`relative_error`: :math:`\\|\\hat B - B\\|_F / \\|B\\|_F`, optionally on
  :math:`\\log Y` (paper 1, Table 1; paper 4, Fig. 5);
* :func:`mrmse`, :func:`mpsnr`, :func:`mre`: the per-texture means of the SR
  paper, eqs. (8)-(10), after Dong et al.;
* :func:`psnr`: PSNR of two images (renderings, paper 4 §5), peak given or
  the maximum of the reference.

A BTF ``B`` has rows = light/view pairs (textures) and any trailing shape;
``(n_lv, h, w)`` or ``(n_lv, h, w, C)`` says the texture size, a 2-D
``(n_lv, n_tx)`` is taken as ``n_tx`` texels unless ``n_texels`` is given.

References
----------
.. [1] The thesis, App. paper 1 (den Brok et al.), §4.1.1, the relative
   projection error; App. SR paper ("Per-image super-resolution for material
   BTFs", paper 5), §5.3, eqs. (8)-(10).
.. [2] Y. Dong, J. Wang, X. Tong, J. Snyder, Y. Lan, M. Ben-Ezra and B. Guo,
   "Manifold bootstrapping for SVBRDF capture", ACM TOG 29(4), 2010 (the
   mean RMSE / PSNR convention the SR paper follows).
"""

from __future__ import annotations

import numpy as np

from btfcore.model.colour import LOG_YUV_EPS, _as_float, log_luminance

__all__ = ["mpsnr", "mre", "mrmse", "psnr", "relative_error", "texture_errors"]


def _pair(B, B_hat) -> tuple[np.ndarray, np.ndarray]:
    b = _as_float(B, "B").astype(np.float64, copy=False)
    bh = _as_float(B_hat, "B_hat").astype(np.float64, copy=False)
    if b.shape != bh.shape:
        raise ValueError(f"B has shape {b.shape} but B_hat has shape {bh.shape}; they must match")
    if b.size == 0:
        raise ValueError("B is empty")
    return b, bh


def relative_error(B: np.ndarray, B_hat: np.ndarray, *, space: str = "linear",
                   eps: float = LOG_YUV_EPS) -> float:
    """Relative L2 (Frobenius) error of a reconstruction.

    Parameters
    ----------
    B, B_hat : (n_lv, ...) array_like
        Reference and reconstruction, same shape. For ``space='log_y'``
        linear RGB with the channels on the last axis, ``(..., 3)`` (a BTF
        matrix as ``B.reshape(n_lv, -1, 3)``).
    space : {'linear', 'log_y'}
        ``'log_y'``: compare :math:`\\log \\max(Y, \\varepsilon)` of both
        (:func:`btfcore.model.colour.log_luminance`), as paper 1's Table 1 does.
    eps : float
        Floor of Y for ``'log_y'``.

    Returns
    -------
    error : float
        :math:`\\|\\hat B - B\\|_F / \\|B\\|_F`.

    Raises
    ------
    ValueError
        On mismatched shapes, NaN/Inf (names the index), an unknown space,
        or :math:`\\|B\\|_F = 0`.

    Notes
    -----
    Paper 1, §4.1.1:
    :math:`\\varepsilon = \\|U(U'B) - B\\|_F / \\|B\\|_F`.
    """
    if space not in ("linear", "log_y"):
        raise ValueError(f"space must be 'linear' or 'log_y', got {space!r}")
    b, bh = _pair(B, B_hat)
    if space == "log_y":
        b, bh = log_luminance(b, eps), log_luminance(bh, eps)          # log Y (paper 1, §3.1)
    den = float(np.linalg.norm(b.ravel()))
    if den == 0:
        raise ValueError("||B||_F = 0: the relative error is undefined")
    return float(np.linalg.norm((bh - b).ravel()) / den)             # eq. ||B_hat - B||_F / ||B||_F


def _texels(b: np.ndarray, n_texels: int | None) -> int:
    if n_texels is not None:
        n = int(n_texels)
        if n < 1:
            raise ValueError(f"n_texels must be >= 1, got {n_texels!r}")
        return n
    if b.ndim < 2:
        raise ValueError(f"B must be (n_lv, n_tx), (n_lv, h, w) or (n_lv, h, w, C), got shape {b.shape}")
    return int(b.shape[1] * b.shape[2]) if b.ndim >= 3 else int(b.shape[1])


def texture_errors(B: np.ndarray, B_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-texture L2 norms of the error and of the reference.

    Parameters
    ----------
    B, B_hat : (n_lv, ...) array_like

    Returns
    -------
    err, ref : (n_lv,) ndarray of float64
        :math:`\\|B_{i,:} - \\tilde B_{i,:}\\|_2` and :math:`\\|B_{i,:}\\|_2`,
        over all texels and channels of row ``i``.
    """
    b, bh = _pair(B, B_hat)
    b2 = b.reshape(b.shape[0], -1)
    d2 = (bh - b).reshape(b.shape[0], -1)
    return np.linalg.norm(d2, axis=1), np.linalg.norm(b2, axis=1)


def mrmse(B: np.ndarray, B_hat: np.ndarray, *, n_texels: int | None = None,
          per_texture: bool = False) -> float | np.ndarray:
    """Mean RMSE over textures (SR paper, eq. (8)).

    Parameters
    ----------
    B, B_hat : (n_lv, h, w[, C]) or (n_lv, n_tx) array_like
        Reference and reconstruction.
    n_texels : int, optional
        :math:`w_{BTF} h_{BTF}`; default ``h * w`` (``n_tx`` for 2-D input).
    per_texture : bool
        Return the ``(n_lv,)`` terms instead of their mean.

    Returns
    -------
    mrmse : float or (n_lv,) ndarray

    Notes
    -----
    .. math:: \\mathrm{mRMSE} = \\frac{1}{n_l n_v} \\sum_i
              \\frac{1}{\\sqrt{w_{BTF} h_{BTF}}} \\|B_{i,:} - \\tilde B_{i,:}\\|_2

    taken literally: the norm runs over the whole row (all channels) and is
    divided by the square root of the number of *texels*, so for ``C``
    channels each term is :math:`\\sqrt C` times the RMSE per value. (The
    thesis' sum runs from 0 to :math:`n_l n_v` inclusive, one term too many;
    the mean over the :math:`n_l n_v` rows is meant.)
    """
    b, bh = _pair(B, B_hat)
    err, _ = texture_errors(b, bh)
    terms = err / np.sqrt(_texels(b, n_texels))                       # eq. (8)
    return terms if per_texture else float(terms.mean())


def mpsnr(B: np.ndarray, B_hat: np.ndarray, *, n_texels: int | None = None,
          per_texture: bool = False) -> float | np.ndarray:
    """Mean PSNR over textures, each with its own peak (SR paper, eq. (9)).

    Parameters
    ----------
    B, B_hat : (n_lv, h, w[, C]) or (n_lv, n_tx) array_like
    n_texels : int, optional
        As for :func:`mrmse`.
    per_texture : bool
        Return the ``(n_lv,)`` terms instead of their mean.

    Returns
    -------
    mpsnr : float or (n_lv,) ndarray
        dB; ``inf`` for a texture reconstructed exactly (and then the mean).

    Raises
    ------
    ValueError
        If a texture's maximum is <= 0 (names the row): its PSNR is undefined.

    Notes
    -----
    .. math:: \\mathrm{mPSNR} = \\frac{1}{n_l n_v} \\sum_i 20 \\log_{10}
              \\frac{\\max(B_{i,:})}{\\|B_{i,:} - \\tilde B_{i,:}\\|_2 / \\sqrt{w_{BTF} h_{BTF}}}

    The peak is per texture (the maximum of the reference row), the
    denominator the term of eq. (8).
    """
    b, bh = _pair(B, B_hat)
    peak = b.reshape(b.shape[0], -1).max(axis=1)
    bad = np.flatnonzero(~(peak > 0))
    if bad.size:
        raise ValueError(f"texture {bad[0]} of B has maximum {float(peak[bad[0]])!r} <= 0: its PSNR is undefined; "
                         f"pass linear radiance (not log data)")
    rmse = mrmse(b, bh, n_texels=n_texels, per_texture=True)
    with np.errstate(divide="ignore"):
        terms = 20.0 * np.log10(peak / rmse)                          # eq. (9)
    return terms if per_texture else float(terms.mean())


def mre(B: np.ndarray, B_hat: np.ndarray, *, per_texture: bool = False) -> float | np.ndarray:
    """Mean relative error over textures, in per cent (SR paper, eq. (10)).

    Parameters
    ----------
    B, B_hat : (n_lv, ...) array_like
    per_texture : bool
        Return the ``(n_lv,)`` terms instead of their mean.

    Returns
    -------
    mre : float or (n_lv,) ndarray
        Per cent.

    Raises
    ------
    ValueError
        If a texture of ``B`` is all zero (names the row).

    Notes
    -----
    .. math:: \\mathrm{mRE} = \\frac{1}{n_l n_v} \\sum_i
              \\frac{\\|B_{i,:} - \\tilde B_{i,:}\\|_2}{\\|B_{i,:}\\|_2} \\cdot 100\\%

    Each texture is normalised by its own norm, so dark textures weigh as
    much as bright ones.
    """
    err, ref = texture_errors(B, B_hat)
    bad = np.flatnonzero(ref == 0)
    if bad.size:
        raise ValueError(f"texture {bad[0]} of B is all zero: its relative error is undefined")
    terms = err / ref * 100.0                                         # eq. (10)
    return terms if per_texture else float(terms.mean())


def psnr(reference: np.ndarray, test: np.ndarray, peak: float | None = None) -> float:
    """Peak signal-to-noise ratio of two images (e.g. renderings).

    Parameters
    ----------
    reference, test : (...) array_like
        Same shape (e.g. ``(h, w, 3)``).
    peak : float, optional
        Peak value (255 for 8-bit images); default the maximum of
        ``reference``.

    Returns
    -------
    psnr : float
        :math:`10 \\log_{10}(\\mathrm{peak}^2 / \\mathrm{MSE})` dB, MSE over all
        values; ``inf`` for identical images (OpenCV's ``cv2.PSNR`` returns
        361 dB there instead).

    Raises
    ------
    ValueError
        On mismatched shapes, NaN/Inf, or a peak <= 0.
    """
    r, t = _pair(reference, test)
    pk = float(r.max()) if peak is None else float(peak)
    if not (np.isfinite(pk) and pk > 0):
        raise ValueError(f"peak must be a finite number > 0, got {pk!r} (pass peak= for non-positive images)")
    mse = float(np.mean((t - r) ** 2))
    if mse == 0:
        return float("inf")
    return float(10.0 * np.log10(pk * pk / mse))                      # PSNR = 10 log10(peak² / MSE)
