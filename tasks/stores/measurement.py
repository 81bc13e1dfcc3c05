"""The measurement store (schema ``btf-measurement`` 1.0, docs/measurement-store.md): created,
opened and read here.

What ``btf ingest`` writes for a plan capture that does not separate every LED at every view
(:func:`tasks.measurement.needs_measurement_store`): the rectified HDR textures of the brackets
taken, ``measured``, and the measurement matrix ``G`` relating them to the device's full
single-light light/view rows, ``measured = G B`` for the BTF ``B`` a full ingest would give.

Layout::

    measured        float32 (n_meas, h, w, 3)   chunks (rows_per_block, band, w, 3)
    G               float32 (n_meas, n_lv)      chunks (rows_per_block, n_leds)
    meas_index      int32   (n_meas, 3)         (turntable, camera, illumination) of each row
    shot            int32   (n_meas,)           the plan's shot index of each row
    illumination    uint8   (n_illum, n_leds)   the capture's patterns
    light_dir, view_dir, lv_index               (n_lv, 3) of the full rows (as a full ingest)
    valid_fraction_rows  float64 (n_meas,)      share of usable raw pixels per row
    valid_fraction  float64 (n_turn, n_cam, n_illum)  the same per bracket, 1 where not planned
    written         uint8   (n_blocks,)         resume markers, one per block of rows

Rows ``n_meas`` are the planned brackets ``(t, c, i)`` in row-major order; the full rows ``n_lv``
are ``(t, c, led)`` row-major, exactly the rows of a full ``btf ingest`` of the same device.
The computation that fills a store is :mod:`tasks.measurement`.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import zarr

from btfcore.capture.view_chain import IngestSettings, lv_directions
from tasks.integrity import create_array
from tasks.staging import begin_store, finish_store, staged_target, staging_path
from tasks.stores.btf import band_rows
from tasks.stores.capture import CaptureStore
from tasks.stores.common import to_json_attr

if TYPE_CHECKING:
    from scipy import sparse

__all__ = [
    "SCHEMA_NAME",
    "SCHEMA_VERSION",
    "block_rows",
    "create_measurement_store",
    "measurement_hash",
    "measurement_layout",
    "measurement_target",
    "open_measurement_store",
    "plan_summary",
    "read_G",
    "write_measurement",
]

SCHEMA_NAME = "btf-measurement"
SCHEMA_VERSION = "1.0"


def plan_summary(plan: dict[str, Any] | None) -> dict[str, Any] | None:
    """A small record of a plan dict (strategy, device, shots, its SHA-256) for attributes."""
    if not plan:
        return None
    digest = hashlib.sha256(json.dumps(plan, sort_keys=True).encode()).hexdigest()[:16]
    return {"strategy": plan.get("strategy"), "device": plan.get("device"), "n_shots": len(plan.get("shots", [])),
            "parameters": plan.get("parameters", {}), "sha256": digest}


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
        "settings": asdict(settings), "material": capture.material, "complete": False,
    }))
    return finish_store(path, group)


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


def open_measurement_store(path: str | os.PathLike) -> zarr.Group:
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
    S-matrix capture at bonn-dome2's scale would take 5.5 GB)."""
    from scipy import sparse

    from btfcore.acquisition.measurement_operator import as_sparse_G

    arr = group["G"]
    step = max(1, int(arr.chunks[0]))
    blocks = []
    for r in range(0, arr.shape[0], step):
        block = np.asarray(arr[r:r + step])
        bad = np.argwhere(~np.isfinite(block))
        if bad.size:
            i, j = int(bad[0][0]), int(bad[0][1])
            raise ValueError(f"{getattr(group.store, 'root', group.store)}: G[{r + i}, {j}] = {float(block[i, j])!r} "
                             "is not finite; ingest the plan capture again (`btf ingest CAPTURE --out ... "
                             "--overwrite`)")
        blocks.append(as_sparse_G(block))
    return sparse.vstack(blocks, format="csr")
