"""One view of a capture to rectified linear textures: stages 2-6 composed (docs/architecture.md, "Stages").

The chain for one (turntable, camera) view, thesis §1.1.3:

1. HDR merge of every illumination's exposure bracket in the Bayer domain
   (:func:`btfcore.capture.hdr.merge_linear`, dark frames interpolated to the bracket's
   exposure times);
2. demosaicing of the float HDR mosaic (:func:`btfcore.capture.demosaic.demosaic`);
3. rectification of the sample region to the ``h x w`` texture by one sparse
   operator per view (:func:`btfcore.capture.rectify.rectification_matrix`);
4. demultiplexing of the illumination patterns to single LEDs
   (:func:`btfcore.capture.demultiplex.demultiplex`; the identity for single-LED
   captures);
5. radiometric correction, when a calibration is given: division by each
   LED's RGB gain measured on a white standard
   (:func:`btfcore.capture.radiometric.apply_led_calibration`) and the camera's
   colour matrix (:func:`btfcore.capture.radiometric.apply_colour_matrix`).

Steps 4-5 (:func:`to_single_leds`) can also be applied to the merged and demosaicked window itself:
``process_view(..., roi_out=...)`` keeps the view's single-LED HDR radiance region before
rectification, the input of super-resolution (SR paper §4; ``btf ingest --keep-roi``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import sparse

from btfcore.capture.demosaic import demosaic
from btfcore.capture.demultiplex import demultiplex_operator
from btfcore.capture.hdr import _check_finite, dark_per_exposure, linear_merger, merge_response
from btfcore.capture.radiometric import apply_colour_matrix, apply_led_calibration
from btfcore.capture.rectify import apply_rectification, rectification_matrix, support_window

#: Radius of the demosaicing filters (Malvar 2004: 5 x 5): pixels read around the rectification's window.
DEMOSAIC_RADIUS = 2


@dataclass(frozen=True)
class IngestSettings:
    """Method choices of the per-view chain (hashable: it keys resumption)."""

    demosaic: str = "malvar2004"
    rectify: str = "supersample"
    saturation_margin: float = 0.98


def view_window(homography: np.ndarray, frame_shape: tuple[int, int], texture_shape: tuple[int, int],
                sample_size_m: float, settings: IngestSettings = IngestSettings(), *, whole_frame: bool = False
                ) -> tuple[slice, slice, sparse.csr_matrix]:
    """The part of a view's raw frames that its texture depends on, and its rectification operator.

    Parameters
    ----------
    homography : (3, 3) ndarray
        Sample-plane metres -> raw pixel ``(col, row, 1)``.
    frame_shape : (2,) tuple of int
        ``(rows, cols)`` of the raw frames.
    whole_frame : bool
        The window is the whole frame (the region of interest a camera delivers, kept by
        ``btf ingest --keep-roi``) and the operator the full one.

    Returns
    -------
    row_window, col_window : slice
        The pixels the rectification reads, plus the demosaicing filter's
        radius, starting on the Bayer period (:func:`btfcore.capture.rectify.support_window`);
        the whole frame with ``whole_frame``.
    A : (h * w, n_rows * n_cols) scipy.sparse.csr_matrix
        The rectification operator on that window.
    """
    A_full = rectification_matrix(homography, frame_shape, texture_shape, sample_size_m, method=settings.rectify)
    if whole_frame:
        return slice(0, int(frame_shape[0])), slice(0, int(frame_shape[1])), sparse.csr_matrix(A_full)
    return support_window(A_full, frame_shape, margin=DEMOSAIC_RADIUS, align=2)


def to_single_leds(images: np.ndarray, P: np.ndarray, *, led_gain: np.ndarray | None = None,
                   colour_matrix: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """Steps 4-5 of the chain on any per-pattern images of a view: demultiplexing, LED gains, colour matrix.

    Parameters
    ----------
    images : (n_illum, rows, cols, 3) ndarray of float32
        Linear radiance per illumination pattern (rectified textures, or the regions of interest).
    P : (n_leds, n_illum) ndarray of float32
        :func:`btfcore.capture.demultiplex.demultiplex_operator` of the patterns.
    led_gain, colour_matrix : ndarray, optional
        As in :func:`process_view`.
    out : (n_leds, rows, cols, 3) ndarray of float32, optional
        Where the demultiplexed images go (``images`` itself for a single-LED capture in LED order).

    Returns
    -------
    (n_leds, rows, cols, 3) ndarray of float32
        ``out`` when given; else ``images`` itself (single LEDs without a colour matrix) or a new array.
    """
    n_illum, n_leds = images.shape[0], P.shape[0]
    if _in_led_order(P):
        leds = images                                               # single-LED capture in LED order
    else:
        flat = None if out is None else out.reshape(n_leds, -1)     # a view: the product lands in out
        leds = np.matmul(P, images.reshape(n_illum, -1), out=flat).reshape(n_leds, *images.shape[1:])
    if led_gain is not None:
        apply_led_calibration(leds, led_gain, out=leds)
    if colour_matrix is not None:
        leds = apply_colour_matrix(leds, colour_matrix)
    if out is not None and not np.shares_memory(leds, out):
        out[...] = leds
        leds = out
    return leds


def process_view(frames: np.ndarray, exposure_time: np.ndarray, patterns: np.ndarray, *,
                 bayer_pattern: str | None, black_level: float, white_level: float, homography: np.ndarray,
                 texture_shape: tuple[int, int], sample_size_m: float, response: np.ndarray | None = None,
                 dark_frames: np.ndarray | None = None, dark_exposure_time: np.ndarray | None = None,
                 gain_e_per_dn: float | None = None, read_noise_e: float | None = None,
                 led_gain: np.ndarray | None = None, colour_matrix: np.ndarray | None = None,
                 window: tuple[slice, slice, sparse.csr_matrix] | None = None,
                 out: np.ndarray | None = None, roi_out: np.ndarray | None = None, response_method: str = "debevec",
                 settings: IngestSettings = IngestSettings()) -> tuple[np.ndarray, np.ndarray]:
    """Raw brackets of one view to demultiplexed, rectified linear RGB textures.

    Parameters
    ----------
    frames : (n_illum, n_exp, rows, cols) ndarray of uint16
        The view's raw Bayer brackets, one per illumination pattern: whole
        frames, or only the window when ``window`` is given. With
        ``bayer_pattern=None``, ``(n_illum, n_exp, rows, cols, 3)`` frames of a
        full-RGB sensor (every pixel measures R, G and B; uint16 or float):
        merged per channel and not demosaicked (the simulator's ideal sensor,
        :class:`btfcore.simulate.sensor.SensorModel`).
    exposure_time : (n_illum, n_exp) ndarray
        Seconds, increasing along the exposure axis.
    patterns : (n_illum, n_leds) ndarray
        Binary illumination patterns.
    homography : (3, 3) ndarray
        Sample-plane metres -> raw pixel ``(col, row, 1)``.
    dark_frames : (n_dark, rows, cols) ndarray, optional
        The camera's dark frames (DN, black level included) at ``dark_exposure_time``.
    led_gain : (n_leds, 3) ndarray, optional
        Each LED's RGB gain from a white standard
        (:func:`btfcore.capture.radiometric.led_calibration`, DN/s per unit
        irradiance-weighted reflectance); the textures are divided by it.
    colour_matrix : (3, 3) or (3, 4) ndarray, optional
        Camera RGB -> target RGB, applied after the LED gains.
    window : (slice, slice, sparse matrix), optional
        :func:`view_window` of this view, computed by the caller so that it
        reads only the window of the frames from storage; ``None``: computed
        here from whole frames.
    out : (n_illum, h, w, 3) ndarray of float32, optional
        Buffer for the rectified textures, reused across views by the caller
        (first-touch of fresh memory is slow, docs/architecture.md,
        "Pitfalls"); a single-LED capture's result is returned in it.
    response : (n_codes, 3) ndarray, optional
        A non-linear camera's response (``bayer_pattern=None``, codes in ``frames``): :func:`merge_ldr`.
    roi_out : (n_leds, win_rows, win_cols, 3) ndarray of float32, optional
        Filled with the view's HDR radiance region before rectification (SR paper §4): the merged
        and demosaicked window, demultiplexed to single LEDs and radiometrically corrected like the
        textures, so that the window's operator applied to it gives the textures (to float32
        rounding, when the colour matrix has no offset column).

    Returns
    -------
    textures : (n_leds, h, w, 3) ndarray of float32
        Linear radiance per LED: DN/s without ``led_gain``; with it, radiance
        relative to a unit-irradiance white light (a white Lambertian sample
        of albedo ``a`` reads ``a cos(theta_i) / pi``), the ground truth's unit.
    valid_fraction : (n_illum,) ndarray of float64
        Fraction of the raw pixels read for the texture (the window of
        :func:`btfcore.capture.rectify.support_window`) with at least one usable
        exposure, per pattern.
    """
    n_illum, n_exp = frames.shape[:2]
    # only the window the operator reads (plus the demosaicing filter's radius) is merged and demosaicked
    if window is None:
        row_win, col_win, A = view_window(homography, frames.shape[2:], texture_shape, sample_size_m, settings)
        frames = frames[:, :, row_win, col_win]
    else:
        row_win, col_win, A = window
        expected = (row_win.stop - row_win.start, col_win.stop - col_win.start)
        if frames.shape[2:4] != expected:
            raise ValueError(f"frames are {frames.shape[2:]} pixels but the view's window {row_win}, {col_win} "
                             f"is {expected}: pass frames[..., row_window, col_window]")
    win_shape = frames.shape[2:4]
    full_rgb = bayer_pattern is None                              # no mosaic: frames hold R, G and B
    rectified = np.empty((n_illum, *texture_shape, 3), dtype=np.float32) if out is None else out
    if rectified.shape != (n_illum, *texture_shape, 3) or rectified.dtype != np.float32:
        raise ValueError(f"out must be a float32 array of shape {(n_illum, *texture_shape, 3)}, got "
                         f"{rectified.dtype} {rectified.shape}")
    P = demultiplex_operator(patterns).astype(np.float32)           # (n_leds, n_illum)
    roi = _roi_buffer(roi_out, P, win_shape)                       # (n_illum, *win_shape, 3) or None
    valid_fraction = np.empty(n_illum)
    dark_line = _dark_line(dark_frames, dark_exposure_time, (row_win, col_win), black_level)
    if response is None:               # the sensor's settings and the view's frames and dark model checked once
        merge = linear_merger(frames.shape[2:], frames.dtype, black_level=black_level, white_level=white_level,
                              gain_e_per_dn=gain_e_per_dn, read_noise_e=read_noise_e,
                              saturation_margin=settings.saturation_margin)
        _check_finite_view(frames, dark_line)
    A = A.astype(np.float32, copy=False)             # the float32 products' operator, converted once per view
    block = min(32, n_illum)  # illuminations demosaicked as one batch and rectified by one sparse product
    hdr = np.empty((block, *frames.shape[2:]), dtype=np.float32)                             # reused buffers
    rgb = hdr if full_rgb else np.empty((block, *win_shape, 3), dtype=np.float32)
    dark = None if dark_line is None else np.empty((n_exp, *win_shape), dtype=np.float32)
    for first in range(0, n_illum, block):
        n = min(block, n_illum - first)
        for k in range(n):
            i = first + k
            if dark is not None:
                for k_exp, t_k in enumerate(exposure_time[i]):
                    np.multiply(dark_line[1], np.float32(t_k), out=dark[k_exp])
                    dark[k_exp] += dark_line[0]                                     # dark = offset + rate t
            hdr[k], valid = merge_ldr(frames[i], exposure_time[i], response, response_method) \
                if response is not None else merge(                         # a non-linear (LDR) camera, or raw
                    frames[i], exposure_time[i], dark[..., None] if full_rgb and dark is not None else dark,
                    check_finite=False)
            valid_fraction[i] = np.count_nonzero(valid) / valid.size
        if not full_rgb:
            demosaic(hdr[:n], bayer_pattern, method=settings.demosaic, out=rgb[:n], check_finite=False)
        if roi is not None:
            roi[first:first + n] = rgb[:n]
        # (n, pixels) -> (pixels, n) of RGB triplets and back: OpenCV's blocked transposes (3x numpy's
        # strided copies; demosaicking into a strided view was slower still), so that one sparse
        # product rectifies the n images
        stack = cv2.transpose(rgb[:n].reshape(n, -1, 3)).reshape(*win_shape, 3 * n)
        out = apply_rectification(A, stack, texture_shape, check_finite=False)            # (h, w, 3n)
        rectified[first:first + n].reshape(n, -1, 3)[...] = cv2.transpose(out.reshape(-1, n, 3))
    textures = to_single_leds(rectified, P, led_gain=led_gain, colour_matrix=colour_matrix)
    if roi is not None:
        to_single_leds(roi, P, led_gain=led_gain, colour_matrix=colour_matrix, out=roi_out)
    return textures, valid_fraction


def _dark_line(dark_frames: np.ndarray | None, dark_exposure_time: np.ndarray | None, window: tuple[slice, slice],
               black_level: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The view's dark model over its window, linear in time: ``(offset DN, rate DN/s)``, fitted once per view
    and evaluated per bracket; None without dark frames."""
    if dark_frames is None or dark_exposure_time is None:
        return None
    d1, d2 = dark_per_exposure(dark_frames[:, window[0], window[1]], dark_exposure_time, [1.0, 2.0],
                               black_level=black_level)
    return (2.0 * d1 - d2).astype(np.float32), (d2 - d1).astype(np.float32)


