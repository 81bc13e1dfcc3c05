"""Capture store -> BTF store, one view per Dask task (docs/architecture.md, "Stages": HDR, demosaic,
rectify and demultiplex of each view).

The BTF store (``btf-texture`` 1.0, :mod:`tasks.stores.btf`, docs/btf-store.md) an ingest writes holds

* ``btf``: float32 ``(n_lv, h, w, 3)`` linear radiance (DN/s before radiometric
  correction), rows flattened over (turntable, camera, light), chunked one view
  per chunk so that each view task owns its chunk;
* ``light_dir``, ``view_dir``: float64 ``(n_lv, 3)`` unit vectors in the sample
  frame; ``lv_index``: int32 ``(n_lv, 3)``;
* ``valid_fraction``: float64 ``(n_turn, n_cam, n_illum)`` share of raw pixels with a
  usable exposure;
* ``written``: uint8 ``(n_turn, n_cam)`` resume markers, set after a view's data;
* attrs: schema, version, units, source capture and its config hash, settings,
  ``complete``.

With ``keep_roi`` (``btf ingest --keep-roi``) the store also holds each view's HDR radiance region of
interest before rectification (``roi``, ``(n_lv, rows, cols, 3)`` float32, the whole raw frame of the
view demosaicked, demultiplexed and calibrated like the textures, SR paper §4) and the views'
``homography`` (sample metres -> region pixel); docs/btf-store.md, "Regions of interest".

With a :class:`tasks.radiometric.Calibration` (``btf ingest --white``) the
textures are divided by each LED's gain from a white standard and mapped by
the colour matrix; the store then holds ``led_gain`` (and ``colour_matrix``)
and the attribute ``radiometric`` with their provenance.

``overwrite`` never deletes a finished output first: an ingest that replaces
the store at its output path writes a sibling staging store (:func:`staging_path`,
``X.partial.zarr`` beside ``X.zarr``), which resumes like any output, and
:func:`commit_staged` renames it over the old one once it is complete (and,
in ``btf ingest``, checked); the machinery is :mod:`tasks.staging`, shared
with ``btf resample``.

A capture executed from an acquisition plan (``btf simulate --plan``) is
ingested to a BTF store like any other when it takes every bracket and its
patterns separate every LED (full single-light, full S-matrix,
bootstrapping); otherwise :func:`ingest_capture` writes a measurement store
(``btf-measurement``, :mod:`tasks.stores.measurement`, filled by :mod:`tasks.measurement`) instead: nothing is
demultiplexed, ``btf reconstruct`` solves for the BTF.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable

import numpy as np

from btfcore.capture.demultiplex import demultiplex_operator
from btfcore.capture.view_chain import IngestSettings, lv_directions, process_view, view_window
from btfcore.model.colour import REC709_LUMA
from tasks.buffers import heap_arrays, reused_buffer
from tasks.compute import run_all
from tasks.faults import kill_point
from tasks.measurement import (
    ingest_measurement,
    measurement_error_against_truth,
    needs_measurement_store,
    process_brackets,
)
from tasks.radiometric import CALIBRATED_UNITS, Calibration
from tasks.staging import staged_target, staging_path, store_attrs
from tasks.staging import commit_staged as _commit_staged
from tasks.stores import CaptureMetadata, CaptureStore, open_capture_store, write_chunk_aligned
from tasks.stores.btf import (
    LV_ORDER,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    UNCORRECTED_UNITS,
    BtfStore,
    band_rows,
    create_btf_store,
    open_btf_store,
)
from tasks.stores.common import json_key
from tasks.stores.measurement import SCHEMA_NAME as MEASUREMENT_SCHEMA
from tasks.stores.measurement import measurement_target

__all__ = [
    "band_rows",
    "btf_error_against_truth",
    "check_capture",
    "check_ingest",
    "commit_staged",
    "create_ingest_store",
    "errors_against_truth",
    "ingest_capture",
    "ingest_hash",
    "ingest_view",
    "led_scale",
    "staging_path",
    "view_chain_arguments",
]


def ingest_hash(capture: CaptureStore, settings: IngestSettings, calibration: Calibration | None = None,
                keep_roi: bool = False) -> str:
    """What an ingest output depends on: the capture's config hash, the settings, the calibration and,
    only when kept, the regions of interest (so the stores written without them keep their hashes)."""
    payload = {"capture": capture.group.attrs.get("provenance", {}).get("config_hash"),
               "settings": asdict(settings), "schema": f"{SCHEMA_NAME}/{SCHEMA_VERSION}",
               "calibration": None if calibration is None else calibration.key()}
    if keep_roi:
        payload["keep_roi"] = True
    return json_key(payload)


def _ingest_target(out: Path, key: str, overwrite: bool, keep_roi: bool = False) -> tuple[Path, bool]:
    """The store this ingest writes and whether it is the staging store of a replacement
    (:func:`tasks.staging.staged_target`, keyed by ``ingest_hash``)."""
    note = (f" (the new store is then built in {staging_path(out)} and replaces {out.name} only once it is "
            "complete and checked)")
    return staged_target(out, "ingest_hash", key, overwrite,
                         lambda attrs: _refusal(out, attrs, key, note, keep_roi))


def _refusal(path: str | os.PathLike, attrs: dict[str, Any], key: str, note: str = "",
             keep_roi: bool = False) -> FileExistsError:
    """The error for an output path that holds something other than this ingest."""
    what = (f"holds {'a complete' if attrs.get('complete') else 'an unfinished'} BTF store of another capture or "
            f"settings (ingest_hash {attrs.get('ingest_hash')!r}, this run {key!r})" if attrs else
            "exists and is not a BTF store")
    if attrs and bool(attrs.get("keep_roi")) != keep_roi:
        what += (" written with --keep-roi (regions of interest), this run without" if attrs.get("keep_roi") else
                 " written without --keep-roi, this run keeps the regions of interest")
    return FileExistsError(f"{path} {what}; choose another --out or pass --overwrite{note}")


def commit_staged(out: str | os.PathLike) -> Path:
    """Put the complete staged ingest of ``out`` (:func:`staging_path`) in place of ``out``
    (:func:`tasks.staging.commit_staged`)."""
    return _commit_staged(out, "ingest")


def check_capture(capture: str | os.PathLike | CaptureStore) -> CaptureStore:
    """Open and validate a capture store for ingest (or take the one already opened), before any
    output is touched.

    Raises
    ------
    tasks.stores.CaptureStoreError
        The store breaks its schema (every problem listed).
    ValueError
        Its illumination patterns cannot be demultiplexed into single LEDs.
    """
    if not isinstance(capture, CaptureStore):
        capture = open_capture_store(capture)
    if needs_measurement_store(capture):
        return capture                        # a sparse / partial plan capture: a measurement store, not demultiplexed
    try:
        demultiplex_operator(capture.illumination)
    except ValueError as exc:
        raise ValueError(
            f"{capture.path}: illumination ({capture.n_illum} patterns x {capture.n_leds} LEDs) cannot be "
            f"demultiplexed: {exc}; the patterns must separate every LED (single LEDs or an S-matrix): fix the "
            "store's illumination array or capture again with such patterns") from None
    return capture


def check_ingest(capture_path: str | os.PathLike | CaptureStore, out_path: str | os.PathLike, *,
                 settings: IngestSettings = IngestSettings(), overwrite: bool = False,
                 calibration: Calibration | None = None,
                 keep_roi: bool = False) -> tuple[CaptureStore, tuple[Path, bool]]:
    """Everything ``btf ingest`` refuses, checked before any work (the CLI calls it before a cluster starts).

    Returns
    -------
    capture : CaptureStore
        The validated capture store (``capture_path`` itself when it is one already).
    target : tuple of (Path, bool)
        The store this ingest writes and whether it is the staging store of a replacement.

    Raises
    ------
    tasks.stores.CaptureStoreError, ValueError
        A capture that breaks its schema or cannot be demultiplexed; a calibration that does not fit it;
        ``keep_roi`` for a plan capture whose brackets differ in length (or that goes to a measurement store).
    FileExistsError
        ``out_path`` holds another output and not ``overwrite``.
    """
    capture = check_capture(capture_path)
    if keep_roi:
        _check_keep_roi(capture)
    if needs_measurement_store(capture):
        if calibration is not None:
            raise ValueError(
                f"{capture.path}: a plan capture that is not a full set ({capture.meta.plan.get('strategy')!r} plan) "
                "is ingested to a measurement store, which is not radiometrically corrected (a multiplexed "
                "row mixes LEDs whose RGB gains differ); ingest it without --white/--colour-matrix and pass "
                "them to `btf reconstruct` instead (docs/measurement-store.md)")
        return capture, measurement_target(capture, out_path, settings, overwrite)
    if calibration is not None and calibration.led_gain is not None and len(calibration.led_gain) != capture.n_leds:
        raise ValueError(f"{calibration.info.get('white_standard')}: the white standard has "
                         f"{len(calibration.led_gain)} LEDs, the capture {capture.path} {capture.n_leds}; "
                         "calibrate with a white standard captured on the same dome")
    return capture, _ingest_target(Path(out_path), ingest_hash(capture, settings, calibration, keep_roi), overwrite,
                                   keep_roi)


def _check_keep_roi(capture: CaptureStore) -> None:
    """``--keep-roi`` needs every view's patterns merged from brackets of one length into single LEDs:
    refused for a plan capture that goes to a measurement store or whose brackets differ in length."""
    if needs_measurement_store(capture):
        raise ValueError(
            f"{capture.path}: --keep-roi keeps each view's single-LED regions of interest, but this plan capture "
            f"({capture.meta.plan.get('strategy')!r} plan) is ingested to a measurement store, which holds no "
            "single-LED images; ingest it without --keep-roi, or capture a full set (`btf simulate` without --plan)")
    if capture.is_plan_capture and (capture.exposure_time == 0).any():
        raise ValueError(
            f"{capture.path}: --keep-roi is not supported for a plan capture whose brackets differ in length; "
            "ingest it without --keep-roi, or capture with brackets of one length (`btf simulate` without --plan)")


def create_ingest_store(path: str | os.PathLike, capture: CaptureStore, settings: IngestSettings, *,
                        overwrite: bool = False, calibration: Calibration | None = None,
                        keep_roi: bool = False) -> BtfStore:
    """Create the BTF store of an ingest at ``path`` (:func:`tasks.stores.btf.create_btf_store`), or
    reopen an unfinished one of the same ingest.

    ``overwrite`` replaces a store of another ingest at ``path`` in place; :func:`ingest_capture`
    passes it only for its staging store, never for a finished output. ``keep_roi`` adds the
    regions of interest (``roi``, ``homography``; attributes ``keep_roi``, ``roi_shape``,
    ``sample_size_m``).
    """
    key = ingest_hash(capture, settings, calibration, keep_roi)
    attrs = store_attrs(path)
    if attrs is not None and attrs.get("ingest_hash") == key:
        return BtfStore(path, "r+")
    if attrs is not None and not overwrite:
        raise _refusal(path, attrs, key, keep_roi=keep_roi)
    meta = capture.meta
    h, w = meta.texture_shape
    n_turn, n_cam, n_illum, n_leds = capture.n_turn, capture.n_cam, capture.n_illum, capture.n_leds
    light_dir, view_dir, lv_index = lv_directions(meta.led_position, meta.camera_R, meta.camera_t,
                                                  meta.turntable_angle)
    small = {}
    units = UNCORRECTED_UNITS
    if calibration is not None:
        small = {name: np.asarray(getattr(calibration, name), dtype=np.float64)
                 for name in ("led_gain", "colour_matrix") if getattr(calibration, name) is not None}
        if calibration.led_gain is not None:
            units = CALIBRATED_UNITS
    roi_attrs = {}
    if keep_roi:
        small["homography"] = np.asarray(capture.homography, dtype=np.float64)     # the whole frame is the region
        roi_attrs = {"keep_roi": True, "roi_shape": [int(v) for v in capture.roi_shape],
                     "sample_size_m": float(meta.sample_size_m)}
    return create_btf_store(path, {
        "units": units, "radiometric": None if calibration is None else calibration.info,
        "lv_order": LV_ORDER, "source": str(capture.path), "ingest_hash": key, "settings": asdict(settings),
        "turntable_cameras_leds": [n_turn, n_cam, n_leds], "material": capture.material, **roi_attrs,
    }, light_dir=light_dir, view_dir=view_dir, lv_index=lv_index, texture_shape=(h, w), rows_per_chunk=n_leds,
        band=band_rows(n_leds, h, w), written_shape=(n_turn, n_cam), small=small,
        valid_fraction_shape=(n_turn, n_cam, n_illum), roi_shape=capture.roi_shape if keep_roi else None)


@heap_arrays()
def ingest_view(capture_path: str, meta: CaptureMetadata, out_path: str, settings: IngestSettings, t: int, c: int,
                calibration: Calibration | None = None, keep_roi: bool = False) -> tuple[int, int]:
    """Process one view of the capture and write its chunk of the BTF store.

    ``meta`` is the capture's metadata as the driver validated it (:meth:`CaptureStore.reopen`).
    With ``keep_roi`` the whole frame is processed and its single-LED radiance kept as the view's
    rows of ``roi``.
    """
    capture = CaptureStore.reopen(capture_path, meta)
    window = view_window(capture.homography[t, c], capture.roi_shape, tuple(meta.texture_shape),
                         meta.sample_size_m, settings, whole_frame=keep_roi)
    if capture.is_plan_capture and (capture.exposure_time[t, c] == 0).any():
        return _ingest_plan_view(capture, out_path, settings, t, c, calibration, window)
    win_shape = (window[0].stop - window[0].start, window[1].stop - window[1].start)
    raw = capture.read_raw(t, c, window, out=reused_buffer(
        "raw", (capture.n_illum, capture.n_exp, *win_shape, *capture.raw.shape[6:]), capture.raw.dtype))
    roi = reused_buffer("roi", (capture.n_leds, *win_shape, 3), np.float32) if keep_roi else None
    textures, valid = process_view(
        raw, capture.exposure_time[t, c], capture.illumination,
        **view_chain_arguments(capture, t, c, window, settings, calibration),
        out=reused_buffer("rectified", (capture.n_illum, *meta.texture_shape, 3), np.float32), roi_out=roi)
    _write_view(out_path, capture, t, c, textures, valid, roi)
    return t, c


def view_chain_arguments(capture: CaptureStore, t: int, c: int, window: tuple, settings: IngestSettings,
                         calibration: Calibration | None = None) -> dict[str, Any]:
    """The keyword arguments of :func:`btfcore.capture.view_chain.process_view` for view ``(t, c)`` of
    ``capture``: its sensor, geometry and dark frames, the settings and the calibration (also used by
    the error floors of :mod:`tasks.floors`, which replace the frames and the dark frames)."""
    meta, sensor = capture.meta, capture.meta.sensor
    response = capture.response                   # an "RGB" capture of a non-linear camera (btf import-images)
    if response is not None:
        return dict(bayer_pattern=None, black_level=0, white_level=meta.white_level,
                    homography=capture.homography[t, c], texture_shape=tuple(meta.texture_shape),
                    sample_size_m=meta.sample_size_m, response=response[0][c],
                    response_method=response[1].get("method", "debevec"), settings=settings,
                    led_gain=None if calibration is None else calibration.led_gain,
                    colour_matrix=None if calibration is None else calibration.colour_matrix, window=window)
    return dict(bayer_pattern=meta.bayer_pattern, black_level=meta.black_level, white_level=meta.white_level,
                homography=capture.homography[t, c], texture_shape=tuple(meta.texture_shape),
                sample_size_m=meta.sample_size_m, dark_frames=capture.dark_frames[c],
                dark_exposure_time=meta.dark_exposure_time, gain_e_per_dn=sensor.get("gain_e_per_dn"),
                read_noise_e=sensor.get("read_noise_e"), settings=settings,
                led_gain=None if calibration is None else calibration.led_gain,
                colour_matrix=None if calibration is None else calibration.colour_matrix, window=window)


def _write_view(out_path: str, capture: CaptureStore, t: int, c: int, textures: np.ndarray,
                valid: np.ndarray, roi: np.ndarray | None = None) -> None:
    """A view's rows of ``btf`` (exactly one chunk of rows) and of ``roi`` when kept, its valid fractions,
    then its marker."""
    group = BtfStore(out_path, "r+").group
    n_leds = capture.n_leds
    row = (t * capture.n_cam + c) * n_leds
    write_chunk_aligned(group["btf"], slice(row, row + n_leds), textures)
    if roi is not None:
        write_chunk_aligned(group["roi"], slice(row, row + n_leds), roi)
    group["valid_fraction"][t, c] = valid
    kill_point("chunk-written")
    group["written"][t, c] = 1                                 # marker after the data


def _ingest_plan_view(capture: CaptureStore, out_path: str, settings: IngestSettings, t: int, c: int,
                      calibration: Calibration | None, window: tuple) -> tuple[int, int]:
    """A view of a full plan capture whose brackets differ in length: merged per length, then demultiplexed."""
    from btfcore.capture.radiometric import apply_colour_matrix, apply_led_calibration

    illum = np.arange(capture.n_illum)
    frames = capture.read_raw(t, c, window, illum)
    rectified, valid = process_brackets(frames, capture.exposure_time[t, c], capture, t, c, settings, window)
    P = demultiplex_operator(capture.illumination).astype(np.float32)          # (n_leds, n_illum)
    textures = (P @ rectified.reshape(capture.n_illum, -1)).reshape(P.shape[0], *rectified.shape[1:])
    if calibration is not None and calibration.led_gain is not None:
        apply_led_calibration(textures, calibration.led_gain, out=textures)
    if calibration is not None and calibration.colour_matrix is not None:
        textures = apply_colour_matrix(textures, calibration.colour_matrix)
    _write_view(out_path, capture, t, c, textures, valid)
    return t, c


def ingest_capture(capture_path: str | os.PathLike | CaptureStore, out_path: str | os.PathLike, client: Any, *,
                   settings: IngestSettings = IngestSettings(), overwrite: bool = False,
                   calibration: Calibration | None = None,
                   progress: Callable[[int, int], None] | None = None, commit: bool = True,
                   keep_roi: bool = False) -> dict[str, Any]:
    """Ingest a capture store into a BTF store on a Dask cluster; resumes unfinished runs.

    The capture is opened and validated once, here (or by the caller, who passes the
    :class:`CaptureStore`); the view tasks get its path and validated metadata.
    With ``overwrite``, the store at ``out_path`` (another ingest's, or this one's: it is recomputed) is
    replaced only after the new one is complete: the views go to :func:`staging_path` (``"staged": True`` in the result), which
    :func:`commit_staged` then renames over ``out_path``, here when ``commit`` or else by the caller
    once it has checked the staged store (``btf ingest`` checks its valid fractions first). A staging
    store of this ingest is resumed, with or without ``overwrite``. ``keep_roi`` also keeps each
    view's regions of interest (``btf ingest --keep-roi``; part of the ingest hash only when true).
    """
    start = time.perf_counter()
    capture, (target, staged) = check_ingest(capture_path, out_path, settings=settings, overwrite=overwrite,
                                             calibration=calibration, keep_roi=keep_roi)
    if needs_measurement_store(capture):
        return ingest_measurement(capture, out_path, client, settings=settings, overwrite=overwrite,
                                  progress=progress, commit=commit)
    store = create_ingest_store(target, capture, settings, overwrite=staged, calibration=calibration,
                                keep_roi=keep_roi)
    written = store.written
    pending = [] if store.complete else [(t, c) for t, c in np.ndindex(written.shape) if not written[t, c]]
    run_all(client, ingest_view, [(capture.path, capture.meta, str(target), settings, t, c, calibration,
                                   keep_roi) for t, c in pending], progress)
    store.mark_complete("views")
    if staged and commit:
        commit_staged(out_path)
    result = {"views_processed": len(pending), "views_skipped": written.size - len(pending), "staged": staged}
    if not pending:
        return {**result, "seconds": 0.0}
    raw_bytes = int(np.prod(capture.raw.shape[:3])) * capture.n_exp * int(np.prod(capture.roi_shape)) * 2
    seconds = time.perf_counter() - start
    return {**result, "seconds": round(seconds, 3), "raw_mb_per_s": round(raw_bytes / 1e6 / max(seconds, 1e-9), 2)}


def _relative_errors(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Relative L2 error on linear RGB and on ``log(Y + eps)``, eps = 1e-3 of the truth's mean Y
    (noise below 0.1 % of the mean is not log-amplified)."""
    rel_linear = float(np.linalg.norm(est - truth) / np.linalg.norm(truth))
    luma = REC709_LUMA
    y_est, y_true = est @ luma, truth @ luma
    eps = 1e-3 * float(y_true.mean())
    log_est, log_true = np.log(np.maximum(y_est, 0.0) + eps), np.log(y_true + eps)
    return rel_linear, float(np.linalg.norm(log_est - log_true) / np.linalg.norm(log_true))


