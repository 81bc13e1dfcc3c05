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

Layout (docs/measurement-store.md)::

    measured        float32 (n_meas, h, w, 3)   chunks (rows_per_block, band, w, 3)
    G               float32 (n_meas, n_lv)      chunks (rows_per_block, n_leds)
    meas_index      int32   (n_meas, 3)         (turntable, camera, illumination) of each row
    shot            int32   (n_meas,)           the plan's shot index of each row
    illumination    uint8   (n_illum, n_leds)   the capture's patterns
    light_dir, view_dir, lv_index               (n_lv, 3) of the full rows (as a full ingest)
    valid_fraction_rows  float64 (n_meas,)      share of usable raw pixels per row
    valid_fraction  float64 (n_turn, n_cam, n_illum)  the same per bracket, 1 where not planned
    written         uint8   (n_blocks,)         resume markers, one per block of rows

Rows ``n_meas`` are the planned brackets ``(t, c, i)`` in row-major order; the
full rows ``n_lv`` are ``(t, c, led)`` row-major, exactly the rows of a full
``btf ingest`` of the same device.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable

import numpy as np
import zarr

from btfcore.capture.demultiplex import demultiplex_operator
from btfcore.capture.view_chain import IngestSettings, lv_directions, process_view, view_window
from btfcore.acquisition.plan import CapturePlan
from tasks.integrity import create_array
from tasks.staging import begin_store, finish_store, staged_target, staging_path
from tasks.stores import CaptureStore, bracket_steps, open_capture_store, to_json_attr

__all__ = [
    "SCHEMA_NAME",
    "SCHEMA_VERSION",
    "block_rows",
    "create_measurement_store",
    "ingest_measurement",
    "measurement_error_against_truth",
    "measurement_layout",
    "needs_measurement_store",
    "open_measurement",
    "plan_layout",
    "process_brackets",
    "write_measurement",
]

SCHEMA_NAME = "btf-measurement"
SCHEMA_VERSION = "1.0"
#: Bytes of one chunk of ``measured`` aimed for (as ``tasks.ingest.CHUNK_BYTES``).
CHUNK_BYTES = 4 << 20


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


def plan_summary(plan: dict[str, Any] | None) -> dict[str, Any] | None:
    """A small record of a plan dict (strategy, device, shots, its SHA-256) for attributes."""
    if not plan:
        return None
    digest = hashlib.sha256(json.dumps(plan, sort_keys=True).encode()).hexdigest()[:16]
    return {"strategy": plan.get("strategy"), "device": plan.get("device"), "n_shots": len(plan.get("shots", [])),
            "parameters": plan.get("parameters", {}), "sha256": digest}


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


def measurement_layout(capture: CaptureStore) -> tuple[np.ndarray, np.ndarray]:
    """Rows of a capture's measurement and its matrix ``G``.

    Returns
    -------
    meas_index : (n_meas, 3) ndarray of int32
        ``(t, c, i)`` of the planned brackets, row-major.
    G : (n_meas, n_lv) ndarray of float32
        ``G[r, (t * n_cam + c) * n_leds + l] = illumination[i, l]``: each
        measured texture is the sum of the single-LED textures of its pattern
        (light superposes) at its view.
    """
    meas_index = np.argwhere(capture.planned).astype(np.int32)
    n_cam, n_leds = capture.n_cam, capture.n_leds
    G = np.zeros((len(meas_index), capture.n_lv), dtype=np.float32)
    view = meas_index[:, 0] * n_cam + meas_index[:, 1]
    cols = view[:, None] * n_leds + np.arange(n_leds)[None, :]
    G[np.arange(len(meas_index))[:, None], cols] = capture.illumination[meas_index[:, 2]]
    return meas_index, G


def block_rows(meas_index: np.ndarray) -> int:
    """Rows per chunk of ``measured``: the most brackets any view takes (a view's worth, as a BTF store's
    chunk is one view's LEDs)."""
    if not len(meas_index):
        return 1
    _, counts = np.unique(meas_index[:, 0] * (meas_index[:, 1].max() + 1) + meas_index[:, 1], return_counts=True)
    return int(counts.max())


def measurement_hash(capture: CaptureStore, settings: IngestSettings) -> str:
    """What a measurement store depends on: the capture's config hash and the ingest settings."""
    payload = {"capture": capture.group.attrs.get("provenance", {}).get("config_hash"),
               "settings": asdict(settings), "schema": f"{SCHEMA_NAME}/{SCHEMA_VERSION}"}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]