def _check_finite_view(frames: np.ndarray, dark_line: tuple[np.ndarray, np.ndarray] | None) -> None:
    """NaN/Inf in a view's frames or its dark model, named by index (:func:`~btfcore.capture.hdr.merge_linear`'s
    own check), once before its brackets are merged unchecked."""
    _check_finite(frames, "frames")
    if dark_line is not None:
        _check_finite(dark_line[0], "dark offset")
        _check_finite(dark_line[1], "dark rate")


def merge_ldr(codes: np.ndarray, exposure_time: np.ndarray, response: np.ndarray, method: str = "debevec"
              ) -> tuple[np.ndarray, np.ndarray]:
    """One bracket of a non-linear camera's 8- or 16-bit codes (stored as uint16) merged through its
    ``(n_codes, 3)`` response (:func:`btfcore.capture.hdr.merge_response`, ``method`` ``'debevec'`` or
    ``'robertson'``): ``(radiance, valid)`` in the response's relative units per second."""
    codes = codes.astype(np.uint8) if response.shape[0] == 256 else codes
    return merge_response(codes, exposure_time, response, method=method, return_valid=True)


def _roi_buffer(roi_out: np.ndarray | None, P: np.ndarray, win_shape: tuple[int, int]) -> np.ndarray | None:
    """Where :func:`process_view` collects the demosaicked window of every pattern: ``roi_out`` itself
    for a single-LED capture in LED order, else a new ``(n_illum, *win_shape, 3)`` array (demultiplexed
    into ``roi_out`` at the end)."""
    if roi_out is None:
        return None
    n_leds, n_illum = P.shape
    if roi_out.shape != (n_leds, *win_shape, 3) or roi_out.dtype != np.float32:
        raise ValueError(f"roi_out must be a float32 array of shape {(n_leds, *win_shape, 3)} (the LEDs x the "
                         f"view's window), got {roi_out.dtype} {roi_out.shape}")
    return roi_out if _in_led_order(P) else np.empty((n_illum, *win_shape, 3), dtype=np.float32)


