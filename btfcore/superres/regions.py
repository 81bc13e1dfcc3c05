"""Regions of interest at a finer pixel grid: up-sampling them and rectifying them at a larger texture.

The SR paper (§3.3-§4) up-samples each image's HDR radiance region of
interest *before* rectification and angular resampling; rectifying the
up-sampled region with the view's homography at twice the texture size gives
the super-resolved BTF row. This module holds the two steps shared by
``btf superres apply`` and the evaluation: :func:`upsample_regions` (the
``method=`` dispatcher: the ESPCN of :mod:`btfcore.superres.espcn`, or bicubic
interpolation as the floor) and :func:`rectify_regions` (the view's operator
for a camera of ``factor`` times the pixels, :func:`scale_homography`).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from btfcore.capture.rectify import apply_rectification, rectification_matrix
from btfcore.dome import pixel_scale_matrix
from btfcore.superres.scaling import bicubic_upsample

__all__ = ["UPSAMPLE_METHODS", "rectify_regions", "scale_homography", "upsample_regions"]

#: Methods of :func:`upsample_regions`.
UPSAMPLE_METHODS: tuple[str, ...] = ("espcn", "bicubic")


def scale_homography(homography: np.ndarray, factor: float) -> np.ndarray:
    """The homography of the same view seen by a camera with ``factor`` times the pixels per axis.

    Parameters
    ----------
    homography : (3, 3) ndarray
        Sample-plane metres ``(x, y, 1)`` -> region pixel ``(col, row, 1)``.
    factor : float
        2 for the up-sampled region, 0.5 for the area-down-sampled one.

    Returns
    -------
    (3, 3) ndarray
        ``S H`` with :func:`btfcore.dome.pixel_scale_matrix`: a pixel of the
        original grid covers exactly the ``factor x factor`` block of the new one.
    """
    return pixel_scale_matrix(factor) @ np.asarray(homography, dtype=np.float64)


def rectify_regions(regions: np.ndarray, homography: np.ndarray, texture_shape: tuple[int, int],
                    sample_size_m: float, *, method: str = "supersample") -> np.ndarray:
    """Rectify a view's regions of interest to textures (thesis §1.1.3; SR paper §3.3).

    Parameters
    ----------
    regions : (n, rows, cols, 3) ndarray of float32
        The view's linear radiance regions, one per light.
    homography : (3, 3) ndarray
        Sample-plane metres -> pixel of ``regions`` (:func:`scale_homography` for an up-sampled region).
    texture_shape : (2,) tuple of int
        ``(h, w)`` of the textures.

    Returns
    -------
    textures : (n, h, w, 3) ndarray of float32
        ``A`` applied to every region, ``A`` the view's one
        :func:`btfcore.capture.rectify.rectification_matrix`.
    """
    regions = np.asarray(regions, dtype=np.float32)
    if regions.ndim != 4 or regions.shape[-1] != 3:
        raise ValueError(f"regions must be (n, rows, cols, 3), got shape {regions.shape}")
    n, rows, cols, _ = regions.shape
    h, w = (int(v) for v in texture_shape)
    A = rectification_matrix(homography, (rows, cols), (h, w), sample_size_m, method=method)
    # (n, pixels, 3) -> (pixels, 3 n): one sparse product rectifies the n regions (as the view chain does)
    stack = cv2.transpose(np.ascontiguousarray(regions).reshape(n, -1, 3)).reshape(rows, cols, 3 * n)
    out = apply_rectification(A, stack, (h, w))
    return np.ascontiguousarray(cv2.transpose(out.reshape(-1, n, 3)).reshape(n, h, w, 3))


def upsample_regions(regions: np.ndarray, *, method: str = "espcn", model: Any = None, factor: int = 2,
                     device: str = "cpu") -> np.ndarray:
    """Up-sample regions of interest by ``factor``: the ``method=`` dispatcher.

    Parameters
    ----------
    regions : (n, rows, cols, 3) ndarray
        Linear HDR radiance.
    method : {'espcn', 'bicubic'}
        ``'espcn'``: the network of SR paper §4 (``model``, an
        :class:`btfcore.superres.espcn.Espcn`), one colour channel at a time;
        ``'bicubic'``: ``cv2.resize`` with ``INTER_CUBIC``, the floor.
    factor : int
        2 (the network's scale).

    Returns
    -------
    (n, factor rows, factor cols, 3) ndarray of float32
    """
    regions = np.asarray(regions, dtype=np.float32)
    if regions.ndim != 4 or regions.shape[-1] != 3:
        raise ValueError(f"regions must be (n, rows, cols, 3), got shape {regions.shape}")
    if method == "bicubic":
        return bicubic_upsample(regions, factor)
    if method != "espcn":
        raise ValueError(f"method {method!r} is unknown; choose one of {', '.join(UPSAMPLE_METHODS)}")
    from btfcore.superres.espcn import upscale_rgb

    if model is None:
        raise ValueError("method 'espcn' needs a model (train one with `btf superres train`)")
    if int(model.config.scale) != int(factor):
        raise ValueError(f"the model up-samples by {model.config.scale}, not {factor}")
    return upscale_rgb(model, regions, device=device)
