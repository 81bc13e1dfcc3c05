"""Import brackets of 8- or 16-bit TIFF, PNG and JPEG images of a non-linear camera into a capture store.

The sibling of :mod:`tasks.ingest_raw` for cameras that deliver processed images instead of raw files:
the same manifest (``file,turntable,camera,illumination,exposure[,exposure_time]``; shutter times as
photographers write them, brackets in any order, every problem listed at once) is checked by the same
:func:`tasks.ingest_raw.plan_raw_import`, with OpenCV reading the files (``cv2.IMREAD_UNCHANGED``, colour
order BGR -> RGB; greyscale repeated to three channels, an alpha channel dropped) instead of LibRaw.
Exposure times missing from the manifest are read from the file's EXIF ``ExposureTime`` where Pillow finds
one. Dark rows are refused (a processed image has no black level left to measure).

The capture store (docs/capture-store.md, "Colour images and the camera response") holds the codes as
they are, ``raw`` with a trailing channel axis (``bayer_pattern`` ``"RGB"``), and each camera's
inverse response ``response`` ``(n_cam, 2**bit_depth, 3)``, either calibrated once per camera from its
brackets (:func:`calibrate_camera_responses`: Debevec & Malik or Robertson et al.,
:func:`btfcore.capture.hdr.calibrate_response`) or read from a file (:func:`load_response`).
``btf ingest`` merges the brackets through it (:func:`btfcore.capture.hdr.merge_response`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from btfcore.capture.hdr import RESPONSE_METHODS, calibrate_response
from btfcore.dome import Device
from tasks.ingest_raw import (
    RawFrameInfo,
    RawImportError,
    RawImportPlan,
    identify_image_file,
    import_raw,
    plan_raw_import,
    raw_import_metadata,
)
from tasks.stores import CaptureMetadata, CaptureStore

__all__ = [
    "CALIBRATION_BRACKETS",
    "calibrate_camera_responses",
    "image_import_metadata",
    "import_images",
    "load_response",
    "plan_image_import",
    "probe_image_file",
    "read_image_frame",
]

#: Most brackets per camera the response is calibrated from, spread evenly over its brackets.
CALIBRATION_BRACKETS = 8
#: EXIF tag of the exposure time (seconds, a rational).
_EXIF_EXPOSURE_TIME = 33434


def _read_bgr(path: str | os.PathLike) -> np.ndarray:
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError("OpenCV cannot decode it")
    if image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"its samples are {image.dtype}; only 8- and 16-bit integer images are brackets of an "
                         "LDR camera (convert float or 32-bit images to 16-bit)")
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)                    # greyscale: R = G = B
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ValueError(f"it has {image.shape[2] if image.ndim == 3 else image.ndim} channels; give colour "
                         "(3 channels, or 4 with alpha) or greyscale images")
    return image[..., :3]


def read_image_frame(path: str | os.PathLike) -> np.ndarray:
    """One image's codes, ``(rows, cols, 3)`` uint16 in R, G, B order (OpenCV reads B, G, R)."""
    return np.ascontiguousarray(_read_bgr(path)[..., ::-1]).astype(np.uint16)


def _exif_exposure_time(path: str | os.PathLike) -> float | None:
    try:
        from PIL import Image

        with Image.open(path) as im:
            exif = im.getexif()
            value = exif.get_ifd(0x8769).get(_EXIF_EXPOSURE_TIME) or exif.get(_EXIF_EXPOSURE_TIME)
        seconds = float(value) if value is not None else 0.0
    except Exception:  # noqa: BLE001 - no EXIF is the common case; the manifest then needs the time
        return None
    return seconds if np.isfinite(seconds) and seconds > 0 else None


def probe_image_file(path: str | os.PathLike) -> RawFrameInfo:
    """Size, bit depth and EXIF exposure time of an image (the probe of :func:`plan_image_import`):
    ``bayer_pattern`` ``"RGB"``, black level 0, white level 255 or 65535."""
    image = _read_bgr(path)
    white = int(np.iinfo(image.dtype).max)
    return RawFrameInfo(shape=(int(image.shape[0]), int(image.shape[1])), bayer_pattern="RGB",
                        black_level_per_channel=(0, 0, 0, 0), white_level=white,
                        exposure_time=_exif_exposure_time(path),
                        white_level_source=f"{white.bit_length()}-bit image")


