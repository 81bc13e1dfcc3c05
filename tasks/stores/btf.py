"""The BTF store (schema ``btf-texture`` 1.0, docs/btf-store.md): created, opened, validated and
described here, for every stage that writes or reads one.

A BTF store is a Zarr v3 group holding a BTF as linear textures, one row per light/view pair:
``btf`` ``(n_lv, h, w, 3)`` float32, so that ``B = btf.reshape(n_lv, -1)`` is the BTF matrix with
rows as textures and columns as ABRDFs; the light and view
direction of each row; ``lv_index``; and ``written`` resume markers, set after the data they mark.
Three stages write one, each with its own content key and rows:

- ``btf ingest`` (:mod:`tasks.ingest`): rows ``(turntable, camera, light)``, one chunk per view and
  band of texture rows (:func:`band_rows`), ``valid_fraction``, key ``ingest_hash``; with
  ``--keep-roi`` also each view's HDR radiance region of interest before rectification, ``roi``
  ``(n_lv, rows, cols, 3)``, and the views' ``homography`` (:data:`ROI_ARRAYS`);
- ``btf resample`` (:mod:`tasks.resample`): rows ``(view, light)``, key ``resample_hash``;
- ``btf reconstruct`` (:mod:`tasks.reconstruct`): rows as ingested, one marker per band of texture
  rows, key ``reconstruct_hash``.
- ``btf import-btf`` (:mod:`tasks.bonn.import_btf`): a Bonn BTF file's rows ``(view, light)``, one
  marker per chunk (view x band of texture rows), key ``import_hash``.

:func:`create_btf_store` writes the common layout, :func:`open_btf_store` gives a reader a
:class:`BtfStore` after the checks every reader needs (schema name and version, finished, the arrays
a reader uses and their shapes), each refusal a :class:`BtfStoreError` naming the store and what to
do, and :func:`validate_btf_store` lists every problem of a store (``btf validate``).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import zarr

from tasks.integrity import CorruptChunkError, create_array
from tasks.staging import begin_store, finish_store
from tasks.stores.common import ROOT_ATTRS, WHOLE_STORE, Problem, is_url, root_attr_problems, store_arg, to_json_attr

__all__ = [
    "ARRAYS",
    "CHUNK_BYTES",
    "ROI_ARRAYS",
    "SCHEMA_NAME",
    "SCHEMA_VERSION",
    "BtfStore",
    "BtfStoreError",
    "band_rows",
    "create_btf_store",
    "open_btf_store",
    "validate_btf_store",
]

SCHEMA_NAME = "btf-texture"
SCHEMA_VERSION = "1.0"
#: Rows of an ingested or reconstructed store, flattened row-major.
LV_ORDER = ["turntable", "camera", "light"]
#: Rows of a resampled store: view-major, light fastest.
RESAMPLED_LV_ORDER = ["view", "light"]
#: ``units`` of a store that is not radiometrically corrected.
UNCORRECTED_UNITS = "DN/s per unit LED drive, before radiometric correction"
#: Bytes of one chunk of the ``btf`` array that :func:`band_rows` aims for.
CHUNK_BYTES = 4 << 20
#: The commands that write a BTF store, for messages.
PRODUCERS = "`btf ingest`, `btf import-btf`, `btf resample`, `btf reconstruct` or `btf superres apply`"
#: Attributes every BTF store has (besides one content key of :data:`CONTENT_KEYS`).
REQUIRED_ATTRS = ("schema", "schema_version", "units", "lv_order", "texture_shape", "complete")
#: What identifies a store's content, by the stage that wrote it.
CONTENT_KEYS = ("ingest_hash", "resample_hash", "reconstruct_hash", "superres_hash", "import_hash")
#: Unit length tolerance of the direction arrays.
UNIT_TOL = 1e-6

#: The arrays of every BTF store: name -> (dtype kind, shape, meaning).
ARRAYS: dict[str, tuple[str, str, str]] = {
    "btf": ("float32", "(n_lv, h, w, 3)", "linear radiance of each light/view pair"),
    "light_dir": ("float64", "(n_lv, 3)", "unit light direction of each row, sample frame (z = normal)"),
    "view_dir": ("float64", "(n_lv, 3)", "unit view direction of each row, sample frame"),
    "lv_index": ("int", "(n_lv, len(lv_order))", "the row's index along each axis of lv_order"),
    "written": ("uint8", "(markers...)", "resume markers (views, target views or bands), set after the data"),
}
#: The arrays every reader uses.
READ_ARRAYS = ("btf", "light_dir", "view_dir")
#: The arrays of a store with regions of interest (``btf ingest --keep-roi``): name -> (dtype, shape, meaning).
ROI_ARRAYS: dict[str, tuple[str, str, str]] = {
    "roi": ("float32", "(n_lv, rows, cols, 3)", "HDR radiance region of interest of each row, before rectification"),
    "homography": ("float64", "(n_turn, n_cam, 3, 3)", "sample-plane metres -> roi pixel (col, row, 1) per view"),
}


class BtfStoreError(ValueError):
    """A BTF store that cannot be used as asked: the message names the store, what is wrong and what to do.

    Parameters
    ----------
    path : str
        Store path or URL.
    message : str
        The whole message (it starts with the path).
    """

    def __init__(self, path: Any, message: str) -> None:
        self.path = str(path)
        super().__init__(message)

    def __reduce__(self):  # picklable across Dask / Prefect process boundaries
        return (type(self), (self.path, self.args[0]))


def band_rows(n_leds: int, h: int, w: int) -> int:
    """Texture rows per chunk of ``btf``: one view's LEDs x a band of rows, about :data:`CHUNK_BYTES`.

    A view task writes every band of its view (whole chunks, so parallel views never share one),
    and the model fitting streams bands of texels across all views without reading whole views.
    """
    return int(min(h, max(1, CHUNK_BYTES // (n_leds * w * 3 * 4))))


# --------------------------------------------------------------------------- creating


def create_btf_store(path: str | os.PathLike, attrs: Mapping[str, Any], *, light_dir: np.ndarray,
                     view_dir: np.ndarray, lv_index: np.ndarray, texture_shape: Sequence[int], rows_per_chunk: int,
                     band: int, written_shape: tuple[int, ...], small: Mapping[str, np.ndarray] | None = None,
                     valid_fraction_shape: tuple[int, int, int] | None = None,
                     roi_shape: Sequence[int] | None = None) -> BtfStore:
    """Create an empty BTF store at ``path`` (replacing whatever is there), ``complete`` false.

    Parameters
    ----------
    path : path-like
        The new store (written through :func:`tasks.staging.begin_store`, so a killed creation
        leaves no half-made store).
    attrs : mapping
        The writing stage's attributes: ``units``, ``lv_order``, its content key (one of
        :data:`CONTENT_KEYS`) and its own; ``schema``, ``schema_version``, ``texture_shape`` and
        ``complete`` are set here.
    light_dir, view_dir : (n_lv, 3) ndarray of float64
        Unit directions of the rows, sample frame.
    lv_index : (n_lv, len(lv_order)) ndarray of int
    texture_shape : (2,) sequence of int
        ``(h, w)``.
    rows_per_chunk, band : int
        Chunks of ``btf``: ``(rows_per_chunk, band, w, 3)`` (a view's rows x a band of texture rows).
    written_shape : tuple of int
        Shape of the resume markers, one chunk each.
    small : mapping of str to ndarray, optional
        Further arrays stored whole (``led_gain``, ``target_light_dirs``, ``outside_hull`` ...).
    valid_fraction_shape : (n_turn, n_cam, n_illum), optional
        An ingest's ``valid_fraction``, one chunk per view.
    roi_shape : (rows, cols), optional
        An ingest's regions of interest (``btf ingest --keep-roi``): ``roi`` ``(n_lv, rows, cols, 3)``
        float32, chunks of ``rows_per_chunk`` rows x a band of about :data:`CHUNK_BYTES` of region
        rows (:func:`band_rows`); its ``homography`` comes in ``small``.

    Returns
    -------
    BtfStore
        Opened ``"r+"``.
    """
    h, w = (int(v) for v in texture_shape)
    n_lv = len(light_dir)
    if np.shape(light_dir) != (n_lv, 3) or np.shape(view_dir) != (n_lv, 3) or len(lv_index) != n_lv:
        raise ValueError(f"{path}: light_dir {np.shape(light_dir)}, view_dir {np.shape(view_dir)} and lv_index "
                         f"{np.shape(lv_index)} must have one row per light/view pair ({n_lv}, 3)")
    missing = [key for key in ("units", "lv_order") if key not in attrs]
    if missing or not any(key in attrs for key in CONTENT_KEYS):
        raise ValueError(f"{path}: BTF store attributes {missing or list(CONTENT_KEYS)} are missing; the writing "
                         "stage must give its units, lv_order and content key")
    group = begin_store(path)
    create_array(group, "btf", shape=(n_lv, h, w, 3), chunks=(int(rows_per_chunk), int(band), w, 3),
                 dtype="float32", fill_value=0.0, compressors=None,
                 dimension_names=["lv", "tex_row", "tex_col", "channel"])
    whole = {"light_dir": light_dir, "view_dir": view_dir, "lv_index": lv_index, **(small or {})}
    for name, data in whole.items():
        data = np.asarray(data)
        create_array(group, name, shape=data.shape, dtype=data.dtype, chunks=data.shape, compressors=None)[...] = data
    if roi_shape is not None:
        rows, cols = (int(v) for v in roi_shape)
        create_array(group, "roi", shape=(n_lv, rows, cols, 3),
                     chunks=(int(rows_per_chunk), band_rows(int(rows_per_chunk), rows, cols), cols, 3),
                     dtype="float32", fill_value=0.0, compressors=None,
                     dimension_names=["lv", "roi_row", "roi_col", "channel"])
    if valid_fraction_shape is not None:
        create_array(group, "valid_fraction", shape=valid_fraction_shape, chunks=(1, 1, valid_fraction_shape[2]),
                     dtype="float64", fill_value=0.0, compressors=None)
    create_array(group, "written", shape=written_shape, chunks=(1,) * len(written_shape), dtype="uint8",
                 fill_value=0, compressors=None)
    group.attrs.put(to_json_attr({"schema": SCHEMA_NAME, "schema_version": SCHEMA_VERSION, **attrs,
                                  "texture_shape": [h, w], "complete": False}))
    return BtfStore(path, "r+", group=finish_store(path, group))


# --------------------------------------------------------------------------- opening


def open_btf_store(path: str | os.PathLike, mode: str = "r", *, require_complete: bool = True,
                   ingested_only: str | None = None, produced_by: str = PRODUCERS) -> BtfStore:
    """Open a BTF store for reading after the checks every reader needs.

    Parameters
    ----------
    path : str or path-like
        Store directory or fsspec URL.
    mode : {"r", "r+"}
    require_complete : bool
        Refuse a store whose writing stage has not finished (``complete`` false).
    ingested_only : str, optional
        Refuse a resampled store (its rows are not the capture's), with this hint
        (:meth:`BtfStore.require_ingested`).
    produced_by : str
        The commands whose output the caller reads, for the messages (e.g. ``"`btf ingest`"``).

    Returns
    -------
    BtfStore

    Raises
    ------
    FileNotFoundError
        Nothing at ``path``.
    BtfStoreError
        Not a Zarr v3 group, not a ``btf-texture`` store, another schema version, resampled
        (with ``ingested_only``), unfinished, or ``btf``/``light_dir``/``view_dir`` missing or not
        fitting together: the first of these, naming the store and the fix.
    """
    if mode not in ("r", "r+"):
        raise ValueError(f"mode must be 'r' or 'r+', got {mode!r}; create stores with create_btf_store")
    if not is_url(path) and not os.path.exists(os.fspath(path)):
        raise FileNotFoundError(f"{path} does not exist; give a BTF store written by {produced_by}")
    try:
        group = zarr.open_group(store_arg(path), mode=mode, zarr_format=3)
    except (FileNotFoundError, ValueError, TypeError) as exc:
        raise BtfStoreError(path, f"{path} is not a Zarr v3 group ({exc}); give a BTF store written by "
                                  f"{produced_by}") from None
    attrs = dict(group.attrs)
    if attrs.get("schema") != SCHEMA_NAME:
        raise BtfStoreError(path, f"{path} is not a BTF store (schema {attrs.get('schema')!r}, expected "
                                  f"{SCHEMA_NAME!r}); give the output of {produced_by}")
    if attrs.get("schema_version", SCHEMA_VERSION) != SCHEMA_VERSION:
        raise BtfStoreError(path, f"{path}: BTF store of schema version {attrs['schema_version']!r}; this code "
                                  f"reads {SCHEMA_NAME} {SCHEMA_VERSION}: use the btf-pipeline version that wrote "
                                  f"it or write it again with {produced_by}")
    store = BtfStore(path, mode, group=group)
    if ingested_only is not None:
        store.require_ingested(ingested_only)
    if require_complete and not attrs.get("complete"):
        raise BtfStoreError(path, f"{path} is an unfinished BTF store (attribute complete is false); finish "
                                  f"{produced_by} into it first (run it again with the same --out to resume)")
    store.check_arrays(produced_by)
    return store


class BtfStore:
    """An opened BTF store.

    Use :func:`open_btf_store` or :func:`create_btf_store` rather than the constructor, which
    checks nothing (the workers of a stage reopen the store their driver checked this way).

    Attributes
    ----------
    path : str
        Store path or URL.
    mode : {"r", "r+"}
    group : zarr.Group
        The root group.
    """

    def __init__(self, path: str | os.PathLike, mode: str = "r", *, group: zarr.Group | None = None) -> None:
        self.path = str(path) if is_url(path) else os.fspath(path)
        self.mode = mode
        self.group = group if group is not None else zarr.open_group(store_arg(path), mode=mode, zarr_format=3)

    def __repr__(self) -> str:
        return (f"BtfStore({self.path!r}, mode={self.mode!r}, btf={self.btf.shape}, kind={self.kind!r}, "
                f"complete={self.complete})")

    def check_arrays(self, produced_by: str = PRODUCERS) -> None:
        """``btf``, ``light_dir`` and ``view_dir`` are there and fit together, the directions finite.

        Raises
        ------
        BtfStoreError
            Naming the arrays and the fix.
        """
        missing = [name for name in READ_ARRAYS if name not in self.group]
        if missing:
            raise BtfStoreError(self.path, f"{self.path}: arrays {missing} are missing; write the store again with "
                                           f"{produced_by} into a new --out")
        btf, light, view = self.btf, self.group["light_dir"], self.group["view_dir"]
        if btf.ndim != 4 or btf.shape[3] != 3 or light.shape != (btf.shape[0], 3) or view.shape != light.shape:
            raise BtfStoreError(self.path, f"{self.path}: btf {btf.shape}, light_dir {light.shape} and view_dir "
                                           f"{view.shape} do not fit ((n_lv, h, w, 3), (n_lv, 3), (n_lv, 3)); write "
                                           f"the store again with {produced_by} into a new --out")
        for name in ("light_dir", "view_dir"):          # small: every reader interpolates or exports them
            d = np.asarray(self.group[name][...])
            bad = np.flatnonzero(~np.isfinite(d).all(axis=1))
            if bad.size:
                raise BtfStoreError(self.path, f"{self.path}: {name}[{int(bad[0])}] = {d[bad[0]].tolist()} is not "
                                               f"finite ({bad.size} row(s) with NaN/Inf); write the store again with "
                                               f"{produced_by} into a new --out")

    def require_ingested(self, hint: str) -> None:
        """Refuse a store that ``btf ingest`` did not write (a resampled one), with the caller's ``hint``.

        Raises
        ------
        BtfStoreError
            ``"<path>: not the output of `btf ingest` (schema ..., resampled); <hint>"``.
        """
        if self.is_resampled:
            raise BtfStoreError(self.path, f"{self.path}: not the output of `btf ingest` (schema {SCHEMA_NAME!r}, "
                                           f"resampled); {hint}")

    def mark_complete(self, unit: str = "views") -> None:
        """Set ``complete`` once every resume marker is set.

        Raises
        ------
        RuntimeError
            Some ``unit`` (views, bands, target views) were not written.
        """
        if not self.written.all():
            raise RuntimeError(f"{self.path}: some {unit} were not written; re-run to resume")
        if not self.complete:
            self.group.attrs["complete"] = True

    # ---- arrays ---------------------------------------------------------------
    @property
    def btf(self) -> zarr.Array:
        """``(n_lv, h, w, 3)`` float32 textures (read lazily)."""
        return self.group["btf"]

    @property
    def light_dir(self) -> np.ndarray:
        """``(n_lv, 3)`` float64 unit light directions."""
        return np.asarray(self.group["light_dir"][...], dtype=np.float64)

    @property
    def view_dir(self) -> np.ndarray:
        """``(n_lv, 3)`` float64 unit view directions."""
        return np.asarray(self.group["view_dir"][...], dtype=np.float64)

    @property
    def lv_index(self) -> np.ndarray:
        """``(n_lv, len(lv_order))`` int: each row's index along the axes of ``lv_order``."""
        return self.group["lv_index"][...]

    @property
    def roi(self) -> zarr.Array | None:
        """``(n_lv, rows, cols, 3)`` float32 HDR radiance regions of interest before rectification (read
        lazily; ``btf ingest --keep-roi``), or ``None`` when the store has none."""
        return self.group["roi"] if "roi" in self.group else None

    @property
    def homography(self) -> np.ndarray | None:
        """``(n_turn, n_cam, 3, 3)`` float64: sample-plane metres -> :attr:`roi` pixel ``(col, row, 1)``
        of each view, or ``None`` when the store has no regions of interest."""
        return np.asarray(self.group["homography"][...], dtype=np.float64) if "homography" in self.group else None

    @property
    def written(self) -> np.ndarray:
        """The resume markers (read fresh)."""
        return self.group["written"][...]

    # ---- attributes -------------------------------------------------------------
    @property
    def attrs(self) -> dict[str, Any]:
        """The root attributes (read fresh)."""
        return dict(self.group.attrs)

    @property
    def complete(self) -> bool:
        return self.group.attrs.get("complete") is True

    @property
    def n_lv(self) -> int:
        return int(self.btf.shape[0])

    @property
    def texture_shape(self) -> tuple[int, int]:
        return int(self.btf.shape[1]), int(self.btf.shape[2])

    @property
    def units(self) -> str | None:
        return self.group.attrs.get("units")

    @property
    def is_resampled(self) -> bool:
        return "resampled_from" in self.group.attrs

    @property
    def is_reconstructed(self) -> bool:
        return "reconstruct_hash" in self.group.attrs

    @property
    def is_imported(self) -> bool:
        """Written by ``btf import-btf`` from a Bonn BTF file (attribute ``imported_from``)."""
        return "imported_from" in self.group.attrs

    @property
    def kind(self) -> str:
        """``"resampled"``, ``"reconstructed"``, ``"imported"`` or ``"ingested"``: which stage wrote it."""
        return ("resampled" if self.is_resampled else "reconstructed" if self.is_reconstructed
                else "imported" if self.is_imported else "ingested")

    @property
    def content_key(self) -> str | None:
        """What identifies the content: its ingest hash (or, resampled, its resample hash; super-resolved,
        its superres hash; imported from a Bonn file, its import hash)."""
        attrs = self.group.attrs
        return (attrs.get("ingest_hash") or attrs.get("resample_hash") or attrs.get("superres_hash")
                or attrs.get("import_hash"))


# --------------------------------------------------------------------------- validating


def validate_btf_store(path: str | os.PathLike, *, require_complete: bool = True) -> list[Problem]:
    """Check a BTF store against the schema and list every problem (``btf validate``).

    Reads the attributes and the small arrays (never ``btf`` itself).

    Parameters
    ----------
    path : str or path-like
        Store directory or fsspec URL.
    require_complete : bool
        Report an unfinished store (``complete`` false, markers not all set) as a problem.

    Returns
    -------
    list of Problem
        Empty when the store is valid. Content problems never raise.
    """
    if not is_url(path) and not os.path.exists(os.fspath(path)):
        return [Problem(WHOLE_STORE, None, "a BTF store directory", f"nothing at {os.fspath(path)!r}",
                        "check the path, or write the store (`btf ingest`)")]
    try:
        group = zarr.open_group(store_arg(path), mode="r", zarr_format=3)
    except Exception as e:  # noqa: BLE001 - any failure to open is one problem
        return [Problem(WHOLE_STORE, None, "a Zarr v3 group (zarr.json with node_type 'group')",
                        f"{type(e).__name__}: {e}", "this is not a BTF store; check the path")]
    attrs = dict(group.attrs)
    if attrs.get("schema") != SCHEMA_NAME:
        return [Problem(ROOT_ATTRS, "schema", repr(SCHEMA_NAME), repr(attrs.get("schema")),
                        f"this is not a BTF store; give the output of {PRODUCERS}")]
    problems = _attr_problems(attrs)
    data = _small_arrays(group, problems)
    _shape_problems(group, attrs, data, problems)
    _roi_problems(group, attrs, problems)
    _marker_problems(attrs, data.get("written"), problems, require_complete=require_complete)
    return problems


def _attr_problems(attrs: Mapping[str, Any]) -> list[Problem]:
    """Root attributes: present, of the schema's version, ``texture_shape`` and ``lv_order`` well-formed."""
    rewrite = f"write the store again with {PRODUCERS}"
    problems = root_attr_problems(attrs, REQUIRED_ATTRS, SCHEMA_NAME, SCHEMA_VERSION, rewrite)
    if not any(attrs.get(key) for key in CONTENT_KEYS):
        problems.append(Problem(ROOT_ATTRS, "ingest_hash", f"one of {list(CONTENT_KEYS)}", "none",
                                f"the writing stage records what the store holds; {rewrite}"))
    ts = attrs.get("texture_shape")
    if "texture_shape" in attrs and not (isinstance(ts, list) and len(ts) == 2
                                         and all(isinstance(v, int) and v > 0 for v in ts)):
        problems.append(Problem(ROOT_ATTRS, "texture_shape", "[h, w], two positive integers", repr(ts), rewrite))
    order = attrs.get("lv_order")
    if "lv_order" in attrs and order not in (LV_ORDER, RESAMPLED_LV_ORDER):
        problems.append(Problem(ROOT_ATTRS, "lv_order", f"{LV_ORDER!r} or {RESAMPLED_LV_ORDER!r}", repr(order),
                                rewrite))
    if "complete" in attrs and not isinstance(attrs["complete"], bool):
        problems.append(Problem(ROOT_ATTRS, "complete", "true or false", repr(attrs["complete"]), rewrite))
    return problems


def _small_arrays(group: zarr.Group, problems: list[Problem]) -> dict[str, np.ndarray]:
    """The schema's arrays other than ``btf``, read (a chunk that does not read back is a problem)."""
    data: dict[str, np.ndarray] = {}
    for name in ARRAYS:
        node = group.get(name)
        if node is None:
            problems.append(Problem(name, None, f"array {name!r} {ARRAYS[name][1]}", "nothing",
                                    f"the store is incomplete; write it again with {PRODUCERS}"))
        elif not isinstance(node, zarr.Array):
            problems.append(Problem(name, None, "an array", "a group", f"write the store again with {PRODUCERS}"))
        elif name != "btf":
            try:
                data[name] = np.asarray(node[...])
            except CorruptChunkError as e:             # a checksum mismatch / truncated chunk: named, not raised
                problems.append(Problem(name, f"chunk {e.chunk}", "a chunk that reads back as written",
                                        e.problem, e.hint))
    return data


def _shape_problems(group: zarr.Group, attrs: Mapping[str, Any], data: Mapping[str, np.ndarray],
                    problems: list[Problem]) -> None:
    """``btf`` against ``texture_shape``; directions and ``lv_index`` against ``btf``'s rows."""
    rewrite = f"write the store again with {PRODUCERS}"
    btf = group.get("btf")
    if not isinstance(btf, zarr.Array):
        return
    ts = attrs.get("texture_shape")
    if str(btf.dtype) != "float32":
        problems.append(Problem("btf", None, "dtype float32", f"dtype {btf.dtype}", rewrite))
    if btf.ndim != 4 or btf.shape[3] != 3:
        problems.append(Problem("btf", None, "shape (n_lv, h, w, 3)", f"shape {btf.shape}", rewrite))
        return
    if isinstance(ts, list) and list(btf.shape[1:3]) != ts:
        problems.append(Problem("btf", "axes 1, 2 (tex_row, tex_col)", f"texture_shape {ts}",
                                f"{list(btf.shape[1:3])}", rewrite))
    n_lv = btf.shape[0]
    tcl = attrs.get("turntable_cameras_leds")
    if isinstance(tcl, list) and len(tcl) == 3 and int(np.prod(tcl)) != n_lv:
        problems.append(Problem(ROOT_ATTRS, "turntable_cameras_leds", f"a product of {n_lv} (btf rows)",
                                repr(tcl), rewrite))
    for name in ("light_dir", "view_dir"):
        d = data.get(name)
        if d is None:
            continue
        if d.shape != (n_lv, 3):
            problems.append(Problem(name, None, f"shape ({n_lv}, 3) to match btf", f"shape {d.shape}", rewrite))
            continue
        norm = np.linalg.norm(d, axis=1)
        bad = np.flatnonzero(~np.isfinite(norm) | (np.abs(norm - 1) > UNIT_TOL))
        if len(bad):
            problems.append(Problem(name, f"lv {', '.join(map(str, bad[:10].tolist()))}",
                                    "finite unit vectors in the sample frame", f"{len(bad)} other row(s)", rewrite))
    index = data.get("lv_index")
    order = attrs.get("lv_order")
    if index is not None and isinstance(order, list):
        if index.dtype.kind not in "iu" or index.shape != (n_lv, len(order)):
            problems.append(Problem("lv_index", None, f"integers of shape ({n_lv}, {len(order)}) (lv_order {order})",
                                    f"{index.dtype} {index.shape}", rewrite))


def _roi_problems(group: zarr.Group, attrs: Mapping[str, Any], problems: list[Problem]) -> None:
    """``roi`` and ``homography`` (``btf ingest --keep-roi``), when present or promised by ``keep_roi``:
    both there, ``roi`` ``(n_lv, rows, cols, 3)`` float32 with ``roi_shape`` ``[rows, cols]``,
    ``homography`` ``(n_turn, n_cam, 3, 3)`` of ``turntable_cameras_leds`` and finite."""
    rewrite = "write the store again with `btf ingest --keep-roi` into a new --out"
    present = {name: group.get(name) for name in ROI_ARRAYS}
    if not attrs.get("keep_roi") and all(node is None for node in present.values()):
        return
    for name, node in present.items():
        if not isinstance(node, zarr.Array):
            problems.append(Problem(name, None, f"array {name!r} {ROI_ARRAYS[name][1]} (a store with regions of "
                                                "interest)", "nothing" if node is None else "a group", rewrite))
    roi, homography, btf = present["roi"], present["homography"], group.get("btf")
    roi_shape = attrs.get("roi_shape")
    if isinstance(roi, zarr.Array):
        n_lv = btf.shape[0] if isinstance(btf, zarr.Array) else roi.shape[0]
        rows_cols = list(roi_shape) if isinstance(roi_shape, list) and len(roi_shape) == 2 else ["rows", "cols"]
        if str(roi.dtype) != "float32" or roi.ndim != 4 or roi.shape[0] != n_lv or roi.shape[3] != 3 or \
                list(roi.shape[1:3]) != rows_cols:
            problems.append(Problem("roi", None, f"float32 of shape ({n_lv}, {rows_cols[0]}, {rows_cols[1]}, 3) "
                                                 "(btf's rows, attribute roi_shape)", f"{roi.dtype} {roi.shape}",
                                    rewrite))
    if isinstance(homography, zarr.Array):
        tcl = attrs.get("turntable_cameras_leds")
        want = (tuple(tcl[:2]) if isinstance(tcl, list) and len(tcl) == 3 else ("n_turn", "n_cam")) + (3, 3)
        if homography.shape != want or str(homography.dtype) != "float64":
            problems.append(Problem("homography", None, f"float64 of shape {want} (turntable_cameras_leds)",
                                    f"{homography.dtype} {homography.shape}", rewrite))
        else:
            try:
                finite = bool(np.isfinite(homography[...]).all())
            except CorruptChunkError as e:
                problems.append(Problem("homography", f"chunk {e.chunk}", "a chunk that reads back as written",
                                        e.problem, e.hint))
                finite = True
            if not finite:
                problems.append(Problem("homography", None, "finite values", "NaN or infinity", rewrite))


def _marker_problems(attrs: Mapping[str, Any], written: np.ndarray | None, problems: list[Problem], *,
                     require_complete: bool) -> None:
    """``written``: 0 or 1, all set in a complete store; an unfinished store, when it must be complete."""
    resume = "run the command that writes the store again with the same --out to resume"
    if written is not None:
        bad = ~np.isin(written, (0, 1))
        if bad.any():
            problems.append(Problem("written", None, "0 or 1", f"{int(bad.sum())} other value(s)",
                                    f"the resume markers are corrupt; write the store again with {PRODUCERS}"))
        elif attrs.get("complete") is True and not (written == 1).all():
            problems.append(Problem("written", None, "every marker set (the store is marked complete)",
                                    f"{int((written != 1).sum())} of {written.size} not set", resume))
    if require_complete and attrs.get("complete") is False:
        problems.append(Problem(ROOT_ATTRS, "complete", "true", "false", resume))
