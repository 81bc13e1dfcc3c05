"""Projection of the sample's ground-truth texture into a camera's region of interest.

A view ``(t, c)`` of the dome sees the planar sample through the homography
``H`` (sample-plane metres -> ROI pixels, :meth:`Device.homography`). The
frame is rendered by inverse mapping with area anti-aliasing: every ROI pixel
is split into ``supersample x supersample`` sub-pixels, each sub-pixel centre
is mapped back to the sample plane by ``H^-1``, the texture is looked up
bilinearly there if the point lies on the sample and the sample holder's
radiance is used otherwise, and the sub-pixels are averaged. At grazing
views one pixel covers several texels along the foreshortened axis and the
average is the box-filtered texture, as a real pixel integrates the radiance
over its footprint.
"""

from __future__ import annotations

import cv2
import numpy as np

from btfcore.dome import Device

__all__ = ["holder_radiance", "render_frame", "sample_corners_px", "sample_mask"]


def _apply_h(H: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    return (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w, (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w


def sample_corners_px(H: np.ndarray, sample_size_m: float) -> np.ndarray:
    """ROI pixel coordinates of the sample's four corners.

    Parameters
    ----------
    H : (3, 3) ndarray
        Sample-plane metres -> ROI pixels.
    sample_size_m : float
        Side of the sample square.

    Returns
    -------
    corners : (4, 2) ndarray of float64
        ``(col, row)`` of ``(-s/2, -s/2), (s/2, -s/2), (s/2, s/2), (-s/2, s/2)``.
    """
    h = sample_size_m / 2.0
    x = np.array([-h, h, h, -h])
    y = np.array([-h, -h, h, h])
    col, row = _apply_h(np.asarray(H, dtype=np.float64), x, y)
    return np.stack([col, row], axis=1)


def homography_sample_mask(H: np.ndarray, roi_shape: tuple[int, int], sample_size_m: float) -> np.ndarray:
    """Frame pixels whose centre maps inside the sample square.

    Parameters
    ----------
    H : (3, 3) ndarray
        Homography sample plane (metres) -> frame pixel ``(col, row, 1)``.
    roi_shape : (int, int)
        Frame ``(rows, cols)``.
    sample_size_m : float
        Side ``s`` of the square sample.

    Returns
    -------
    mask : (rows, cols) ndarray of bool
        True where ``H^-1 (col, row, 1)`` lies strictly inside ``|x|, |y| < s/2``.
    """
    rows, cols = roi_shape
    Hinv = np.linalg.inv(np.asarray(H, dtype=np.float64))
    r, q = np.mgrid[0:rows, 0:cols].astype(np.float64)
    x, y = _apply_h(Hinv, q, r)
    half = sample_size_m / 2.0
    return (np.abs(x) < half) & (np.abs(y) < half)


def sample_mask(device: Device, t: int, c: int) -> np.ndarray:
    """ROI pixels whose centre falls on the sample.

    Parameters
    ----------
    device : Device
        The dome.
    t, c : int
        Turntable position and camera.

    Returns
    -------
    mask : (rows, cols) ndarray of bool
        True where ``H^-1 (col, row, 1)`` lies strictly inside the sample
        square ``|x|, |y| < s/2``.
    """
    return homography_sample_mask(device.homography(t, c), device.roi_shape, device.sample_size_m)


def holder_radiance(light_dirs: np.ndarray, albedo: float = 0.1) -> np.ndarray:
    """Radiance of the matte sample holder around the sample under each light.

    Parameters
    ----------
    light_dirs : (n, 3) ndarray
        Unit light directions, sample frame.
    albedo : float
        Lambertian albedo of the holder (dark grey by default).

    Returns
    -------
    radiance : (n,) ndarray of float64
        In the BTF's units (radiance per unit irradiance at normal incidence).

    Notes
    -----
    .. math:: L = \\frac{\\rho}{\\pi} \\max(\\omega_i \\cdot n, 0), \\quad n = (0, 0, 1)
    """
    d = np.asarray(light_dirs, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"light_dirs must be (n, 3), got {d.shape}")
    return albedo / np.pi * np.maximum(d[:, 2], 0.0)                    # eq. Lambert


def _sample_bbox(H: np.ndarray, roi_shape: tuple[int, int], s: float) -> tuple[int, int, int, int]:
    """Rows/cols ``[r0, r1) x [c0, c1)`` of the ROI that can see the sample (1 px margin)."""
    rows, cols = roi_shape
    corners = sample_corners_px(H, s)
    c0 = int(np.clip(np.floor(corners[:, 0].min() - 1), 0, cols))
    c1 = int(np.clip(np.ceil(corners[:, 0].max() + 2), 0, cols))
    r0 = int(np.clip(np.floor(corners[:, 1].min() - 1), 0, rows))
    r1 = int(np.clip(np.ceil(corners[:, 1].max() + 2), 0, rows))
    return r0, r1, c0, c1


def _to_rgb(rgba: np.ndarray, dst: np.ndarray) -> None:
    """Copy the first three channels of ``rgba`` into the (strided) view ``dst``."""
    res = cv2.cvtColor(rgba, cv2.COLOR_RGBA2RGB, dst=dst)
    if not np.shares_memory(res, dst):  # OpenCV reallocated: fall back to numpy
        dst[...] = rgba[..., :3]


def render_frame(texture_2x: np.ndarray, background: np.ndarray, H: np.ndarray, roi_shape: tuple[int, int],
                 sample_size_m: float, supersample: int = 3, *, out: np.ndarray | None = None) -> np.ndarray:
    """Project textures of the sample into a camera's region of interest.

    Parameters
    ----------
    texture_2x : (n, H2, W2, 3) ndarray of float32
        Radiance of the sample under ``n`` illuminations for this view, on a
        texture grid covering the sample square (the ground truth at twice
        the device's texture size; any size works). Texel ``(i, j)`` is
        centred at ``x = ((j + 0.5) / W2 - 0.5) s``, ``y = (0.5 - (i + 0.5) / H2) s``.
    background : (n, 3) ndarray
        Radiance of the sample holder around the sample under each illumination.
    H : (3, 3) ndarray
        Sample-plane metres ``(x, y, 1)`` -> ROI pixels ``(col, row, 1)``.
    roi_shape : (2,) tuple of int
        ``(rows, cols)``.
    sample_size_m : float
        Side ``s`` of the sample square.
    supersample : int
        Sub-pixels per pixel along each axis (area anti-aliasing).
    out : (n, rows, cols, 3) ndarray of float32, optional
        Buffer to write into (reused across views to avoid first-touch cost).

    Returns
    -------
    frames : (n, rows, cols, 3) ndarray of float32
        Radiance reaching each ROI pixel.

    Notes
    -----
    For pixel :math:`p` with sub-pixel centres :math:`q_k`,
    :math:`k = 1..S^2`, at offsets :math:`((a + 1/2)/S - 1/2, (b + 1/2)/S - 1/2)`:

    .. math::
        (x_k, y_k, 1)^T \\sim H^{-1} (q_k, 1)^T, \\qquad
        F_p = \\frac{1}{S^2} \\sum_k \\begin{cases}
            T(u_k, v_k) & |x_k|, |y_k| \\le s/2 \\\\ L_{bg} & \\text{else} \\end{cases}

    with texel coordinates :math:`u = (x/s + 1/2) W_2 - 1/2`,
    :math:`v = (1/2 - y/s) H_2 - 1/2` and bilinear lookup :math:`T` (edge texels
    replicated out to the sample border). The sub-pixel maps are computed once
    and each of the ``n`` textures is remapped with ``cv2.remap`` (whose
    bilinear weights are quantised to 1/32 texel; sub-pixels off the sample
    read the border value, set to the holder's radiance) and box-averaged
    with ``cv2.resize(..., INTER_AREA)`` (exact for integer factors); only
    the bounding box of the projected sample is supersampled, the rest of
    the ROI is the holder's radiance.
    """
    tex = np.asarray(texture_2x)
    if tex.ndim != 4 or tex.shape[-1] != 3:
        raise ValueError(f"texture_2x must be (n, H2, W2, 3), got shape {tex.shape}")
    n, th, tw, _ = tex.shape
    bg = np.asarray(background, dtype=np.float32)
    if bg.shape != (n, 3):
        raise ValueError(f"background must be ({n}, 3), got {bg.shape}")
    rows, cols = (int(v) for v in roi_shape)
    S = int(supersample)
    if S < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    H = np.asarray(H, dtype=np.float64)
    s = float(sample_size_m)
    if out is None:
        out = np.empty((n, rows, cols, 3), dtype=np.float32)
    elif out.shape != (n, rows, cols, 3) or out.dtype != np.float32:
        raise ValueError(f"out must be float32 {(n, rows, cols, 3)}, got {out.dtype} {out.shape}")
    out[...] = bg[:, None, None, :]
    r0, r1, c0, c1 = _sample_bbox(H, (rows, cols), s)
    if r1 <= r0 or c1 <= c0:
        return out
    nr, nc = r1 - r0, c1 - c0
    off = (np.arange(S) + 0.5) / S - 0.5
    qc = (c0 + np.arange(nc)[:, None] + off[None, :]).reshape(-1)          # sub-pixel centres
    qr = (r0 + np.arange(nr)[:, None] + off[None, :]).reshape(-1)
    Q, R = np.meshgrid(qc, qr)                                             # (nr*S, nc*S)
    x, y = _apply_h(np.linalg.inv(H), Q, R)                                # eq. H^-1 q
    inside = (np.abs(x) <= s / 2) & (np.abs(y) <= s / 2)
    u = (x / s + 0.5) * tw - 0.5                                           # eq. texel column
    v = (0.5 - y / s) * th - 0.5                                           # eq. texel row
    map_u = np.where(inside, np.clip(u, 0, tw - 1), -4.0).astype(np.float32)   # off the sample ->
    map_v = np.where(inside, np.clip(v, 0, th - 1), -4.0).astype(np.float32)   # the border value
    # Four-channel images take OpenCV's vectorised remap path (2x faster than three).
    tex4 = np.empty((th, tw, 4), dtype=np.float32)
    sub = np.empty((nr * S, nc * S, 4), dtype=np.float32)
    mean = np.empty((nr, nc, 4), dtype=np.float32)
    for i in range(n):
        cv2.cvtColor(tex[i] if tex.dtype == np.float32 else tex[i].astype(np.float32), cv2.COLOR_RGB2RGBA,
                     dst=tex4)
        bgi = (float(bg[i, 0]), float(bg[i, 1]), float(bg[i, 2]), 0.0)
        # sub-pixels off the sample read the border value: the holder's radiance (eq. F_p, else-branch)
        cv2.remap(tex4, map_u, map_v, cv2.INTER_LINEAR, dst=sub, borderMode=cv2.BORDER_CONSTANT, borderValue=bgi)
        if S > 1:
            cv2.resize(sub, (nc, nr), dst=mean, interpolation=cv2.INTER_AREA)      # eq. 1/S^2 sum
            _to_rgb(mean, out[i, r0:r1, c0:c1])
        else:
            _to_rgb(sub, out[i, r0:r1, c0:c1])
    return out