def _image_unreadable(where: str, path: Path, exc: Exception) -> str:
    kind = identify_image_file(path)
    if kind is None:
        return (f"{where}: not a TIFF, PNG or JPEG image OpenCV can read ({exc}); camera raw files go to "
                "`btf import-raw`, images must be re-exported")
    return f"{where}: {kind} that cannot be used ({exc}); re-export it from the camera's software"


def plan_image_import(folder: str | os.PathLike, manifest: str | os.PathLike) -> RawImportPlan:
    """Check a folder of images and its manifest completely (:func:`tasks.ingest_raw.plan_raw_import` with
    OpenCV as the reader); raise :class:`tasks.ingest_raw.RawImportError` listing every problem."""
    try:
        plan = plan_raw_import(folder, manifest, probe=probe_image_file, unreadable=_image_unreadable)
    except RawImportError as err:
        problems = [p.replace("all files of a capture must come from one camera model and mode",
                              "all images of a capture must have one size and bit depth") for p in err.problems]
        raise RawImportError(problems) from None
    if plan.darks:
        raise RawImportError([f"{manifest}: rows with role 'dark' are for camera raw files (btf import-raw); an "
                              "image's black level is already removed by the camera, drop them"])
    return plan


def load_response(path: str | os.PathLike, n_codes: int) -> np.ndarray:
    """A camera response from a file: ``(n_codes, 3)`` float64 relative exposure per code and channel.

    ``.npy`` (an array), ``.json`` (a list, or an object with key ``response``) or text (``.csv``,
    ``.txt``: ``n_codes`` rows of 1 or 3 numbers, e.g. ``np.savetxt`` of OpenCV's
    ``CalibrateDebevec`` output reshaped to ``(256, 3)``, in R, G, B column order). One column is used for
    every channel. Raises ``ValueError`` naming the file, what is wrong and what to give."""
    p = Path(path)
    want = f"{n_codes} rows (one per code of the images' {int(n_codes - 1).bit_length()}-bit values) of 1 or 3 " \
           "numbers (R, G, B), finite and >= 0"
    try:
        if p.suffix.lower() == ".npy":
            r = np.load(p, allow_pickle=False)
        elif p.suffix.lower() == ".json":
            data = json.loads(p.read_text())
            r = np.asarray(data["response"] if isinstance(data, dict) else data, dtype=np.float64)
        else:
            r = np.loadtxt(p, delimiter="," if p.suffix.lower() == ".csv" else None, ndmin=2)
        r = np.asarray(r, dtype=np.float64)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{p}: cannot read a camera response ({type(exc).__name__}: {exc}); give {want}") from None
    if r.ndim == 1:
        r = r[:, None]
    if r.ndim != 2 or r.shape[0] != n_codes or r.shape[1] not in (1, 3):
        raise ValueError(f"{p}: the response has shape {r.shape}; give {want}")
    bad = ~(np.isfinite(r) & (r >= 0))
    if bad.any():
        row, col = (int(v) for v in np.argwhere(bad)[0])
        raise ValueError(f"{p}: response[{row}, {col}] = {float(r[row, col])!r}; give {want}")
    if not (r > 0).any():
        raise ValueError(f"{p}: the response is 0 everywhere; give {want}")
    return np.repeat(r, 3, axis=1) if r.shape[1] == 1 else r


def _calibration_brackets(plan: RawImportPlan, camera: int) -> tuple[list[tuple[int, int]], np.ndarray]:
    """The (turntable, illumination) brackets of ``camera`` that share its most common exposure times, at
    most :data:`CALIBRATION_BRACKETS` of them spread evenly, and those times."""
    n_turn, _, n_illum, _ = plan.shape
    keys = [(t, i) for t in range(n_turn) for i in range(n_illum)]
    times = Counter(tuple(plan.exposure_time[t, camera, i]) for t, i in keys)
    common = max(times, key=times.get)
    same = [k for k in keys if tuple(plan.exposure_time[k[0], camera, k[1]]) == common]
    pick = np.unique(np.linspace(0, len(same) - 1, min(CALIBRATION_BRACKETS, len(same))).round().astype(int))
    return [same[j] for j in pick], np.asarray(common)


