"""Bonn BTF file (DFMF, FMF, BDI, PVF) -> btf-texture store, streamed with bounded memory
(docs/bonn-formats.md, "Importing (btf import-btf)").

:func:`check_import` parses the file's header and body layout (the readers of this package are
lazy: their factor arrays are ``np.memmap`` views checked against the file size, nothing is
decoded), hashes the file and decides where the store is written, all before any cluster starts.
:func:`import_btf` then creates the store (:func:`tasks.stores.btf.create_btf_store`: rows
view-major, light fastest, ``lv_order`` :data:`~tasks.stores.btf.RESAMPLED_LV_ORDER`, the file's
row ``l + n_l v`` is store row ``l + n_l v``) and decodes it as Dask tasks, one per group of views
x band of texture rows (for BDI: all views x one band, the file's own unit). A task reads only
its rows of ``U`` and, a block of texels at a time, its texels of ``SxV`` from the memory maps,
decodes them (:func:`btfcore.bonn.decode_textures`, :func:`btfcore.bonn.decode_colour`,
:func:`btfcore.bonn.restore_dynamic_range`), writes whole chunks of ``btf`` and then their ``written``
markers (one per chunk: ``(n_v, n_bands)``). A killed import resumes the chunks not marked; a
finished output is replaced (``overwrite``) only by a complete one built beside it
(:mod:`tasks.staging`), exactly like ``btf resample``.

:func:`bonn_dask_array` is the same decoding as a lazy Dask array over the file.
"""

from __future__ import annotations

import hashlib
import math
import mmap
import os
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from btfcore.bonn import decode_colour, decode_textures, restore_dynamic_range
from tasks.compute import run_all
from tasks.faults import kill_point
from tasks.staging import (
    check_output_location,
    commit_staged,
    output_refusal,
    refuse_inputs_as_outputs,
    staged_target,
    store_attrs,
)
from tasks.stores.btf import (
    RESAMPLED_LV_ORDER,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    BtfStore,
    band_rows,
    create_btf_store,
)
from tasks.stores.common import json_key

__all__ = [
    "BLOCK_BYTES",
    "DECODER_VERSION",
    "TASK_BYTES",
    "ImportPlan",
    "NonFiniteValueError",
    "bonn_dask_array",
    "check_import",
    "decode_rows",
    "file_sha256",
    "import_block",
    "import_btf",
    "import_hash",
    "open_bonn",
]

#: Version of the decoding (readers + decode formulas): part of ``import_hash``, so that a store
#: decoded by other code is not resumed or taken for this import. Change it when decoded values change.
DECODER_VERSION = "bonn-import/1"
#: Bytes of output chunks one import task holds at most (fewer on workers with a small memory limit).
TASK_BYTES = 64 << 20
#: Bytes of factor texels (as float32) and of decoded values one decoding step holds at most.
BLOCK_BYTES = 8 << 20
#: Read size of the file hash.
_HASH_BLOCK = 8 << 20
#: Formats by :data:`tasks.bonn.header.SIGNATURES` value -> the reader that opens them.
FACTORISED = ("dfmf", "fmf", "fmf12")


class NonFiniteValueError(ValueError):
    """A decoded value that is NaN or infinite: names the file, the row (view, light) and the texel.

    Parameters
    ----------
    message : str
        The whole message (it starts with the file).
    """

    def __reduce__(self):  # picklable across Dask process boundaries
        return (type(self), (self.args[0],))


# --------------------------------------------------------------------------- opening a file


def _format_of(path: str | os.PathLike) -> tuple[str, str]:
    """``(format, signature)`` of a Bonn file, from its first bytes (:func:`tasks.bonn.header.read_signature`)."""
    from tasks.bonn.header import SIGNATURES, open_reader, read_signature

    with open_reader(path) as reader:
        signature = read_signature(reader)
    return SIGNATURES[signature], signature


def _open(path: str, fmt: str) -> Any:
    """The lazy reader object of a Bonn file of format ``fmt``."""
    if fmt in FACTORISED:
        from tasks.bonn.dfmf import read_factorised
        return read_factorised(path)
    if fmt == "bdi":
        from tasks.bonn.bdi import read_bdi
        return read_bdi(path)
    if fmt == "pvf":
        from tasks.bonn.pvf import read_pvf
        return read_pvf(path)
    raise ValueError(f"{path}: format {fmt!r} cannot be imported; give a DFMF, FMF, BDI or PVF file")


