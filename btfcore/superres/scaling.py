"""Area down-sampling and bicubic up-sampling of image stacks by an integer factor.

The two fixed resamplers of super-resolution: the training and evaluation
data are made by :func:`area_downsample` (SR paper §5.1.1 halves its 200 x 200
regions twice but does not name the filter; the exact block mean is the
down-sampling ``D`` of SR paper §3.4, eq. (3), for an ideal box-shaped
pixel), and :func:`bicubic_upsample` is the floor the evaluation compares
every up-sampler with.

Pixel-centre convention (both functions, and :mod:`btfcore.superres.dong`):
a low-resolution pixel covers exactly the ``f x f`` block of high-resolution
pixels it is the mean of, so pixel centres map as
:math:`x_{high} = f\\,x_{low} + (f - 1)/2` (OpenCV's ``resize`` convention).

Images are stacks ``(n, H, W)`` or ``(n, H, W, C)``, channels last
(docs/architecture.md, "Matrix convention"); results are float32.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["area_downsample", "bicubic_upsample", "check_factor", "check_stack"]


def check_factor(factor: int) -> int:
    """Validate an integer scale factor ``>= 1``; ``ValueError`` naming ``factor`` otherwise."""
    if isinstance(factor, (bool, np.bool_)) or not isinstance(factor, (int, np.integer)) or factor < 1:
        raise ValueError(f"factor must be an integer >= 1, got {factor!r}")
    return int(factor)


def check_stack(images: np.ndarray, name: str = "images", *, min_size: int = 1) -> np.ndarray:
    """Validate an image stack ``(n, H, W)`` or ``(n, H, W, C)`` of real numbers, each image at least
    ``min_size`` pixels on a side; returns it as an ndarray (no copy where possible)."""
    a = np.asarray(images)
    if a.ndim not in (3, 4):
        raise ValueError(f"{name} must be a stack (n, H, W) or (n, H, W, C), got shape {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name} must hold real numbers, got dtype {a.dtype}")
    if a.shape[0] == 0:
        raise ValueError(f"{name} is empty: shape {a.shape}")
    if min(a.shape[1:3]) < min_size:
        raise ValueError(f"{name} of shape {a.shape} has images of {a.shape[1]} x {a.shape[2]} pixels, "
                         f"smaller than the factor {min_size}; each side needs at least {min_size} pixels")
    return a


def area_downsample(images: np.ndarray, factor: int = 2) -> np.ndarray:
    """Down-sample each image by the exact mean of every ``factor x factor`` block.

    Parameters
    ----------
    images : (n, H, W) or (n, H, W, C) array_like of real numbers
        The high-resolution stack; ``H, W >= factor``.
    factor : int
        The scale factor ``f >= 1``.

    Returns
    -------
    (n, H // f, W // f) or (n, H // f, W // f, C) ndarray of float32
        Block means, accumulated in float64. A last ``H % f`` rows or
        ``W % f`` columns that do not fill a block are dropped.

    Raises
    ------
    ValueError
        A stack of another rank, an empty stack, images smaller than the
        factor, or a factor that is not an integer ``>= 1``.

    Notes
    -----
    The operator ``D`` of SR paper §3.4, eq. (3), with a box-shaped pixel;
    low-resolution pixel ``i`` covers high-resolution pixels
    ``f i .. f i + f - 1`` (see the module docstring).
    """
    f = check_factor(factor)
    a = check_stack(images, min_size=f)
    n, H, W = a.shape[:3]
    h, w = H // f, W // f
    blocks = a[:, :h * f, :w * f].reshape(n, h, f, w, f, *a.shape[3:])
    return blocks.mean(axis=(2, 4), dtype=np.float64).astype(np.float32)


def bicubic_upsample(images: np.ndarray, factor: int = 2) -> np.ndarray:
    """Up-sample each image by ``factor`` with OpenCV's bicubic interpolation (the evaluation's floor).

    Parameters
    ----------
    images : (n, h, w) or (n, h, w, C) array_like of real numbers
        The low-resolution stack.
    factor : int
        The scale factor ``f >= 1``.

    Returns
    -------
    (n, f h, f w) or (n, f h, f w, C) ndarray of float32
        ``cv2.resize(..., INTER_CUBIC)`` per image and channel (Keys' cubic,
        ``a = -0.75``, which is symmetric but not exact on linear ramps;
        replicated border), in float32.

    Raises
    ------
    ValueError
        As :func:`area_downsample` (the images need only be non-empty).
    """
    f = check_factor(factor)
    a = check_stack(images).astype(np.float32, copy=False)
    n, h, w = a.shape[:3]
    planes = a.reshape(n, h, w, -1)
    out = np.empty((n, f * h, f * w, planes.shape[3]), np.float32)
    for i in range(n):
        for c in range(planes.shape[3]):
            out[i, :, :, c] = cv2.resize(np.ascontiguousarray(planes[i, :, :, c]), (f * w, f * h),
                                         interpolation=cv2.INTER_CUBIC)
    return out.reshape((n, f * h, f * w) + a.shape[3:])