def btf_error_against_truth(btf_path: str | os.PathLike,
                            capture: str | os.PathLike | CaptureStore) -> dict[str, float]:
    """Relative L2 errors of an ingested BTF against a simulated capture's ground truth,
    on linear RGB and on log luminance (``log(Y + eps)``, eps = 1e-3 mean Y).

    ``capture``: the simulated capture's path, or the store already opened.
    ``relative_l2_*``: each (light, channel) of the BTF is first brought to the
    truth's scale by the least-squares factor over all views of that light
    (what a white-standard calibration measures), so that the figures
    measure the chain, not the calibration. ``calibrated_relative_l2_*``
    (only for a store ingested with ``--white``): the BTF as it is, which
    measures the chain and the white-standard calibration together.
    """
    if (store_attrs(btf_path) or {}).get("schema") == MEASUREMENT_SCHEMA:
        return measurement_error_against_truth(btf_path, capture)
    store = open_btf_store(btf_path, require_complete=False, produced_by="`btf ingest`",
                           ingested_only="the truth is sampled like the capture, so evaluate the ingested "
                                         "store, not a resampled one")
    if not isinstance(capture, CaptureStore):
        capture = open_capture_store(capture)
    btf = np.asarray(store.btf[...], dtype=np.float64)
    truth = np.asarray(capture.truth["btf"][...], dtype=np.float64)
    return errors_against_truth(btf, truth, capture.n_leds,
                                bool((store.attrs.get("radiometric") or {}).get("white_standard")))