def calibrate_camera_responses(plan: RawImportPlan, method: str = "debevec", seed: int = 0
                               ) -> tuple[np.ndarray, dict[str, Any]]:
    """Each camera's response, calibrated from its brackets (:func:`btfcore.capture.hdr.calibrate_response`).

    Returns
    -------
    responses : (n_cam, n_codes, 3) ndarray of float64
    info : dict
        ``method``, ``source`` (``"calibrated"``), ``seed`` and per camera the brackets used.
    """
    n_cam = plan.shape[1]
    n_codes = int(plan.white_level) + 1
    out = np.empty((n_cam, n_codes, 3))
    used = {}
    for c in range(n_cam):
        brackets, times = _calibration_brackets(plan, c)
        stack = np.stack([np.stack([read_image_frame(plan.files[(t, c, i, e)]) for e in range(plan.shape[3])])
                          for t, i in brackets], axis=1)                        # (n_exp, n_brackets, rows, cols, 3)
        codes = stack.astype(np.uint8) if n_codes == 256 else stack
        out[c] = calibrate_response(codes, times, method=method, rng=seed)
        used[str(c)] = [[int(t), int(i)] for t, i in brackets]
    return out, {"method": method, "source": "calibrated", "seed": int(seed), "brackets": used}


def image_import_metadata(plan: RawImportPlan, device: Device, response_key: dict[str, Any],
                          provenance: dict[str, Any] | None = None) -> CaptureMetadata:
    """The capture-store metadata of an image import: :func:`tasks.ingest_raw.raw_import_metadata` with
    ``bayer_pattern`` ``"RGB"`` and a ``config_hash`` that also covers how the response is obtained
    (``response_key``: method, and the file's content hash or the calibration seed)."""
    meta = raw_import_metadata(plan, device, provenance)
    prov = dict(meta.provenance)
    key = json.dumps({"raw": prov["config_hash"], "response": response_key}, sort_keys=True)
    prov.update(config_hash=hashlib.sha256(key.encode()).hexdigest()[:16], response=response_key,
                source="ingest")
    prov.pop("dark_frames", None)
    return dataclasses.replace(meta, bayer_pattern="RGB", provenance=prov)


def response_key(method: str, response_file: str | os.PathLike | None, seed: int = 0) -> dict[str, Any]:
    """What the stored response depends on: the merge method and the file's content, or the seed."""
    if method not in RESPONSE_METHODS:
        raise ValueError(f"unknown response method {method!r}; choose one of {', '.join(RESPONSE_METHODS)}")
    if response_file is None:
        return {"method": method, "source": "calibrated", "seed": int(seed)}
    digest = hashlib.sha256(Path(response_file).read_bytes()).hexdigest()[:16]
    return {"method": method, "source": "file", "file": str(response_file), "sha256": digest}


def import_images(plan: RawImportPlan, device: Device, out: str | os.PathLike, client: Any = None, *,
                  method: str = "debevec", response_file: str | os.PathLike | None = None, seed: int = 0,
                  provenance: dict[str, Any] | None = None, overwrite: bool = False,
                  strict_brackets: bool = False) -> CaptureStore:
    """Write a validated image import into a capture store: the cameras' responses (calibrated, or read
    from ``response_file`` for every camera), then one view per task (:func:`tasks.ingest_raw.import_raw`,
    which also flags brackets that do not scale with their exposure times)."""
    key = response_key(method, response_file, seed)
    meta = image_import_metadata(plan, device, key, provenance)
    n_codes = int(plan.white_level) + 1
    if response_file is None:
        responses, info = calibrate_camera_responses(plan, method, seed)
    else:
        one = load_response(response_file, n_codes)
        responses, info = np.repeat(one[None], plan.shape[1], axis=0), dict(key)
    return import_raw(plan, device, out, client, overwrite=overwrite, strict_brackets=strict_brackets, meta=meta,
                      read_frame=read_image_frame, responses=responses, response_info=info)