def _in_led_order(P: np.ndarray) -> bool:
    """Whether the demultiplexing operator ``P`` is the identity (single LEDs, in LED order)."""
    return P.shape[0] == P.shape[1] and np.array_equal(P, np.eye(P.shape[0], dtype=P.dtype))


def lv_directions(led_position: np.ndarray, camera_R: np.ndarray, camera_t: np.ndarray,
                  turntable_angle_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Light and view directions of every light/view pair in the sample frame.

    Parameters
    ----------
    led_position : (n_leds, 3) ndarray
        World positions (metres); lights are directional at the sample centre.
    camera_R, camera_t : (n_cam, 3, 3), (n_cam, 3) ndarray
        World-to-camera poses; the camera centre is :math:`-R^T t`.
    turntable_angle_deg : (n_turn,) ndarray
        The sample frame is the world frame rotated by this angle about z.

    Returns
    -------
    light_dir, view_dir : (n_lv, 3) ndarray
        Unit vectors, flattened row-major over (turntable, camera, light).
    lv_index : (n_lv, 3) ndarray of int32
        ``(turntable, camera, light)`` of each row.
    """
    leds = led_position / np.linalg.norm(led_position, axis=1, keepdims=True)
    centres = -np.einsum("cji,cj->ci", camera_R, camera_t)             # -R^T t
    cams = centres / np.linalg.norm(centres, axis=1, keepdims=True)
    a = np.radians(np.asarray(turntable_angle_deg, dtype=np.float64))
    c, s = np.cos(-a), np.sin(-a)
    Rz = np.zeros((a.size, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0   # d_s = Rz(-a) d_w
    n_turn, n_cam, n_leds = a.size, cams.shape[0], leds.shape[0]
    light = np.einsum("tij,lj->tli", Rz, leds)                         # (n_turn, n_leds, 3)
    view = np.einsum("tij,cj->tci", Rz, cams)                          # (n_turn, n_cam, 3)
    light_dir = np.broadcast_to(light[:, None], (n_turn, n_cam, n_leds, 3)).reshape(-1, 3)
    view_dir = np.broadcast_to(view[:, :, None], (n_turn, n_cam, n_leds, 3)).reshape(-1, 3)
    lv_index = np.stack(np.meshgrid(np.arange(n_turn), np.arange(n_cam), np.arange(n_leds), indexing="ij"),
                        axis=-1).reshape(-1, 3).astype(np.int32)
    return np.ascontiguousarray(light_dir), np.ascontiguousarray(view_dir), lv_index