#: Readers opened in this process: ``(path, size, mtime_ns) -> (format, reader)``; a few, since each
#: holds memory maps of its file (pages are released after every block, :func:`_release_pages`).
_OPENED: OrderedDict[tuple, tuple[str, Any]] = OrderedDict()
_MAX_OPENED = 4


def _stamp(path: str | os.PathLike) -> tuple[str, int, int]:
    st = os.stat(path)
    return os.path.abspath(os.fspath(path)), int(st.st_size), int(st.st_mtime_ns)


def open_bonn(path: str | os.PathLike) -> tuple[str, Any]:
    """Open a Bonn BTF file lazily: ``(format, reader)``, cached per process by path, size and mtime.

    Parameters
    ----------
    path : path-like
        A DFMF, FMF, BDI or PVF file.

    Returns
    -------
    format : str
        ``"dfmf"``, ``"fmf"``, ``"fmf12"``, ``"bdi"`` or ``"pvf"``.
    reader : object
        :class:`tasks.bonn.dfmf.Factorised`, :class:`tasks.bonn.bdi.Bdi` or the PVF reader; its
        large arrays are memory maps, nothing is decoded.

    Raises
    ------
    FileNotFoundError
        Nothing at ``path``.
    tasks.bonn.errors.BonnFormatError
        The file does not parse (names the byte offset and field).
    """
    key = _stamp(path)
    if key in _OPENED:
        _OPENED.move_to_end(key)
        return _OPENED[key]
    fmt, _ = _format_of(path)
    opened = (fmt, _open(key[0], fmt))
    _OPENED[key] = opened
    while len(_OPENED) > _MAX_OPENED:
        _OPENED.popitem(last=False)
    return opened


def _release_pages(arrays: Any) -> None:
    """Drop the resident pages of the memory maps behind ``arrays`` from this process (``MADV_DONTNEED``).

    File pages a task touched through a memory map count in its resident set until they are
    unmapped; a worker's memory limit is enforced on the resident set. The pages stay in the
    page cache, so a later read is not a disk read.
    """
    seen: set[int] = set()
    stack = list(arrays)
    while stack:
        a = stack.pop()
        if isinstance(a, (list, tuple)):
            stack.extend(a)
            continue
        mm = getattr(a, "_mmap", None)
        base = a
        while mm is None and getattr(base, "base", None) is not None:
            base = base.base
            mm = base if isinstance(base, mmap.mmap) else getattr(base, "_mmap", None)
        if isinstance(mm, mmap.mmap) and id(mm) not in seen and hasattr(mm, "madvise"):
            seen.add(id(mm))
            try:
                mm.madvise(mmap.MADV_DONTNEED)
            except (OSError, ValueError):   # closed map, or a platform without it
                pass


def _channels(path: str, fmt: str, reader: Any) -> int:
    if fmt in FACTORISED:
        return len(reader.U)
    return int(reader.header.n_channels)


# --------------------------------------------------------------------------- decoding


