"""Plan captures and measurement stores: what a capture plan measured, as ``G B``.

A capture executed from an acquisition plan (:mod:`btfcore.acquisition.plan`, ``btf simulate
--plan``) holds, per view, only the brackets the plan takes (the capture store's
``plan/shot``, docs/capture-store.md). When those brackets are a full set that
separates every LED at every view (full single-light, full S-matrix, database
bootstrapping), ``btf ingest`` demultiplexes it into a ``btf-texture`` store as
before. Otherwise (sparse, sparse + multiplexed, a subset of cameras, ...) it
writes a **measurement store** (schema ``btf-measurement`` 1.0, this module):
the rectified HDR textures of the brackets taken, ``measured``, and the
measurement matrix ``G`` relating them to the device's full single-light
light/view rows, so that ``measured = G B`` for the BTF ``B`` a full ingest
would give. ``btf reconstruct`` (:mod:`tasks.reconstruct`) solves for ``B``
with a model basis.

The store itself (its layout, creation, opening and ``G``) is :mod:`tasks.stores.measurement`;
this module holds the computation: the capture layout of a plan, which captures need a
measurement store, and the ingest that fills one (one Dask task per block of rows).
"""

from __future__ import annotations

import os
import time
from typing import Any, Callable

import numpy as np
import zarr

from btfcore.acquisition.plan import CapturePlan
from btfcore.capture.demultiplex import demultiplex_operator
from btfcore.capture.view_chain import IngestSettings, process_view, view_window
from tasks.compute import run_all
from tasks.faults import kill_point
from tasks.staging import commit_staged
from tasks.stores import CaptureMetadata, CaptureStore, bracket_steps, open_capture_store
from tasks.stores.measurement import (
    create_measurement_store,
    measurement_target,
    open_measurement_store,
    read_G,
)

__all__ = [
    "ingest_block",
    "ingest_measurement",
    "measurement_error_against_truth",
    "needs_measurement_store",
    "plan_layout",
    "process_brackets",
]


# --------------------------------------------------------------------------- plan -> capture layout