def errors_against_truth(btf: np.ndarray, truth: np.ndarray, n_leds: int, calibrated: bool = False
                         ) -> dict[str, float]:
    """The errors of :func:`btf_error_against_truth` on arrays: ``btf`` and ``truth`` ``(n_lv, h, w, 3)``,
    rows over (turntable, camera, light) with ``n_leds`` lights; the ``calibrated_*`` ones with ``calibrated``."""
    b = np.asarray(btf, dtype=np.float64).reshape(-1, n_leds, *btf.shape[1:])
    g = np.asarray(truth, dtype=np.float64).reshape(b.shape)
    rel_linear, rel_log = _relative_errors(b * led_scale(b, g, n_leds)[None, :, None, None, :], g)
    errors = {"relative_l2_linear": rel_linear, "relative_l2_log_y": rel_log}
    if calibrated:
        rel_linear, rel_log = _relative_errors(b, g)
        errors.update({"calibrated_relative_l2_linear": rel_linear, "calibrated_relative_l2_log_y": rel_log})
    return errors


def led_scale(btf: np.ndarray, truth: np.ndarray, n_leds: int) -> np.ndarray:
    """The least-squares factor per (light, channel) that maps ``btf`` to ``truth`` over every view and texel
    (what a white-standard calibration measures).

    ``btf``, ``truth``: ``(n_lv, h, w, 3)`` (or already ``(n_views, n_leds, h, w, 3)``) with rows over
    (turntable, camera, light). Returns ``(n_leds, 3)``.
    """
    b = np.asarray(btf, dtype=np.float64).reshape(-1, n_leds, *np.shape(btf)[-3:])
    g = np.asarray(truth, dtype=np.float64).reshape(b.shape)
    return (b * g).sum(axis=(0, 2, 3)) / np.maximum((b * b).sum(axis=(0, 2, 3)), 1e-300)

