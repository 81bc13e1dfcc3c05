"""Tone mapping of linear HDR radiance for display (PNG renderings, reports)."""

from __future__ import annotations

import numpy as np


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """sRGB opto-electronic transfer function of values in [0, 1].

    Parameters
    ----------
    linear : (...) ndarray
        Linear values; clipped to [0, 1].

    Returns
    -------
    encoded : (...) ndarray
        sRGB-encoded values in [0, 1] (IEC 61966-2-1).
    """
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)  # IEC 61966-2-1


def tonemap(radiance: np.ndarray, white: float | None = None, percentile: float = 99.5) -> np.ndarray:
    """Map linear HDR radiance to 8-bit sRGB with the extended Reinhard operator.

    Parameters
    ----------
    radiance : (..., 3) or (...) ndarray
        Linear radiance, any non-negative scale.
    white : float, optional
        Radiance mapped to 1; the ``percentile`` of finite values when omitted.
    percentile : float
        Percentile used to pick ``white``.

    Returns
    -------
    image : (..., 3) or (...) ndarray of uint8

    Notes
    -----
    :math:`L_d = L (1 + L / L_w^2) / (1 + L)` after scaling so that :math:`L_w`
    is the white point (Reinhard et al. 2002, eq. 4).
    """
    x = np.nan_to_num(np.asarray(radiance, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    x = np.maximum(x, 0.0)
    if white is None:
        positive = x[x > 0]
        white = float(np.percentile(positive, percentile)) if positive.size else 1.0
    x = x / max(white, 1e-30) * 2.0
    lw = 2.0
    mapped = x * (1.0 + x / lw**2) / (1.0 + x)  # eq. (4)
    return np.round(srgb_encode(mapped) * 255.0).astype(np.uint8)