def plan_layout(plan: CapturePlan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The capture-store layout of a plan: patterns, shot of each bracket, exposure times.

    Parameters
    ----------
    plan : CapturePlan
        Validated against its device (:func:`btfcore.acquisition.plan.validate_plan`).

    Returns
    -------
    illumination : (n_illum, n_leds) ndarray of uint8
        The distinct LED sets of the plan, in order of first appearance (a full
        single-light plan gives the identity in LED order, a multiplexed plan
        the rows of its S-matrix: the layouts of ``btf simulate --illumination``).
    shot : (n_turn, n_cam, n_illum) ndarray of int32
        Plan shot index of each bracket ``(t, c, i)``, -1 where none.
    exposure_time : (n_turn, n_cam, n_illum, n_exp) ndarray of float64
        Seconds; ``n_exp`` is the longest bracket of the plan, a shorter one
        ends in zeros (steps not taken); 0 where no shot.

    Raises
    ------
    ValueError
        Two shots that take the same pattern at the same turntable position
        with the same camera (a capture store holds one bracket per
        ``(t, c, i)``), naming both shots.
    """
    patterns: dict[tuple[int, ...], int] = {}
    for s in plan.shots:
        patterns.setdefault(s.leds, len(patterns))
    illumination = np.zeros((len(patterns), plan.n_leds), dtype=np.uint8)
    for leds, i in patterns.items():
        illumination[i, list(leds)] = 1
    n_exp = max((s.n_exposures for s in plan.shots), default=1)
    shot = np.full((plan.n_turn, plan.n_cam, len(patterns)), -1, dtype=np.int32)
    times = np.zeros((plan.n_turn, plan.n_cam, len(patterns), n_exp))
    for k, s in enumerate(plan.shots):
        i = patterns[s.leds]
        cams = list(s.cameras)
        taken = shot[s.turntable, cams, i]
        if (taken >= 0).any():
            other = int(taken[taken >= 0][0])
            raise ValueError(
                f"plan for {plan.device!r}: shots {other} and {k} both capture LEDs {list(s.leds)} at turntable "
                f"position {s.turntable} with camera {cams[int(np.argmax(taken >= 0))]}; a capture holds one "
                "bracket per (turntable, camera, pattern): merge them into one shot with one bracket")
        shot[s.turntable, cams, i] = k
        times[s.turntable, cams, i, :s.n_exposures] = np.asarray(s.shutter_ms) / 1000.0   # ms -> s
    return illumination, shot, times


# --------------------------------------------------------------------------- measurement layout


def needs_measurement_store(capture: CaptureStore) -> bool:
    """Whether ``btf ingest`` writes a measurement store for this capture (instead of a BTF).

    True for a plan capture unless it takes every bracket of every view and its
    patterns separate every LED (full single-light, full S-matrix,
    bootstrapping); False for every capture without a plan.
    """
    if not capture.is_plan_capture:
        return False
    if not capture.planned.all():
        return True
    try:
        demultiplex_operator(capture.illumination)
    except ValueError:
        return True
    return False


# --------------------------------------------------------------------------- processing


def process_brackets(frames: np.ndarray, exposure_time: np.ndarray, capture: CaptureStore, t: int, c: int,
                     settings: IngestSettings,
                     window: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """HDR-merge, demosaic and rectify brackets of one view, each as measured (no demultiplexing).

    Parameters
    ----------
    frames : (k, n_exp, rows_w, cols_w) ndarray of uint16
        The window (:func:`btfcore.capture.view_chain.view_window`) of ``k`` brackets of view ``(t, c)``.
    exposure_time : (k, n_exp) ndarray
        Seconds; a plan capture's shorter brackets end in zeros, which are left out.

    Returns
    -------
    textures : (k, h, w, 3) ndarray of float32
        Linear radiance, DN/s.
    valid_fraction : (k,) ndarray of float64
    """
    meta, sensor = capture.meta, capture.meta.sensor
    steps = bracket_steps(exposure_time)
    k = len(frames)
    out = np.empty((k, *meta.texture_shape, 3), dtype=np.float32)
    valid = np.empty(k)
    for n in np.unique(steps).tolist():                  # brackets of equal length together
        sel = np.flatnonzero(steps == n)
        if n == 0:
            raise ValueError(f"{capture.path}: exposure_time[(t, c)=({t}, {c})] has an empty bracket at rows "
                             f"{sel.tolist()}; write the capture again")
        tex, val = process_view(
            np.ascontiguousarray(frames[sel, :n]), exposure_time[sel, :n], np.eye(len(sel), dtype=np.uint8),
            bayer_pattern=meta.bayer_pattern, black_level=meta.black_level, white_level=meta.white_level,
            homography=capture.homography[t, c], texture_shape=tuple(meta.texture_shape),
            sample_size_m=meta.sample_size_m, dark_frames=capture.dark_frames[c],
            dark_exposure_time=meta.dark_exposure_time, gain_e_per_dn=sensor.get("gain_e_per_dn"),
            read_noise_e=sensor.get("read_noise_e"), settings=settings, window=window)
        out[sel], valid[sel] = tex, val
    return out, valid


def ingest_block(capture_path: str, meta: CaptureMetadata, out_path: str, settings: IngestSettings,
                 block: int) -> int:
    """Process the rows of one block of the measurement (whole chunks of ``measured``) and write them.

    ``meta`` is the capture's metadata as the driver validated it (:meth:`CaptureStore.reopen`).
    """
    capture = CaptureStore.reopen(capture_path, meta)
    group = zarr.open_group(out_path, mode="r+", zarr_format=3)
    meas_index = group["meas_index"][...]
    rows = int(group.attrs["rows_per_block"])
    r0, r1 = block * rows, min((block + 1) * rows, len(meas_index))
    idx = meas_index[r0:r1]
    textures = np.empty((r1 - r0, *capture.meta.texture_shape, 3), dtype=np.float32)
    valid = np.empty(r1 - r0)
    view = idx[:, 0] * capture.n_cam + idx[:, 1]
    for v in np.unique(view).tolist():
        sel = np.flatnonzero(view == v)
        t, c = divmod(v, capture.n_cam)
        window = view_window(capture.homography[t, c], capture.roi_shape, tuple(capture.meta.texture_shape),
                             capture.meta.sample_size_m, settings)
        frames = capture.read_raw(t, c, window, idx[sel, 2])
        et = capture.exposure_time[t, c][idx[sel, 2]]
        textures[sel], valid[sel] = process_brackets(frames, et, capture, t, c, settings, window)
    group["measured"][r0:r1] = textures              # whole chunks: the block's rows x every band
    group["valid_fraction_rows"][r0:r1] = valid
    kill_point("chunk-written")
    group["written"][block] = 1                       # marker after the data
    return block


def ingest_measurement(capture: str | os.PathLike | CaptureStore, out_path: str | os.PathLike, client: Any, *,
                       settings: IngestSettings = IngestSettings(), overwrite: bool = False,
                       progress: Callable[[int, int], None] | None = None, commit: bool = True) -> dict[str, Any]:
    """Ingest a plan capture into a measurement store on a Dask cluster (resumes; staged like ``btf ingest``).

    Parameters
    ----------
    capture : str, path-like or CaptureStore
        A plan capture (:func:`needs_measurement_store`), or the store already opened (and so validated)
        by the caller.
    out_path : str or path-like
        The measurement store (.zarr).
    client : distributed.Client
    overwrite : bool
        Replace another output at ``out_path``, only once the new store is
        complete (built at :func:`tasks.staging.staging_path`).
    commit : bool
        Rename a staged replacement over ``out_path`` here (else the caller does,
        with :func:`tasks.ingest.commit_staged`).

    Returns
    -------
    summary : dict
        ``kind`` (``"measurement"``), blocks processed/skipped, ``staged``, seconds.
    """
    start = time.perf_counter()
    if not isinstance(capture, CaptureStore):
        capture = open_capture_store(capture)
    target, staged = measurement_target(capture, out_path, settings, overwrite)
    group = create_measurement_store(target, capture, settings, overwrite=staged)
    written = group["written"][...]
    pending = [] if group.attrs.get("complete") else np.flatnonzero(written == 0).tolist()
    run_all(client, ingest_block, [(capture.path, capture.meta, str(target), settings, b) for b in pending], progress)
    if not group["written"][...].all():
        raise RuntimeError(f"{target}: some blocks of rows were not written; re-run to resume")
    if not group.attrs.get("complete"):
        meas_index = group["meas_index"][...]
        vf = np.ones((capture.n_turn, capture.n_cam, capture.n_illum))
        vf[tuple(meas_index.T)] = group["valid_fraction_rows"][...]
        group["valid_fraction"][...] = vf                    # one writer, after every block
        group.attrs["complete"] = True
    if staged and commit:
        commit_staged(out_path, "ingest")
    return {"kind": "measurement", "blocks_processed": len(pending), "blocks_skipped": int(written.size - len(pending)),
            "n_meas": int(group["measured"].shape[0]), "staged": staged,
            "seconds": round(time.perf_counter() - start, 3)}


# --------------------------------------------------------------------------- reading


def measurement_error_against_truth(path: str | os.PathLike,
                                    capture: str | os.PathLike | CaptureStore) -> dict[str, float]:
    """Relative L2 error of a measurement store against ``G`` times a simulated capture's ground truth.

    Each (measured row, channel) is first brought to the truth's scale by its
    least-squares factor (the unknown LED gains and sensor conversion), so the
    figure measures the HDR / demosaic / rectify chain. ``capture``: its path, or the store opened.
    """
    group = open_measurement_store(path)
    if not isinstance(capture, CaptureStore):
        capture = open_capture_store(capture)
    measured = np.asarray(group["measured"][...], dtype=np.float64)
    truth = np.asarray(capture.truth["btf"][...], dtype=np.float64)
    expected = np.asarray(read_G(group) @ truth.reshape(truth.shape[0], -1)).reshape(measured.shape)
    scale = (measured * expected).sum(axis=(1, 2)) / np.maximum((measured ** 2).sum(axis=(1, 2)), 1e-300)
    est = measured * scale[:, None, None, :]
    return {"measurement_relative_l2_linear": float(np.linalg.norm(est - expected) / np.linalg.norm(expected))}