def _factorised_rows(path: str, fact: Any, rows: np.ndarray, y0: int, y1: int,
                     block_bytes: int = BLOCK_BYTES) -> np.ndarray:
    """Decode file rows ``rows`` x texture rows ``y0:y1`` of a DFMF/FMF file to linear RGB.

    Reads ``U[c][rows]`` once and ``SxV[c]`` a block of texels at a time (at most ``block_bytes``
    of factor texels as float32 and of decoded values), releasing the mapped pages after each block.
    Each block of ``SxV`` is copied to an aligned float32 array first: the factors of a Bonn file lie
    at odd byte offsets, and GEMMs on unaligned memory maps run off BLAS (2-3x slower, measured).
    """
    w = int(fact.header.width)
    n_rows = len(rows)
    U = [np.asarray(u[rows], dtype=np.float32) for u in fact.U]       # (n_rows, K_c), small
    unique = {id(s): s for s in fact.SxV}                               # FMF: one SxV for all channels
    k_sum = sum(max(1, int(s.shape[1])) for s in unique.values())
    step = max(1, min(block_bytes // (4 * k_sum), block_bytes // (12 * max(1, n_rows))))
    t0, t1 = y0 * w, y1 * w
    out = np.empty((n_rows, t1 - t0, 3), dtype=np.float32)
    buf = np.empty((n_rows, min(step, t1 - t0), 3), dtype=np.float32)
    try:
        for s0 in range(t0, t1, step):
            s1 = min(t1, s0 + step)
            block = {key: np.array(s[s0:s1], dtype=np.float32) for key, s in unique.items()}
            decoded = decode_textures(U, [block[id(s)] for s in fact.SxV], slice(None), out=buf[:, :s1 - s0])
            decoded = decode_colour(decoded, fact.colour_model, fact.colour_mean, fact.colour_matrix)
            if fact.dynamic_range_reduced:                  # after the colour model, as btflib
                decoded = restore_dynamic_range(decoded)
            out[:, s0 - t0:s1 - t0] = decoded
            del block
            _release_pages(fact.SxV)
    finally:
        _release_pages(fact.SxV)
        _release_pages(fact.U)
    return out.reshape(n_rows, y1 - y0, w, 3)


def _pvf_rows(path: str, pvf: Any, rows: np.ndarray, y0: int, y1: int) -> np.ndarray:
    """Decode file rows x texture rows ``y0:y1`` of a PVF file (:meth:`tasks.bonn.pvf.Pvf.decode_rows`:
    each view's weights and components of these texels only), then drop the mapped pages."""
    w = int(pvf.header.width)
    try:
        data = pvf.decode_rows(rows, slice(y0 * w, y1 * w))              # (n_rows, band texels, 3)
    finally:
        _release_pages([(slot.Cs, slot.Ws) for slot in pvf.slots])
    return np.ascontiguousarray(data, dtype=np.float32).reshape(len(rows), y1 - y0, w, 3)


def decode_rows(path: str | os.PathLike, rows: np.ndarray | slice, y0: int, y1: int) -> np.ndarray:
    """Decode file rows ``rows`` (``l + n_l v``) x texture rows ``y0:y1`` of a Bonn file to linear RGB.

    Parameters
    ----------
    path : path-like
        A DFMF, FMF, BDI or PVF file (opened through :func:`open_bonn`).
    rows : (n,) ndarray of int or slice
        File rows, in the order wanted.
    y0, y1 : int
        Texture rows ``y0 <= y < y1``, full width.

    Returns
    -------
    (n, y1 - y0, w, 3) ndarray of float32
        The file's values, decoded (factor product, colour model to linear RGB, then the
        dynamic range restored where an FMF12 header says so); no cosine division or
        multiplication. Memory: the result plus one block of :data:`BLOCK_BYTES` (BDI: the
        file's chunks covering ``y0:y1``, all rows).
    """
    path = os.fspath(path)
    fmt, reader = open_bonn(path)
    header = reader.header
    n_lv = header.n_lv
    rows = np.arange(n_lv)[rows] if isinstance(rows, slice) else np.asarray(rows, dtype=np.int64).reshape(-1)
    if fmt in FACTORISED:
        return _factorised_rows(path, reader, rows, int(y0), int(y1))
    if fmt == "bdi":
        data = reader.read_texture_rows(int(y0), int(y1))        # (n_lv, y1 - y0, w, n_ch)
        if len(rows) == n_lv and np.array_equal(rows, np.arange(n_lv)):
            return data                                            # every row: no copy
        return np.ascontiguousarray(data[rows], dtype=np.float32)
    return _pvf_rows(path, reader, rows, int(y0), int(y1))


def _raise_nonfinite(path: str, data: np.ndarray, rows: np.ndarray, n_l: int, y0: int) -> None:
    """Name the first NaN/Inf of decoded ``data`` ``(n, band, w, 3)`` by file row (view, light) and texel."""
    finite = np.isfinite(data)
    if finite.all():
        return
    bad = int(np.count_nonzero(~finite))
    i, y, x, c = (int(v) for v in np.unravel_index(int(np.argmin(finite)), data.shape))
    row = int(rows[i])
    v, l = divmod(row, n_l)
    raise NonFiniteValueError(
        f"{path}: decoded value {float(data[i, y, x, c])!r} at row {row} (view {v}, light {l}), texel "
        f"(x {x}, y {y0 + y}) = index {x + data.shape[2] * (y0 + y)}, channel {c} ({bad} non-finite value(s) "
        "in this block): the file's factors hold NaN/Inf or overflow their precision; the file is damaged or "
        "was written wrongly, so export it again from its source")


# --------------------------------------------------------------------------- planning


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file, read in blocks of 8 MiB into one reused buffer (cached per process by
    path, size and mtime, so the preflight and the import hash a file once)."""
    key = _stamp(path)
    if key in _HASHES:
        return _HASHES[key]
    h = hashlib.sha256()
    buf = bytearray(_HASH_BLOCK)
    view = memoryview(buf)
    with open(path, "rb", buffering=0) as f:
        while n := f.readinto(buf):
            h.update(view[:n])
    _HASHES[key] = h.hexdigest()
    return _HASHES[key]


_HASHES: dict[tuple, str] = {}


def import_hash(sha256: str) -> str:
    """What an imported store depends on: the file's SHA-256, :data:`DECODER_VERSION` and the schema."""
    payload = {"file_sha256": sha256, "decoder": DECODER_VERSION, "schema": f"{SCHEMA_NAME}/{SCHEMA_VERSION}"}
    return json_key(payload)


def _plain(value: Any) -> Any:
    """numpy values -> JSON-able Python values (lists for arrays)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    return value


def _bonn_attrs(fmt: str, reader: Any) -> dict[str, Any]:
    """Every header field of the file (and the body's layout) as JSON for the ``bonn`` attribute."""
    hd = reader.header
    attrs: dict[str, Any] = {
        "signature": hd.signature, "version": int(hd.version), "measurement_setup": hd.measurement_setup,
        "image_sensor": hd.image_sensor, "light_source": hd.light_source, "ppmm": float(hd.ppmm),
        "rgb_scale_factor": [float(v) for v in hd.rgb_scale_factor], "cosine_flag": bool(hd.cosine_flag),
        "xml": hd.xml, "channel_names": list(hd.channel_names), "width": int(hd.width), "height": int(hd.height),
        "n_views": int(hd.n_v), "n_lights": int(hd.n_l),
        "n_rot": None if hd.rotations is None else int(len(hd.rotations)),
        "rotations": None if hd.rotations is None else np.asarray(hd.rotations, dtype=np.float64).tolist(),
    }
    if fmt in FACTORISED:
        attrs.update({
            "colour_model": int(reader.colour_model),
            "colour_mean": np.asarray(reader.colour_mean, dtype=np.float64).tolist(),
            "colour_matrix": np.asarray(reader.colour_matrix, dtype=np.float64).tolist(),
            "components": [int(u.shape[1]) for u in reader.U],
            "scalar_size": int(reader.scalar_size),
            "dynamic_range_reduced": bool(reader.dynamic_range_reduced),
            "height_map_shape": None if reader.height_map is None else list(np.shape(reader.height_map)),
        })
    elif fmt == "bdi":
        attrs.update({"lines_per_chunk": int(reader.lines_per_chunk), "compression": int(reader.compression),
                      "mask_present": int(np.count_nonzero(reader.mask))})
    elif fmt == "pvf":
        attrs.update({"orientation": reader.orientation, "legacy": bool(reader.legacy),
                      "components": [int(slot.Cs.shape[1]) for slot in reader.slots],
                      "scalar_size": int(reader.slots[0].scalar_size) if reader.slots else None})
    return _plain(attrs)


def _units(fmt: str, signature: str, cosine_flag: bool) -> str:
    cos = ("cosine flag set: the values have cos(theta_l) multiplied in; Bonn readers divide by it, this "
           "store does not" if cosine_flag else "cosine flag not set: no cos(theta_l) factor in the values")
    return f"as stored in {fmt.upper()} {signature} ({cos}), decoded to linear RGB"


@dataclass
class ImportPlan:
    """What :func:`check_import` found: the file, its layout and hash, and where the store goes.

    Attributes
    ----------
    source : str
        Absolute path of the file.
    format, signature : str
        ``"dfmf"``, ``"fmf"``, ``"fmf12"``, ``"bdi"`` or ``"pvf"``, and the signature string.
    n_v, n_l, height, width : int
        Views, lights per view, texture size.
    file_bytes : int
    file_sha256 : str
    key : str
        ``import_hash`` (:func:`import_hash`).
    out : Path
        The ``--out`` given.
    target : Path
        The store this import writes: ``out`` or its staging store ``X.partial.zarr``.
    staged : bool
        ``target`` is the staging store (an ``overwrite``, or its resumption).
    band : int
        Texture rows per chunk of ``btf``.
    hash_seconds : float
    """

    source: str
    format: str
    signature: str
    n_v: int
    n_l: int
    height: int
    width: int
    file_bytes: int
    file_sha256: str
    key: str
    out: Path
    target: Path
    staged: bool
    band: int
    hash_seconds: float
    stamp: tuple = field(repr=False, default=())

    @property
    def n_lv(self) -> int:
        return self.n_v * self.n_l

    @property
    def n_bands(self) -> int:
        return -(-self.height // self.band)


def _band(fmt: str, reader: Any, n_l: int, h: int, w: int) -> int:
    """Texture rows per chunk: about 4 MiB per view (:func:`tasks.stores.btf.band_rows`); for BDI the
    file's scan lines per chunk, so that every file chunk is decoded once."""
    if fmt == "bdi":
        return int(min(h, max(1, int(reader.lines_per_chunk))))
    return band_rows(n_l, h, w)


def check_import(source: str | os.PathLike, out: str | os.PathLike, overwrite: bool = False) -> ImportPlan:
    """Check everything about an import before any cluster starts; cheap but for hashing the file.

    Parses the file's header and body layout (the readers are lazy: their counts are checked
    against the file size, nothing is decoded), refuses what cannot be imported, hashes the file
    and decides the store to write (``out``, or its staging store when replacing or resuming a
    replacement: :func:`tasks.staging.staged_target`, keyed by ``import_hash``). A commit into
    ``out`` killed between its renames is finished first.

    Parameters
    ----------
    source : path-like
        A Bonn BTF file: DFMF (``!DFMF08FCR``), FMF (``!FMF12FCER``, ``!FMF06FC[R]``), BDI
        (``!BDIF06R2!``) or PVF.
    out : path-like
        The store to write (``--out``).
    overwrite : bool
        Replace a store of something else at ``out`` (only once the new one is complete).

    Returns
    -------
    ImportPlan

    Raises
    ------
    FileNotFoundError
        No file at ``source``.
    tasks.bonn.errors.BonnFormatError
        The file does not parse: names the file, byte offset and field.
    ValueError
        Not 3 colour channels (a spectral file), views with different light counts, an empty texture.
    FileExistsError
        ``out`` is or holds the source, or holds something else and not ``overwrite``.
    NotADirectoryError, PermissionError
        ``out`` cannot be created (:func:`tasks.staging.check_output_location`).
    """
    src = Path(source)
    if not src.is_file():
        raise FileNotFoundError(f"{source}: no such file; give a Bonn BTF file (DFMF, FMF, BDI or PVF)")
    out = Path(out)
    refuse_inputs_as_outputs({"--out": out}, {"FILE": src})
    check_output_location(out)
    fmt, reader = open_bonn(src)
    hd = reader.header
    try:
        n_l = int(hd.n_l)
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}; a btf-texture store needs the same lights for every view "
                         "(resample the BTF to one sampling first)") from None
    n_ch = _channels(str(src), fmt, reader)
    if n_ch != 3:
        raise ValueError(f"{source}: {n_ch} colour channels {list(hd.channel_names)}; a btf-texture store holds "
                         "linear RGB (3 channels): convert the spectral BTF to RGB first")
    if hd.n_v == 0 or n_l == 0 or hd.width == 0 or hd.height == 0:
        raise ValueError(f"{source}: empty BTF ({hd.n_v} views x {n_l} lights, {hd.width} x {hd.height} texels); "
                         "nothing to import")
    start = time.perf_counter()
    sha = file_sha256(src)
    hash_seconds = time.perf_counter() - start
    key = import_hash(sha)
    empty = out.is_dir() and not any(out.iterdir())
    refusal = lambda attrs: output_refusal(out, attrs, "import_hash", key,  # noqa: E731
                                           "imported BTF store", "another file or decoder version")
    target, staged = staged_target(out, "import_hash", key, overwrite or empty, refusal)
    signature = hd.signature
    return ImportPlan(source=str(src.resolve()), format=fmt, signature=signature, n_v=int(hd.n_v), n_l=n_l,
                      height=int(hd.height), width=int(hd.width), file_bytes=src.stat().st_size, file_sha256=sha,
                      key=key, out=out, target=Path(target), staged=staged,
                      band=_band(fmt, reader, n_l, int(hd.height), int(hd.width)),
                      hash_seconds=round(hash_seconds, 3), stamp=_stamp(src))


# --------------------------------------------------------------------------- the store


def _create_store(plan: ImportPlan, material: dict[str, str] | None) -> BtfStore:
    fmt, reader = open_bonn(plan.source)
    hd = reader.header
    n_v, n_l = plan.n_v, plan.n_l
    lv_index = np.stack(np.meshgrid(np.arange(n_v), np.arange(n_l), indexing="ij"), -1).reshape(-1, 2)
    small: dict[str, np.ndarray] = {
        "bonn_view_angles": np.asarray(hd.view_angles, dtype=np.float32),
        "bonn_light_angles": np.stack([np.asarray(a, dtype=np.float32) for a in hd.light_angles]),
    }
    if fmt in FACTORISED and reader.height_map is not None:
        small["height_map"] = np.asarray(reader.height_map, dtype=np.float32)
    if fmt == "bdi":
        small["bonn_mask"] = np.asarray(reader.mask, dtype=bool)
    attrs = {
        "units": _units(fmt, plan.signature, bool(hd.cosine_flag)),
        "lv_order": RESAMPLED_LV_ORDER, "views_lights": [n_v, n_l],
        # the rows as one turntable position of n_v cameras x n_l lights (the same row-major flattening),
        # which `btf build-db` and `btf reconstruct` read from every store they take
        "turntable_cameras_leds": [1, n_v, n_l],
        "import_hash": plan.key,
        "imported_from": {"path": plan.source, "sha256": plan.file_sha256, "bytes": plan.file_bytes,
                          "format": fmt, "signature": plan.signature, "decoder": DECODER_VERSION},
        "bonn": _bonn_attrs(fmt, reader),
        "material": material,
        "written_unit": "chunk: written[v, b] marks rows of view v x texture-row band b",
    }
    return create_btf_store(plan.target, attrs, light_dir=hd.light_dir(), view_dir=hd.view_dir(),
                            lv_index=lv_index.astype(np.int32), texture_shape=(plan.height, plan.width),
                            rows_per_chunk=n_l, band=plan.band, written_shape=(n_v, plan.n_bands), small=small)


def import_block(source: str, target: str, stamp: tuple, views: list[int], band_index: int, band: int,
                 block_bytes: int = BLOCK_BYTES) -> dict[str, Any]:
    """Decode views ``views`` x texture-row band ``band_index`` of a Bonn file into the store (one Dask task).

    Parameters
    ----------
    source : str
        The Bonn file.
    target : str
        The store being written (created by :func:`import_btf`).
    stamp : tuple
        ``(path, size, mtime_ns)`` of the file when the import was planned: a file changed since is
        refused (its store would mix two files).
    views : list of int
        Views whose chunk of this band is written (each ``(n_l, band, w, 3)``, one chunk).
    band_index, band : int
        Texture rows ``band_index * band`` up to ``(band_index + 1) * band`` (clipped to h).
    block_bytes : int
        Bytes of one decoding step (:func:`decode_rows`).

    Returns
    -------
    dict
        ``chunks`` written.

    Raises
    ------
    NonFiniteValueError
        A decoded value is NaN or infinite (nothing of this task is marked written).
    RuntimeError
        The file changed since the import was planned.
    """
    if _stamp(source) != tuple(stamp):
        raise RuntimeError(f"{source} changed while it was being imported (size or modification time); run "
                           "`btf import-btf` again (with --overwrite) to import the new file")
    fmt, reader = open_bonn(source)
    hd = reader.header
    n_l, h, w = int(hd.n_l), int(hd.height), int(hd.width)
    y0, y1 = band_index * band, min(h, (band_index + 1) * band)
    rows = (np.asarray(views, dtype=np.int64)[:, None] * n_l + np.arange(n_l)).reshape(-1)
    if fmt in FACTORISED:
        data = _factorised_rows(source, reader, rows, y0, y1, block_bytes)
    else:
        data = decode_rows(source, rows, y0, y1)
    _raise_nonfinite(source, data, rows, n_l, y0)
    store = BtfStore(target, "r+").group
    btf, written = store["btf"], store["written"]
    for i, v in enumerate(views):
        btf[v * n_l:(v + 1) * n_l, y0:y1] = data[i * n_l:(i + 1) * n_l]        # exactly one chunk
    del data
    kill_point("chunk-written")
    for v in views:
        written[v, band_index] = 1                                          # markers after the data
    return {"chunks": len(views)}


def _worker_budget(client: Any) -> tuple[int, int, int]:
    """``(task bytes, block bytes, worker threads)`` for the cluster behind ``client``: a task's chunks
    and a decoding block take at most 1/12 and 1/40 of the smallest worker memory limit (a worker
    process needs about 90 MiB before it runs anything, and Dask pauses a worker at 80 % of its limit)."""
    workers = client.scheduler_info().get("workers", {})
    limits = [int(w.get("memory_limit") or 0) for w in workers.values()]
    limits = [v for v in limits if v > 0]
    slots = max(1, sum(client.nthreads().values()))
    if not limits:
        return TASK_BYTES, BLOCK_BYTES, slots
    least = min(limits)
    return min(TASK_BYTES, least // 12), max(1 << 20, min(BLOCK_BYTES, least // 40)), slots


def _tasks(written: np.ndarray, plan: ImportPlan, task_bytes: int, slots: int) -> list[tuple[list[int], int]]:
    """``(views, band index)`` of the tasks that write the unmarked chunks: per band, groups of at most
    ``task_bytes`` of chunks (BDI: every unmarked view of the band in one task, the file's unit), and
    small enough that every worker thread gets a few."""
    chunk_bytes = plan.n_l * plan.band * plan.width * 12
    pending = int((written == 0).sum())
    per_task = max(1, min(task_bytes // max(1, chunk_bytes), math.ceil(pending / (3 * slots)) if pending else 1))
    out = []
    for b in range(plan.n_bands):
        views = [int(v) for v in np.flatnonzero(written[:, b] == 0)]
        if plan.format == "bdi":
            if views:
                out.append((views, b))
            continue
        out.extend((views[i:i + per_task], b) for i in range(0, len(views), per_task))
    return out


def import_btf(source: str | os.PathLike, out: str | os.PathLike, client: Any, *, overwrite: bool = False,
               material_class: str | None = None, material_id: str | None = None,
               on_progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Import a Bonn BTF file into a btf-texture store on a Dask cluster; resumes unfinished imports.

    Parameters
    ----------
    source : path-like
        DFMF, FMF, BDI or PVF file; never modified.
    out : path-like
        The store (docs/bonn-formats.md, "Importing (btf import-btf)"): ``btf`` ``(n_v n_l, h, w, 3)``
        float32, rows view-major with light fastest (file row ``l + n_l v``), ``lv_order``
        ``["view", "light"]``, chunks ``(n_l, band, w, 3)``, ``written`` ``(n_v, n_bands)``.
    client : distributed.Client
    overwrite : bool
        Replace the store at ``out`` (of another file, or this one: recomputed) once the new one is
        complete, built in ``X.partial.zarr`` beside it (:mod:`tasks.staging`). A staging store of this
        import is resumed with or without ``overwrite``.
    material_class, material_id : str, optional
        Written as attribute ``material`` ``{"material_id", "class"}`` (what ``btf build-db`` reads);
        ``material_id`` defaults to the file's stem when a class is given.
    on_progress : callable, optional
        ``on_progress(chunks_done, chunks_total)`` as tasks finish.

    Returns
    -------
    dict
        ``out``, ``rows``, ``views``, ``lights``, ``texture_shape``, ``format``, ``signature``,
        ``import_hash``, ``staged``, ``chunks``, ``chunks_written``, ``chunks_skipped`` (marked by an
        earlier run), ``views_resumed`` (views with some chunk from an earlier run), ``tasks``,
        ``file_bytes``, ``hash_seconds``, ``seconds``, ``mb_per_s`` (decoded output).

    Raises
    ------
    FileNotFoundError, ValueError, FileExistsError
        As :func:`check_import`.
    NonFiniteValueError
        A decoded value is NaN/Inf (file, row (view, light), texel); the store stays unfinished.
    """
    start = time.perf_counter()
    plan = check_import(source, out, overwrite)
    material = None
    if material_class is not None or material_id is not None:
        material = {"material_id": material_id or Path(source).stem, "class": material_class}
    attrs = store_attrs(plan.target) or {}
    store = BtfStore(plan.target, "r+") if attrs.get("import_hash") == plan.key else None
    if store is None:
        store = _create_store(plan, material)
    elif material is not None and store.attrs.get("material") != material:
        store.group.attrs["material"] = material
    written = store.written
    n_chunks = int(written.size)
    done_before = int(written.sum())
    views_resumed = int(((written == 1).any(axis=1)).sum())
    summary = {"out": str(plan.out), "rows": plan.n_lv, "views": plan.n_v, "lights": plan.n_l,
               "texture_shape": [plan.height, plan.width], "format": plan.format, "signature": plan.signature,
               "import_hash": plan.key, "staged": plan.staged, "chunks": n_chunks, "file_bytes": plan.file_bytes,
               "hash_seconds": plan.hash_seconds}
    tasks: list[tuple[list[int], int]] = []
    if not store.complete:
        task_bytes, block_bytes, slots = _worker_budget(client)
        tasks = _tasks(written, plan, task_bytes, slots)
        run_all(client, import_block, [(plan.source, str(plan.target), plan.stamp, views, b, plan.band, block_bytes)
                                       for views, b in tasks], on_progress, weights=[len(v) for v, _ in tasks])
        store.mark_complete("chunks (views x bands)")
    if plan.staged:
        commit_staged(plan.out, "import-btf")
    seconds = time.perf_counter() - start
    written_now = n_chunks - done_before if tasks else 0
    out_bytes = written_now * plan.n_l * plan.band * plan.width * 12
    return {**summary, "chunks_written": written_now, "chunks_skipped": n_chunks - written_now,
            "views_resumed": views_resumed if done_before < n_chunks else 0, "tasks": len(tasks),
            "seconds": round(seconds, 3), "mb_per_s": round(out_bytes / 1e6 / max(seconds, 1e-9), 1)}


# --------------------------------------------------------------------------- lazy Dask array


class _LazyBonn:
    """Array-like over a Bonn file for :func:`dask.array.from_array`: ``(n_lv, h, w, 3)`` float32,
    decoding on ``__getitem__`` only the rows and texture rows asked for. Pickles as its path."""

    ndim = 4
    dtype = np.dtype(np.float32)

    def __init__(self, path: str, shape: tuple[int, int, int, int]) -> None:
        self.path, self.shape = path, shape

    def __getitem__(self, key: Any) -> np.ndarray:
        key = key if isinstance(key, tuple) else (key,)
        key = key + (slice(None),) * (4 - len(key))
        n_lv, h = self.shape[:2]
        rows = np.arange(n_lv)[key[0]]
        ys = np.arange(h)[key[1]]
        scalar_row, scalar_y = np.ndim(rows) == 0, np.ndim(ys) == 0
        rows, ys = np.atleast_1d(rows), np.atleast_1d(ys)
        if len(rows) == 0 or len(ys) == 0:
            return np.zeros((len(rows), len(ys), self.shape[2], 3), np.float32)[
                (slice(None), slice(None), key[2], key[3])]
        y0, y1 = int(ys.min()), int(ys.max()) + 1
        data = decode_rows(self.path, rows, y0, y1)[:, ys - y0][(slice(None), slice(None), key[2], key[3])]
        if scalar_y:
            data = data[:, 0]
        if scalar_row:
            data = data[0]
        return data


def bonn_dask_array(path: str | os.PathLike) -> Any:
    """A lazy Dask array over a Bonn BTF file: ``(n_lv, h, w, 3)`` float32, decoded block by block.

    Rows are the file's (``l + n_l v``: view-major, light fastest), texels ``[y, x]`` of texel
    index ``x + w y`` (no flip), values the file's decoded to linear RGB exactly as
    :func:`import_btf` stores them. Nothing is decoded until a block is computed; a block reads
    only its rows of ``U`` and its texels of ``SxV`` from the memory-mapped file.

    Parameters
    ----------
    path : path-like
        DFMF, FMF, PVF or BDI file (the header is parsed now, lazily).

    Returns
    -------
    dask.array.Array
        Chunks ``(n_l, band, w, 3)``: one view x a band of about 4 MiB of texture rows
        (:func:`tasks.stores.btf.band_rows`); for BDI ``(n_lv, lines_per_chunk, w, 3)``, the file's
        own unit (every block of it holds all rows).

    Raises
    ------
    FileNotFoundError, tasks.bonn.errors.BonnFormatError
        As :func:`open_bonn`.
    """
    import dask.array as da

    path = os.path.abspath(os.fspath(path))
    fmt, reader = open_bonn(path)
    hd = reader.header
    n_l, n_v, h, w = int(hd.n_l), int(hd.n_v), int(hd.height), int(hd.width)
    band = _band(fmt, reader, n_l, h, w)
    rows = (n_v * n_l,) if fmt == "bdi" else (n_l,) * n_v
    bands = (band,) * (h // band) + ((h % band,) if h % band else ())
    name = "bonn-" + hashlib.sha256(repr((_stamp(path), DECODER_VERSION)).encode()).hexdigest()[:16]
    return da.from_array(_LazyBonn(path, (n_v * n_l, h, w, 3)), chunks=(rows, bands, (w,), (3,)), name=name,
                         asarray=False, fancy=False, lock=False, meta=np.empty((0, 0, 0, 0), np.float32))