def create_measurement_store(path: str | os.PathLike, capture: CaptureStore, settings: IngestSettings, *,
                             overwrite: bool = False) -> zarr.Group:
    """Create the measurement store of a plan capture at ``path`` (or reopen an unfinished one of it)."""
    from tasks.ingest import band_rows, material_of

    key = measurement_hash(capture, settings)
    if Path(path).exists():
        try:
            attrs = dict(zarr.open_group(str(path), mode="r", zarr_format=3).attrs)
        except Exception:  # noqa: BLE001 - not a group: refused below
            attrs = {}
        if attrs.get("ingest_hash") == key:
            return zarr.open_group(str(path), mode="r+", zarr_format=3)
        if not overwrite:
            raise FileExistsError(f"{path} holds something else (ingest_hash {attrs.get('ingest_hash')!r}, this run "
                                  f"{key!r}); choose another --out or pass --overwrite")
    meta = capture.meta
    h, w = meta.texture_shape
    meas_index, G = measurement_layout(capture)
    n_meas, n_leds = len(meas_index), capture.n_leds
    rows = block_rows(meas_index)
    n_blocks = -(-n_meas // rows)
    group = begin_store(path)
    create_array(group, "measured", shape=(n_meas, h, w, 3), chunks=(rows, band_rows(rows, h, w), w, 3),
                       dtype="float32", fill_value=0.0, compressors=None,
                       dimension_names=["meas", "tex_row", "tex_col", "channel"])
    g = create_array(group, "G", shape=G.shape, chunks=(rows, n_leds), dtype="float32", fill_value=0.0,
                           compressors=None, dimension_names=["meas", "lv"])
    g[...] = G                                            # chunks that are all 0 are not stored
    light_dir, view_dir, lv_index = lv_directions(meta.led_position, meta.camera_R, meta.camera_t,
                                                  meta.turntable_angle)
    small = {"meas_index": meas_index, "shot": meta.plan_shot[tuple(meas_index.T)].astype(np.int32),
             "illumination": capture.illumination.astype(np.uint8), "light_dir": light_dir, "view_dir": view_dir,
             "lv_index": lv_index}
    for name, data in small.items():
        create_array(group, name, shape=data.shape, dtype=data.dtype, chunks=data.shape, compressors=None)[...] = data
    create_array(group, "valid_fraction_rows", shape=(n_meas,), chunks=(rows,), dtype="float64", fill_value=0.0,
                       compressors=None)
    create_array(group, "valid_fraction", shape=(capture.n_turn, capture.n_cam, capture.n_illum),
                       chunks=(capture.n_turn, capture.n_cam, capture.n_illum), dtype="float64", fill_value=1.0,
                       compressors=None)
    create_array(group, "written", shape=(n_blocks,), chunks=(1,), dtype="uint8", fill_value=0, compressors=None)
    single = bool(np.all((G == 0) | (G == 1)) and np.all((G != 0).sum(axis=1) == 1))
    group.attrs.put(to_json_attr({
        "schema": SCHEMA_NAME, "schema_version": SCHEMA_VERSION,
        "units": "DN/s per unit LED drive, before radiometric correction",
        "lv_order": ["turntable", "camera", "light"], "meas_order": ["turntable", "camera", "illumination"],
        "texture_shape": [h, w], "turntable_cameras_leds": [capture.n_turn, capture.n_cam, n_leds],
        "n_meas": n_meas, "rows_per_block": rows, "single_light": single,
        "plan": plan_summary(meta.plan), "source": str(capture.path), "ingest_hash": key,
        "settings": asdict(settings), "material": material_of(capture), "complete": False,
    }))
    return finish_store(path, group)


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


def ingest_block(capture_path: str, out_path: str, settings: IngestSettings, block: int) -> int:
    """Process the rows of one block of the measurement (whole chunks of ``measured``) and write them."""
    from tasks.ingest import open_capture_once

    capture = open_capture_once(capture_path)
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
    group["written"][block] = 1                       # marker after the data
    return block


def measurement_target(capture: CaptureStore, out_path: str | os.PathLike, settings: IngestSettings,
                       overwrite: bool) -> tuple[Path, bool]:
    """The store an ingest of ``capture`` into a measurement store at ``out_path`` writes, and whether it
    is the staging store of a replacement (:func:`tasks.staging.staged_target`, keyed by
    :func:`measurement_hash`); ``btf ingest`` asks it before any cluster starts.

    Raises
    ------
    FileExistsError
        ``out_path`` holds another store and not ``overwrite`` (the message names ``--overwrite``).
    """
    def refusal(attrs):
        what = (f"holds another store (schema {attrs.get('schema')!r}, ingest_hash {attrs.get('ingest_hash')!r})"
                if attrs else "exists and is not a Zarr store")
        return FileExistsError(f"{out_path} {what}; choose another --out or pass --overwrite (the new store is then "
                               f"built in {staging_path(out_path)} and replaces it only once complete)")

    return staged_target(Path(out_path), "ingest_hash", measurement_hash(capture, settings), overwrite, refusal)


def ingest_measurement(capture_path: str | os.PathLike, out_path: str | os.PathLike, client: Any, *,
                       settings: IngestSettings = IngestSettings(), overwrite: bool = False,
                       progress: Callable[[int, int], None] | None = None, commit: bool = True) -> dict[str, Any]:
    """Ingest a plan capture into a measurement store on a Dask cluster (resumes; staged like ``btf ingest``).

    Parameters
    ----------
    capture_path : str or path-like
        A plan capture (:func:`needs_measurement_store`).
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
    from distributed import as_completed

    from tasks.ingest import commit_staged

    start = time.perf_counter()
    capture = open_capture_store(capture_path)
    target, staged = measurement_target(capture, out_path, settings, overwrite)
    group = create_measurement_store(target, capture, settings, overwrite=staged)
    written = group["written"][...]
    pending = [] if group.attrs.get("complete") else np.flatnonzero(written == 0).tolist()
    futures = [client.submit(ingest_block, str(capture_path), str(target), settings, b, pure=False) for b in pending]
    for done, future in enumerate(as_completed(futures), 1):
        future.result()
        if progress is not None:
            progress(done, len(futures))
    if not group["written"][...].all():
        raise RuntimeError(f"{target}: some blocks of rows were not written; re-run to resume")
    if not group.attrs.get("complete"):
        meas_index = group["meas_index"][...]
        vf = np.ones((capture.n_turn, capture.n_cam, capture.n_illum))
        vf[tuple(meas_index.T)] = group["valid_fraction_rows"][...]
        group["valid_fraction"][...] = vf                    # one writer, after every block
        group.attrs["complete"] = True
    if staged and commit:
        commit_staged(out_path)
    return {"kind": "measurement", "blocks_processed": len(pending), "blocks_skipped": int(written.size - len(pending)),
            "n_meas": int(group["measured"].shape[0]), "staged": staged,
            "seconds": round(time.perf_counter() - start, 3)}


def write_measurement(path: str | os.PathLike, measured: np.ndarray, G: np.ndarray, light_dir: np.ndarray,
                      view_dir: np.ndarray, turntable_cameras_leds: tuple[int, int, int], *,
                      units: str = "linear radiance", source: str = "", material: dict[str, Any] | None = None,
                      rows_per_block: int | None = None) -> zarr.Group:
    """Write an in-memory measurement (``measured = G B``) as a finished measurement store.

    For measurements made elsewhere (another device's software, a synthetic
    experiment): the layout of :func:`create_measurement_store`, with
    ``meas_index``/``shot``/``illumination`` left out (they describe a capture).

    Parameters
    ----------
    measured : (n_meas, h, w, 3) ndarray
    G : (n_meas, n_lv) ndarray
    light_dir, view_dir : (n_lv, 3) ndarray
        Directions of the full rows, ``n_lv = n_turn * n_cam * n_leds``.
    turntable_cameras_leds : (3,) tuple of int

    Raises
    ------
    ValueError
        Inconsistent shapes, NaN/Inf, or something at ``path`` already.
    """
    measured, G = np.asarray(measured, dtype=np.float32), np.asarray(G, dtype=np.float32)
    n_turn, n_cam, n_leds = (int(v) for v in turntable_cameras_leds)
    n_lv = n_turn * n_cam * n_leds
    if measured.ndim != 4 or measured.shape[3] != 3 or G.shape != (measured.shape[0], n_lv):
        raise ValueError(f"measured {measured.shape} and G {G.shape} must be (n_meas, h, w, 3) and (n_meas, {n_lv})")
    if light_dir.shape != (n_lv, 3) or view_dir.shape != (n_lv, 3):
        raise ValueError(f"light_dir {light_dir.shape} and view_dir {view_dir.shape} must be ({n_lv}, 3)")
    for name, a in (("measured", measured), ("G", G)):
        bad = np.argwhere(~np.isfinite(a))
        if bad.size:
            raise ValueError(f"{name}{bad[0].tolist()} is not finite")
    if Path(path).exists():
        raise ValueError(f"{path} exists; choose another path")
    from tasks.ingest import band_rows

    n_meas, h, w, _ = measured.shape
    rows = int(rows_per_block or min(n_meas, n_leds))
    group = begin_store(path)
    create_array(group, "measured", shape=measured.shape, chunks=(rows, band_rows(rows, h, w), w, 3), dtype="float32",
                       fill_value=0.0, compressors=None,
                       dimension_names=["meas", "tex_row", "tex_col", "channel"])[...] = measured
    create_array(group, "G", shape=G.shape, chunks=(rows, n_leds), dtype="float32", fill_value=0.0, compressors=None,
                       dimension_names=["meas", "lv"])[...] = G
    lv_index = np.indices((n_turn, n_cam, n_leds)).reshape(3, -1).T.astype(np.int32)
    for name, data in (("light_dir", np.asarray(light_dir, np.float64)), ("view_dir", np.asarray(view_dir, np.float64)),
                       ("lv_index", lv_index)):
        create_array(group, name, shape=data.shape, dtype=data.dtype, chunks=data.shape, compressors=None)[...] = data
    key = hashlib.sha256(measured.tobytes() + G.tobytes()).hexdigest()[:16]
    single = bool(np.all((G == 0) | (G == 1)) and np.all((G != 0).sum(axis=1) == 1))
    group.attrs.put(to_json_attr({
        "schema": SCHEMA_NAME, "schema_version": SCHEMA_VERSION, "units": units,
        "lv_order": ["turntable", "camera", "light"], "texture_shape": [h, w],
        "turntable_cameras_leds": [n_turn, n_cam, n_leds], "n_meas": n_meas, "rows_per_block": rows,
        "single_light": single, "plan": None, "source": source, "ingest_hash": key, "settings": None,
        "material": material, "complete": True}))
    return finish_store(path, group)


# --------------------------------------------------------------------------- reading


def open_measurement(path: str | os.PathLike) -> zarr.Group:
    """Open a finished measurement store, naming what is wrong with it.

    Raises
    ------
    ValueError
        Not a ``btf-measurement`` store, or unfinished.
    """
    try:
        group = zarr.open_group(str(path), mode="r", zarr_format=3)
    except Exception as exc:  # noqa: BLE001
        raise ValueError(f"{path}: not a readable Zarr store ({exc}); give the output of `btf ingest`") from None
    attrs = dict(group.attrs)
    if attrs.get("schema") != SCHEMA_NAME:
        raise ValueError(f"{path}: schema {attrs.get('schema')!r}, not a measurement store ({SCHEMA_NAME}); "
                         "give the `btf ingest` output of a plan capture")
    if not attrs.get("complete"):
        raise ValueError(f"{path}: the measurement ingest is unfinished (complete = false); run `btf ingest` again")
    return group


def read_G(group: zarr.Group) -> "sparse.csr_matrix":
    """A measurement store's ``G``, read block of rows by block into a float64 CSR matrix (dense, a full
    S-matrix capture at the thesis' scale would take 5.5 GB)."""
    from scipy import sparse

    from btfcore.acquisition.measurement_operator import as_sparse_G

    arr = group["G"]
    step = max(1, int(arr.chunks[0]))
    return sparse.vstack([as_sparse_G(np.asarray(arr[r:r + step])) for r in range(0, arr.shape[0], step)],
                         format="csr")


def measurement_error_against_truth(path: str | os.PathLike, capture_path: str | os.PathLike) -> dict[str, float]:
    """Relative L2 error of a measurement store against ``G`` times a simulated capture's ground truth.

    Each (measured row, channel) is first brought to the truth's scale by its
    least-squares factor (the unknown LED gains and sensor conversion), so the
    figure measures the HDR / demosaic / rectify chain.
    """
    group = open_measurement(path)
    capture = open_capture_store(capture_path)
    measured = np.asarray(group["measured"][...], dtype=np.float64)
    truth = np.asarray(capture.truth["btf"][...], dtype=np.float64)
    expected = np.asarray(read_G(group) @ truth.reshape(truth.shape[0], -1)).reshape(measured.shape)
    scale = (measured * expected).sum(axis=(1, 2)) / np.maximum((measured ** 2).sum(axis=(1, 2)), 1e-300)
    est = measured * scale[:, None, None, :]
    return {"measurement_relative_l2_linear": float(np.linalg.norm(est - expected) / np.linalg.norm(expected))}
