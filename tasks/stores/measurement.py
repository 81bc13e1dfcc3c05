"""The measurement store (schema ``btf-measurement`` 1.0, docs/measurement-store.md): created,
opened, validated (:func:`validate_measurement_store`, ``btf validate``) and read here.

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
import os
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import zarr

from btfcore.capture.view_chain import IngestSettings, lv_directions
from tasks.integrity import CorruptChunkError, create_array, open_any_store
from tasks.staging import begin_store, finish_store, staged_target, staging_path
from tasks.stores.btf import UNIT_TOL, band_rows
from tasks.stores.capture import CaptureStore
from tasks.stores.common import (
    json_key,
    ROOT_ATTRS,
    WHOLE_STORE,
    Problem,
    listing,
    read_whole,
    root_attr_problems,
    to_json_attr,
)

if TYPE_CHECKING:
    from scipy import sparse

__all__ = [
    "ARRAYS",
    "CAPTURE_ARRAYS",
    "REQUIRED_ATTRS",
    "SCHEMA_NAME",
    "SCHEMA_VERSION",
    "block_rows",
    "create_measurement_store",
    "g_rows",
    "measurement_hash",
    "measurement_layout",
    "measurement_target",
    "open_measurement_store",
    "plan_summary",
    "read_G",
    "validate_measurement_store",
    "write_measurement",
]

SCHEMA_NAME = "btf-measurement"
SCHEMA_VERSION = "1.0"
#: Root attributes of every measurement store (both writers).
REQUIRED_ATTRS = ("schema", "schema_version", "units", "lv_order", "texture_shape", "turntable_cameras_leds",
                  "n_meas", "rows_per_block", "single_light", "ingest_hash", "complete")
#: Arrays of every measurement store: name -> (dtype, or ``"float"``/``"int"`` for any of that kind; shape by
#: the sizes of the attributes: ``n_lv = n_turn * n_cam * n_leds`` of ``turntable_cameras_leds``).
ARRAYS: dict[str, tuple[str, tuple[str | int, ...]]] = {
    "measured": ("float32", ("n_meas", "h", "w", 3)), "G": ("float32", ("n_meas", "n_lv")),
    "light_dir": ("float", ("n_lv", 3)), "view_dir": ("float", ("n_lv", 3)), "lv_index": ("int", ("n_lv", 3))}
#: The further arrays of a store that ``btf ingest`` wrote from a plan capture (attribute ``meas_order``);
#: ``n_illum`` is the number of patterns, ``n_blocks`` that of blocks of ``rows_per_block`` rows.
CAPTURE_ARRAYS: dict[str, tuple[str, tuple[str | int, ...]]] = {
    "meas_index": ("int", ("n_meas", 3)), "shot": ("int", ("n_meas",)),
    "illumination": ("uint8", ("n_illum", "n_leds")),
    "valid_fraction_rows": ("float64", ("n_meas",)), "valid_fraction": ("float64", ("n_turn", "n_cam", "n_illum")),
    "written": ("uint8", ("n_blocks",))}
#: What to do about a store that does not hold what the schema says.
_REWRITE = ("write the store again (`btf ingest CAPTURE --out STORE --overwrite` of the plan capture, or "
            "tasks.stores.measurement.write_measurement)")


def plan_summary(plan: dict[str, Any] | None) -> dict[str, Any] | None:
    """A small record of a plan dict (strategy, device, shots, its SHA-256) for attributes."""
    if not plan:
        return None
    digest = json_key(plan)
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
    return meas_index, g_rows(meas_index, capture.illumination, capture.n_cam, capture.n_leds, capture.n_lv)


def g_rows(meas_index: np.ndarray, illumination: np.ndarray, n_cam: int, n_leds: int, n_lv: int) -> np.ndarray:
    """The rows of ``G`` of some brackets: each measured texture is the sum of the single-LED textures of
    its pattern at its view (light superposes).

    Parameters
    ----------
    meas_index : (rows, 3) ndarray of int
        ``(t, c, i)`` of each bracket.
    illumination : (n_illum, n_leds) ndarray
        The capture's patterns.
    n_cam, n_leds, n_lv : int
        Cameras and LEDs of the dome, full rows ``n_turn * n_cam * n_leds``.

    Returns
    -------
    (rows, n_lv) ndarray of float32
        ``G[r, (t * n_cam + c) * n_leds + l] = illumination[i, l]`` for ``meas_index[r] = (t, c, i)``.
    """
    G = np.zeros((len(meas_index), n_lv), dtype=np.float32)
    view = meas_index[:, 0] * n_cam + meas_index[:, 1]
    cols = view[:, None] * n_leds + np.arange(n_leds)[None, :]
    G[np.arange(len(meas_index))[:, None], cols] = illumination[meas_index[:, 2]]
    return G


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
    return json_key(payload)


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


def validate_measurement_store(path: str | os.PathLike, require_complete: bool = True) -> list[Problem]:
    """Check a measurement store against the schema and list every problem (``btf validate``).

    Checks the root attributes (:data:`REQUIRED_ATTRS`, the schema version, the sizes they give), the
    arrays' presence, dtypes and shapes against those sizes and each other (:data:`ARRAYS`, and
    :data:`CAPTURE_ARRAYS` for a store ingested from a capture), the chunking by ``rows_per_block``,
    the directions (finite unit vectors), ``lv_index`` (row-major over ``turntable_cameras_leds``),
    ``meas_index`` (planned brackets in row-major order, inside the dome), the patterns (0 or 1),
    ``valid_fraction_rows`` (in [0, 1]), the markers (0 or 1, all set in a complete store) and ``G``:
    read block of rows by block, every row the pattern of its bracket at its view (a store ingested
    from a capture) and ``single_light`` as ``G`` says. ``measured`` is never read: its NaN/Inf
    values are found by ``btf validate --deep`` (:func:`tasks.integrity.verify_store`).

    Parameters
    ----------
    path : str or path-like
        Store directory or fsspec URL.
    require_complete : bool
        Report an unfinished store (``complete`` false) as a problem.

    Returns
    -------
    list of Problem
        Empty when the store is valid; each names the array (or attribute) and the index. Content
        problems never raise.
    """
    try:
        group, _ = open_any_store(path)
    except (FileNotFoundError, ValueError) as e:
        return [Problem(WHOLE_STORE, None, "a measurement store (a Zarr v3 group)", str(e),
                        "check the path; give the `btf ingest` output of a plan capture")]
    attrs = dict(group.attrs)
    if attrs.get("schema") != SCHEMA_NAME:
        return [Problem(ROOT_ATTRS, "schema", repr(SCHEMA_NAME), repr(attrs.get("schema")),
                        "this is not a measurement store; give the `btf ingest` output of a plan capture")]
    problems = root_attr_problems(attrs, REQUIRED_ATTRS, SCHEMA_NAME, SCHEMA_VERSION, _REWRITE)
    dims = _attr_sizes(attrs, problems)
    arrays = _checked_arrays(group, {**ARRAYS, **(CAPTURE_ARRAYS if "meas_order" in attrs else {})}, dims, problems)
    data = {name: read_whole(name, arrays[name], problems) for name in arrays if name not in ("measured", "G")}
    _content_problems(attrs, dims, data, problems)
    if "G" in arrays:
        _g_problems(arrays["G"], attrs, dims, data, problems)
    if require_complete and attrs.get("complete") is False:
        problems.append(Problem(ROOT_ATTRS, "complete", "true", "false",
                                "the ingest is unfinished; run `btf ingest` again with the same --out to resume"))
    return problems


def _attr_sizes(attrs: dict[str, Any], problems: list[Problem]) -> dict[str, int]:
    """The sizes the attributes give (``n_meas``, ``h``, ``w``, ``n_turn``, ``n_cam``, ``n_leds``, ``n_lv``,
    ``rows``, ``n_blocks``); a malformed attribute is a problem and its sizes are left out."""
    sizes: dict[str, int] = {}
    for key, names in (("texture_shape", ("h", "w")), ("turntable_cameras_leds", ("n_turn", "n_cam", "n_leds")),
                       ("n_meas", ("n_meas",)), ("rows_per_block", ("rows",))):
        if key not in attrs:
            continue
        value = attrs[key]
        values = value if isinstance(value, list) else [value]
        if len(values) == len(names) and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in values):
            sizes.update(zip(names, values))
        else:
            words = f"[{', '.join(names)}], positive integers" if len(names) > 1 else "a positive integer"
            problems.append(Problem(ROOT_ATTRS, key, words, repr(value), _REWRITE))
    if all(k in sizes for k in ("n_turn", "n_cam", "n_leds")):
        sizes["n_lv"] = sizes["n_turn"] * sizes["n_cam"] * sizes["n_leds"]
    if "rows" in sizes and "n_meas" in sizes:
        sizes["n_blocks"] = -(-sizes["n_meas"] // sizes["rows"])
    if "lv_order" in attrs and attrs["lv_order"] != ["turntable", "camera", "light"]:
        problems.append(Problem(ROOT_ATTRS, "lv_order", repr(["turntable", "camera", "light"]),
                                repr(attrs["lv_order"]), _REWRITE))
    for key in ("single_light", "complete"):
        if key in attrs and not isinstance(attrs[key], bool):
            problems.append(Problem(ROOT_ATTRS, key, "true or false", repr(attrs[key]), _REWRITE))
    return sizes


def _checked_arrays(group: zarr.Group, schema: dict[str, tuple[str, tuple[str | int, ...]]], sizes: dict[str, int],
                    problems: list[Problem]) -> dict[str, zarr.Array]:
    """The arrays of ``schema`` that are there with their dtype and shape (the others are problems);
    ``n_illum`` is taken from ``illumination``."""
    found: dict[str, zarr.Array] = {}
    for name, (dtype, shape) in schema.items():
        node = group.get(name)
        if not isinstance(node, zarr.Array):
            problems.append(Problem(name, None, f"array {name!r}, {dtype} of shape ({', '.join(map(str, shape))})",
                                    "nothing" if node is None else "a group", f"the store is incomplete; {_REWRITE}"))
            continue
        kind = np.dtype(node.dtype).kind
        if not ((dtype == "float" and kind == "f") or (dtype == "int" and kind in "iu") or str(node.dtype) == dtype):
            problems.append(Problem(name, None, f"dtype {dtype}", f"dtype {node.dtype}", _REWRITE))
            continue
        if name == "illumination" and node.ndim == 2:
            sizes["n_illum"] = int(node.shape[0])
        want = tuple(sizes.get(s) if isinstance(s, str) else s for s in shape)
        if node.ndim != len(shape):
            problems.append(Problem(name, None, f"{len(shape)} axes ({', '.join(map(str, shape))})",
                                    f"shape {node.shape}", _REWRITE))
            continue
        bad = [a for a, n in enumerate(want) if n is not None and node.shape[a] != n]
        if bad:
            a = bad[0]
            problems.append(Problem(name, f"axis {a} ({shape[a]})", f"length {want[a]} (shape "
                                    f"({', '.join(str(n if n is not None else s) for n, s in zip(want, shape))}))",
                                    f"length {node.shape[a]} (shape {node.shape})", _REWRITE))
            continue
        if name in ("measured", "G", "valid_fraction_rows") and "rows" in sizes and node.chunks[0] != sizes["rows"]:
            problems.append(Problem(name, "chunks axis 0", f"{sizes['rows']} rows a chunk (rows_per_block: a block "
                                    "of rows owns whole chunks)", f"{node.chunks[0]}", _REWRITE))
        found[name] = node
    return found


def _content_problems(attrs: dict[str, Any], sizes: dict[str, int], data: dict[str, np.ndarray | None],
                      problems: list[Problem]) -> None:
    """Values of the small arrays: directions, ``lv_index``, ``meas_index``, patterns, fractions, markers."""
    for name in ("light_dir", "view_dir"):
        d = data.get(name)
        if d is not None:
            norm = np.linalg.norm(d, axis=1)
            bad = np.flatnonzero(~np.isfinite(norm) | (np.abs(norm - 1) > UNIT_TOL))
            if len(bad):
                problems.append(Problem(name, f"lv {listing(bad[:, None])}", "finite unit vectors in the sample frame",
                                        f"{len(bad)} other row(s)", _REWRITE))
    index = data.get("lv_index")
    if index is not None and "n_lv" in sizes:
        want = np.indices((sizes["n_turn"], sizes["n_cam"], sizes["n_leds"])).reshape(3, -1).T
        bad = np.flatnonzero((index != want).any(axis=1))
        if len(bad):
            problems.append(Problem("lv_index", f"lv {listing(bad[:, None])}", "(turntable, camera, light) of each "
                                    "row, row-major over turntable_cameras_leds", f"{len(bad)} other row(s)", _REWRITE))
    meas = data.get("meas_index")
    if meas is not None and all(k in sizes for k in ("n_turn", "n_cam", "n_illum")):
        inside = np.all((meas >= 0) & (meas < [sizes["n_turn"], sizes["n_cam"], sizes["n_illum"]]), axis=1)
        order = np.ravel_multi_index(tuple(np.where(inside[:, None], meas, 0).T),
                                     (sizes["n_turn"], sizes["n_cam"], sizes["n_illum"]))
        bad = np.flatnonzero(~inside | np.r_[False, np.diff(order) <= 0])
        if len(bad):
            problems.append(Problem("meas_index", f"row {listing(bad[:, None])}", "planned brackets (t, c, i) inside "
                                    f"[0, {sizes['n_turn']}) x [0, {sizes['n_cam']}) x [0, {sizes['n_illum']}), "
                                    "in row-major order", f"{len(bad)} other row(s)", _REWRITE))
    for name, ok, words in (("illumination", lambda v: np.isin(v, (0, 1)), "0 or 1"),
                            ("valid_fraction_rows", lambda v: (v >= 0) & (v <= 1), "in [0, 1]")):
        values = data.get(name)
        bad = np.argwhere(~ok(values)) if values is not None else []
        if len(bad):
            problems.append(Problem(name, listing(bad), f"values {words}", f"{len(bad)} other value(s)", _REWRITE))
    written = data.get("written")
    if written is not None:
        if not np.isin(written, (0, 1)).all():
            problems.append(Problem("written", listing(np.argwhere(~np.isin(written, (0, 1)))), "0 or 1",
                                    "other values", f"the resume markers are corrupt; {_REWRITE}"))
        elif attrs.get("complete") is True and not (written == 1).all():
            problems.append(Problem("written", listing(np.argwhere(written != 1)), "every marker set (the store is "
                                    "marked complete)", f"{int((written != 1).sum())} of {written.size} not set",
                                    "run `btf ingest` again with the same --out to resume"))


def _g_problems(G: zarr.Array, attrs: dict[str, Any], sizes: dict[str, int], data: dict[str, np.ndarray | None],
                problems: list[Problem]) -> None:
    """``G`` read block of rows by block: each row its bracket's pattern at its view (an ingested store) and
    ``single_light`` as ``G`` says (every row one pair with weight 1)."""
    meas, patterns = data.get("meas_index"), data.get("illumination")
    layout = meas is not None and patterns is not None and "n_lv" in sizes and not any(
        p.array in ("meas_index", "illumination") for p in problems)
    single, wrong = True, []
    step = max(1, int(G.chunks[0]))
    for r in range(0, G.shape[0], step):
        try:
            block = np.asarray(G[r:r + step])
        except CorruptChunkError as e:
            problems.append(Problem("G", f"chunk {e.chunk}", "a chunk that reads back as written", e.problem, e.hint))
            return
        single = single and bool(np.all((block == 0) | (block == 1)) and np.all((block != 0).sum(axis=1) == 1))
        if layout:
            want = g_rows(meas[r:r + step], patterns, sizes["n_cam"], sizes["n_leds"], sizes["n_lv"])
            wrong += (r + np.flatnonzero((block != want).any(axis=1))).tolist()
    if wrong:
        problems.append(Problem("G", f"row {listing(np.array(wrong)[:, None])}", "the pattern illumination[i] of "
                                "each row's bracket meas_index = (t, c, i) at the LEDs of its view (t, c)",
                                f"{len(wrong)} other row(s)", _REWRITE))
    if isinstance(attrs.get("single_light"), bool) and attrs["single_light"] != single:
        says = "every" if single else "not every"
        problems.append(Problem(ROOT_ATTRS, "single_light", f"{str(single).lower()}, as G says ({says} row one "
                                "light/view pair with weight 1)", str(attrs["single_light"]).lower(), _REWRITE))


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
