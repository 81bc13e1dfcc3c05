"""Chunk integrity: every chunk the pipeline writes carries a checksum, and a damaged one is named.

Every array of every store kind (capture, btf-texture, measurement, model,
resampled, reconstructed, evaluation) is created through :func:`create_array`,
which appends Zarr v3's ``crc32c`` codec to the array's bytes-to-bytes codecs.
A chunk file that was changed or truncated after it was written then fails to
decode instead of giving numbers.

Zarr's codec raises a bare ``ValueError`` without a location. Importing this
module installs :class:`LocatingCodecPipeline` as Zarr's codec pipeline (once
per process; ``tasks/__init__.py`` imports it, so every process that imports a
``tasks`` module, Dask workers included, has it): when a chunk fails to decode
it finds the chunk and raises :class:`CorruptChunkError`, which names the
store, the array and the chunk index, whatever stage or function read it.

:func:`read_chunk_rows`, :func:`read_chunk_windows` and :func:`write_chunks_directly` read and write the
chunk files of such an array directly where Zarr adds only copies (the writes past the page cache), with the
same bytes and checks.

:func:`verify_store` reads every chunk of every array of a store, one chunk at
a time, and lists corrupt, truncated and missing chunks (``btf validate
--deep``). A chunk is *missing* when the store's own resume markers
(``written``) say it was written but its file is gone (Zarr would return the
fill value for it); see :data:`WRITTEN_RULES`. With ``finite=True`` it also
counts the NaN and Inf values of every chunk of a float array it reads (no
array of any store kind may hold them), in the same single pass.

Examples
--------
>>> arr = create_array(group, "btf", shape=(16, 8, 8, 3), dtype="float32",   # doctest: +SKIP
...                    chunks=(16, 8, 8, 3), fill_value=0.0, compressors=None)
>>> verify_store("capture.zarr")                                               # doctest: +SKIP
[]
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import re
import uuid
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import zarr
from zarr.codecs import Crc32cCodec
from zarr.core.buffer import default_buffer_prototype
from zarr.core.codec_pipeline import BatchedCodecPipeline
from zarr.core.sync import sync

__all__ = [
    "CHECKSUM_NOTE",
    "ChunkProblem",
    "CorruptChunkError",
    "LocatingCodecPipeline",
    "WRITTEN_RULES",
    "checksummed",
    "chunk_files_exist",
    "create_array",
    "has_checksums",
    "missing_chunks",
    "missing_problem",
    "nonfinite_problem",
    "open_any_store",
    "read_chunk_rows",
    "read_chunk_windows",
    "rerun_hint",
    "store_kind",
    "stored_chunks",
    "unchecked_arrays",
    "verify_store",
]

#: What ``btf validate`` says about a store written before checksums were added.
CHECKSUM_NOTE = ("no chunk checksums (written before checksums were added); --deep can only check "
                 "readability (a truncated chunk), not a changed byte")

_DEFAULT_PIPELINE = "zarr.core.codec_pipeline.BatchedCodecPipeline"
_GENERIC_HINT = "re-run the stage that wrote it or restore the store from a backup"
_CHANGED = "checksum mismatch (the chunk file was changed after it was written)"


# --------------------------------------------------------------------------- creating arrays


def checksummed(compressors: Any = None) -> list[Any]:
    """Bytes-to-bytes codecs with a CRC32C checksum last.

    Parameters
    ----------
    compressors : None, codec or sequence of codecs
        What the array would be created with (``None``: uncompressed).

    Returns
    -------
    list
        ``[*compressors, Crc32cCodec()]`` (no second checksum if one is there already).
    """
    if isinstance(compressors, str):
        raise ValueError(f"compressors={compressors!r}: give the codecs (None for uncompressed)")
    if compressors is None:
        codecs: list[Any] = []
    elif isinstance(compressors, (list, tuple)):
        codecs = list(compressors)
    else:
        codecs = [compressors]
    if not any(isinstance(c, Crc32cCodec) for c in codecs):
        codecs.append(Crc32cCodec())
    return codecs


def create_array(group: zarr.Group, name: str, *, compressors: Any = None, **kwargs: Any) -> zarr.Array:
    """``group.create_array(name, ...)`` with a CRC32C checksum on every chunk.

    The one place where the pipeline creates arrays (docs/architecture.md, "Storage contract": one home
    per contract); every keyword is passed on to :meth:`zarr.Group.create_array`.

    Parameters
    ----------
    group : zarr.Group
        Group to create the array in.
    name : str
        Array name.
    compressors : None, codec or sequence of codecs
        Bytes-to-bytes codecs before the checksum (``None``: uncompressed).
    **kwargs
        ``shape``, ``dtype``, ``chunks``, ``fill_value``, ``dimension_names``, ``overwrite``, ...

    Returns
    -------
    zarr.Array
    """
    return group.create_array(name, compressors=checksummed(compressors), **kwargs)


def has_checksums(array: zarr.Array) -> bool:
    """Whether ``array``'s chunks carry a CRC32C checksum."""
    return any(isinstance(c, Crc32cCodec) for c in array.compressors)


# --------------------------------------------------------------------------- naming a damaged chunk


class CorruptChunkError(ValueError):
    """A chunk of a store is corrupt, truncated or missing.

    Parameters
    ----------
    store : str
        Store path or URL.
    array : str
        Array path inside the store, e.g. ``"raw"`` or ``"classes/stone/als/U"``.
    chunk : tuple of int or None
        Chunk index (``None`` when the chunk key could not be parsed).
    problem : str
        What is wrong, e.g. ``"checksum mismatch (...)"``.
    hint : str
        What to do.
    kind : {"corrupt", "truncated", "missing", "unreadable"}
        The problem's class.
    """

    def __init__(self, store: str, array: str, chunk: tuple[int, ...] | None, problem: str,
                 hint: str = _GENERIC_HINT, kind: str = "corrupt") -> None:
        self.store, self.array, self.chunk, self.problem, self.hint = str(store), array, chunk, problem, hint
        self.kind = kind
        where = f"chunk {chunk}" if chunk is not None else "a chunk"
        super().__init__(f"{self.store}: array {array}, {where}: {problem}; {hint}")

    def __reduce__(self):  # picklable across Dask / Prefect process boundaries
        return (type(self), (self.store, self.array, self.chunk, self.problem, self.hint, self.kind))


@dataclass(frozen=True)
class ChunkProblem:
    """One damaged chunk found by :func:`verify_store`.

    Attributes
    ----------
    store, array : str
        Store path and array path inside it.
    chunk : tuple of int
        Chunk index.
    kind : {"corrupt", "truncated", "missing", "unreadable", "nonfinite"}
    problem : str
        What is wrong, in words.
    hint : str
        What to do.
    """

    store: str
    array: str
    chunk: tuple[int, ...]
    kind: str
    problem: str
    hint: str

    def error(self) -> CorruptChunkError:
        """This problem as the exception a stage raises."""
        return CorruptChunkError(self.store, self.array, self.chunk, self.problem, self.hint, self.kind)

    def __str__(self) -> str:
        return str(self.error())


def _store_name(store: Any) -> str:
    root = getattr(store, "root", None)           # LocalStore
    if root is not None:
        return str(root)
    path = getattr(store, "path", None)           # FsspecStore
    return str(path) if path else str(store)


_KEY = re.compile(r"(?:(?P<array>.*)/)?c(?P<coords>(?:[./]\d+)*)")


def _parse_chunk_key(path: str) -> tuple[str, tuple[int, ...] | None]:
    """``"raw/c/0/1/3/0/0/0"`` -> ``("raw", (0, 1, 3, 0, 0, 0))``; unknown layouts: ``(path, None)``."""
    m = _KEY.fullmatch(path)
    if m is None:
        return path, None
    coords = tuple(int(x) for x in re.split(r"[./]", m["coords"])[1:])
    return m["array"] or "", coords


def _native_dtype(dtype: Any) -> np.dtype:
    to_native = getattr(dtype, "to_native_dtype", None)     # zarr >= 3.1: a ZDType
    return np.dtype(to_native() if to_native is not None else dtype)


def _diagnose(pipeline: BatchedCodecPipeline, n_bytes: int, spec: Any, exc: BaseException) -> tuple[str, str]:
    """``(kind, words)`` for a chunk of ``n_bytes`` that failed to decode with ``exc``."""
    try:
        size = int(np.prod(spec.shape)) * _native_dtype(spec.dtype).itemsize
        expected = pipeline.compute_encoded_size(size, spec)
    except Exception:  # noqa: BLE001 - a variable-size codec (compression): no expected size
        expected = None
    if expected is not None and n_bytes < expected:
        return "truncated", (f"truncated ({n_bytes} of {expected} bytes; the chunk file was cut short after it "
                             "was written)")
    if expected is not None and n_bytes > expected:
        return "corrupt", f"wrong size ({n_bytes} bytes, {expected} written)"
    if "checksum" in str(exc).lower():
        return "corrupt", _CHANGED
    return "unreadable", f"does not decode ({type(exc).__name__}: {exc})"


#: ``schema -> what to do`` for the kinds written by one command; see :func:`rerun_hint`.
_RERUN = {
    "btf-capture": "write the capture again (`btf simulate --overwrite` or `btf import-raw --overwrite`) or "
                   "restore the store from a backup",
    "btf-measurement": "re-run `btf ingest --overwrite` on the capture or restore the store from a backup",
    "btf-model": "re-run `btf build-db` into a fresh --out folder or restore the store from a backup",
}


def rerun_hint(attrs: dict[str, Any]) -> str:
    """What to do about a damaged chunk of a store with root attributes ``attrs``."""
    schema = attrs.get("schema")
    if schema in _RERUN:
        return _RERUN[schema]
    if schema == "btf-texture":
        if "resampled_from" in attrs:
            stage = "`btf resample --overwrite`"
        elif "reconstruction_of" in attrs or "kind" in attrs:
            stage = "`btf evaluate acquisition` into a fresh --out folder"
        elif "reconstruct_hash" in attrs:
            stage = "`btf reconstruct --overwrite`"
        elif "import_hash" in attrs:
            stage = "`btf import-btf --overwrite`"
        else:
            stage = "`btf ingest --overwrite`"
        return f"re-run {stage} or restore the store from a backup"
    return _GENERIC_HINT


async def _root_attrs(store: Any, prototype: Any) -> dict[str, Any]:
    try:
        buf = await store.get("zarr.json", prototype=prototype)
        return dict(json.loads(buf.to_bytes()).get("attributes") or {}) if buf is not None else {}
    except Exception:  # noqa: BLE001 - the hint is a courtesy; the location is what matters
        return {}


class LocatingCodecPipeline(BatchedCodecPipeline):
    """Zarr's batched codec pipeline, naming the chunk when one fails to decode.

    Reading is Zarr's own; only after a read fails is each chunk of the
    failed batch fetched and decoded again on its own, and the first one that
    fails becomes a :class:`CorruptChunkError` (store, array path, chunk
    index, truncated or changed). Errors that no single chunk reproduces
    (a full disk, a lost connection) are raised unchanged.
    """

    async def read_batch(self, batch_info: Iterable[tuple], out: Any, drop_axes: tuple[int, ...] = ()) -> None:
        batch_info = list(batch_info)
        try:
            await super().read_batch(batch_info, out, drop_axes)
        except (CorruptChunkError, OSError, MemoryError):
            raise
        except Exception as exc:
            located = await self._locate(batch_info)
            if located is None:
                raise
            raise located from exc

    async def _locate(self, batch_info: Sequence[tuple]) -> CorruptChunkError | None:
        for byte_getter, spec, *_ in batch_info:
            try:
                data = await byte_getter.get(prototype=spec.prototype)
            except Exception:  # noqa: BLE001 - not the codec's failure
                continue
            if data is None:
                continue
            try:
                list(await self.decode_batch([(data, spec)]))
            except Exception as chunk_exc:  # noqa: BLE001 - this chunk is the one
                kind, words = _diagnose(self, len(data), spec, chunk_exc)
                array, chunk = _parse_chunk_key(byte_getter.path)
                attrs = await _root_attrs(byte_getter.store, spec.prototype)
                return CorruptChunkError(_store_name(byte_getter.store), array, chunk, words, rerun_hint(attrs),
                                         kind)
        return None


def _install() -> None:
    """Make :class:`LocatingCodecPipeline` Zarr's codec pipeline in this process (idempotent;
    a pipeline that someone else configured is left alone)."""
    from zarr.registry import register_pipeline

    register_pipeline(LocatingCodecPipeline)
    if zarr.config.get("codec_pipeline.path") == _DEFAULT_PIPELINE:
        zarr.config.set({"codec_pipeline.path": f"{__name__}.LocatingCodecPipeline"})


_install()


# --------------------------------------------------------------------------- which chunks exist


def _local_root(array: zarr.Array) -> str | None:
    root = getattr(array.store, "root", None)
    return None if root is None else os.path.join(os.fspath(root), *array.path.split("/"))


def stored_chunks(array: zarr.Array) -> set[tuple[int, ...]]:
    """Indices of the chunks of ``array`` that have a file in the store (a listing, no reads)."""
    local = _local_root(array)
    keys: list[str] = []
    if local is not None:                                   # os.walk: ten times zarr's rglob listing
        for dirpath, _, files in os.walk(local):
            rel = os.path.relpath(dirpath, local).replace(os.sep, "/")
            keys += [f for f in files] if rel == "." else [f"{rel}/{f}" for f in files]
    else:
        prefix = f"{array.path}/" if array.path else ""

        async def listing() -> list[str]:
            return [k[len(prefix):] async for k in array.store.list_prefix(prefix)]

        keys = sync(listing())
    out = set()
    for key in keys:
        _, coords = _parse_chunk_key(key)
        if coords is not None and len(coords) == array.ndim:
            out.add(coords)
    return out


def chunk_files_exist(array: zarr.Array, chunks: Sequence[tuple[int, ...]]) -> list[bool]:
    """Whether each chunk in ``chunks`` has a file in the store (one ``stat`` each on a local store)."""
    keys = [array.metadata.encode_chunk_key(tuple(int(c) for c in chunk)) for chunk in chunks]
    local = _local_root(array)
    if local is not None:
        return [os.path.isfile(os.path.join(local, *key.split("/"))) for key in keys]
    prefix = f"{array.path}/" if array.path else ""

    async def exist() -> list[bool]:
        return [await array.store.exists(prefix + key) for key in keys]

    return sync(exist())


def read_chunk_rows(array: zarr.Array, start: int, stop: int, out: np.ndarray) -> None:
    """``out[...] = array[:, start:stop]`` for an array chunked along its first two axes only.

    Where the rows ``start:stop`` lie in one chunk row, the array is uncompressed on a local store
    (:func:`_plain_codec`: what :func:`create_array` makes) and every chunk file has its exact size, each
    chunk file is read, and its checksum verified, without Zarr: straight into its part of ``out`` (C
    contiguous) where the rows are the whole chunk's, else into a scratch buffer whose rows are copied
    out (a band split into sub-bands by a fit's memory budget; the edge chunk, stored padded). One copy
    of a whole chunk where Zarr makes two and allocates a new buffer per chunk: 0.18-0.22 s against
    0.49-0.51 s for a 522 MB band of 132 chunks (docs/benchmarks.md 2026-12-05). Anything else, a
    missing chunk or a checksum that does not match included, is read through Zarr, which returns fill
    values or raises :class:`CorruptChunkError` naming the chunk, as every other read does.
    """
    shape, chunks = array.shape, array.chunks
    local, crc = _plain_chunks(array, out.dtype), has_checksums(array)
    n_groups = shape[0] // chunks[0]
    fast = (local is not None and out.flags.c_contiguous and out.shape == (shape[0], stop - start, *shape[2:])
            and 0 <= start < stop <= shape[1] and start // chunks[1] == (stop - 1) // chunks[1]
            and shape[0] % chunks[0] == 0)
    if fast:
        row, first = divmod(start, chunks[1])
        whole = first == 0 and stop - start == chunks[1]
        size = int(np.prod(chunks)) * out.dtype.itemsize                   # bytes of one chunk
        flat = out.reshape(-1).view(np.uint8)
        scratch = None if whole else np.empty(size, np.uint8)
        rest = (0,) * (len(shape) - 2)
        for i in range(n_groups):
            key = array.metadata.encode_chunk_key((i, row, *rest))
            part = flat[i * size:(i + 1) * size] if whole else scratch
            if not _read_chunk_file(os.path.join(local, *key.split("/")), part, crc):
                break
            if not whole:
                chunk = part.view(out.dtype).reshape(chunks)
                out[i * chunks[0]:(i + 1) * chunks[0]] = chunk[:, first:first + stop - start]
        else:
            return
    array.get_basic_selection((slice(None), slice(start, stop)),
                              out=default_buffer_prototype().nd_buffer.from_numpy_array(out))


def _plain_codec(array: zarr.Array, dtype: np.dtype) -> str | None:
    """The local folder of ``array`` where its chunk files are plain: uncompressed, with a CRC32C checksum
    (what :func:`create_array` makes) or without any codec (a store written before checksums, issue 13),
    little-endian, on a local store, for values of ``dtype`` (its native dtype); None otherwise."""
    local, codecs = _local_root(array), len(array.compressors)
    ok = (local is not None and not array.filters and (codecs == 0 or codecs == 1 and has_checksums(array))
          and getattr(array.serializer, "endian", None) is not None and array.serializer.endian.value == "little"
          and dtype == _native_dtype(array.dtype) and dtype.byteorder in ("=", "<", "|"))
    return local if ok else None


def _plain_chunks(array: zarr.Array, dtype: np.dtype) -> str | None:
    """The local folder of ``array`` where its chunk files can be read or written without Zarr: plain
    (:func:`_plain_codec`) and chunked along its first two axes only; None otherwise."""
    local = _plain_codec(array, dtype)
    ok = local is not None and array.ndim >= 2 and tuple(array.chunks[2:]) == tuple(array.shape[2:])
    return local if ok else None


def _read_chunk_file(path: str, part: np.ndarray, crc: bool) -> bool:
    """Read a plain chunk file into ``part`` (contiguous ``uint8``): whether its size and CRC32C (``crc``) match."""
    import google_crc32c

    size = part.nbytes
    try:
        with open(path, "rb", buffering=0) as f:
            if os.fstat(f.fileno()).st_size != size + 4 * crc or f.readinto(memoryview(part)) != size:
                return False
            stored = int.from_bytes(f.read(4), "little") if crc else None
    except OSError:
        return False
    return not crc or google_crc32c.value(part) == stored


def read_chunk_windows(array: zarr.Array, lead: tuple[int, ...], window: tuple[slice, ...],
                       out: np.ndarray | None = None) -> np.ndarray:
    """``array[(*lead, slice(None), *window)]`` (into ``out`` if given) with one chunk per index of the first
    ``len(lead) + 1`` axes, whole along the rest (a capture's ``raw``): plain chunk files (:func:`_plain_codec`)
    read and checked in a scratch buffer, their window copied out; else Zarr, as :func:`read_chunk_rows`."""
    shape, chunks, n = array.shape, array.chunks, len(lead) + 1
    sizes = tuple(len(range(*w.indices(d))) for w, d in zip(window, shape[n:]))
    out = np.empty((shape[n - 1], *sizes), _native_dtype(array.dtype)) if out is None else out
    local, crc = _plain_codec(array, out.dtype), has_checksums(array)
    if (local is not None and tuple(chunks[:n]) == (1,) * n and tuple(chunks[n:]) == tuple(shape[n:])
            and len(window) == len(shape) - n and out.shape == (shape[n - 1], *sizes)):
        scratch = np.empty(int(np.prod(chunks)) * out.dtype.itemsize, np.uint8)
        chunk = scratch.view(out.dtype).reshape(chunks[n:])
        for i in range(shape[n - 1]):
            key = array.metadata.encode_chunk_key((*lead, i) + (0,) * (len(shape) - n))
            if not _read_chunk_file(os.path.join(local, *key.split("/")), scratch, crc):
                break
            out[i] = chunk[window]
        else:
            return out
    array.get_basic_selection((*lead, slice(None), *window),
                              out=default_buffer_prototype().nd_buffer.from_numpy_array(out))
    return out


def write_chunks_directly(array: zarr.Array, block: tuple[slice, ...], data: np.ndarray) -> bool:
    """Write ``data`` into ``array[block]``, a block of whole chunks (checked by
    :func:`tasks.stores.common.write_chunk_aligned`, the one caller), as chunk files past the page cache;
    False, with nothing written, where Zarr has to write it.

    Where Zarr is not needed (:func:`_plain_chunks`, the block spanning the axes after the first two), each chunk's
    bytes and their CRC32C (where the array has the codec) go to a temporary file renamed into place, as Zarr's
    local store writes them: the same bytes, an edge chunk padded with the fill value, and a chunk that holds only
    the fill value not stored (an old file of it removed), as Zarr does without ``write_empty_chunks``. A chunk's
    values are written from ``data`` itself where they are contiguous there and start at a 512-byte aligned address
    (a :func:`tasks.buffers.reused_buffer` is page-aligned), else from a page-aligned per-thread copy. Their whole
    512-byte blocks go with ``O_DIRECT``: on the 2-core VM a buffered write of 522 MB into fresh page-cache pages
    cost 1.26 s of kernel CPU, a direct one 0.015 s at the disk's rate (docs/benchmarks.md, 2026-12-05). A file
    system without ``O_DIRECT`` gets the same files buffered.
    """
    import google_crc32c

    from tasks.buffers import reused_buffer

    shape, chunks, fill = array.shape, array.chunks, array.fill_value
    local, crc = _plain_chunks(array, data.dtype), has_checksums(array)
    if (local is None or data.shape != tuple(s.stop - s.start for s in block)
            or any(s.stop - s.start != n for s, n in zip(block[2:], shape[2:]))
            or array.async_array.config.write_empty_chunks or fill is None or not np.isfinite(fill)):
        return False
    (l0, l1), (r0, r1) = ((s.start, s.stop) for s in block[:2])
    rest = (0,) * (array.ndim - 2)
    for i in range(l0 // chunks[0], -(-l1 // chunks[0])):
        for j in range(r0 // chunks[1], -(-r1 // chunks[1])):
            path = os.path.join(local, *array.metadata.encode_chunk_key((i, j, *rest)).split("/"))
            values = data[i * chunks[0] - l0:(i + 1) * chunks[0] - l0, j * chunks[1] - r0:(j + 1) * chunks[1] - r0]
            if _only_fill(values, fill):
                with contextlib.suppress(FileNotFoundError):        # only fill values: Zarr stores nothing
                    os.remove(path)
                continue
            if (values.shape != tuple(chunks) or not values.flags.c_contiguous
                    or values.ctypes.data % DIRECT_BLOCK):
                staged = reused_buffer("whole-chunk", tuple(chunks), data.dtype)
                if values.shape != tuple(chunks):
                    staged.fill(fill)                                # the edge chunk, padded as Zarr stores it
                staged[:values.shape[0], :values.shape[1]] = values
                values = staged
            part = values.reshape(-1).view(np.uint8)
            _write_chunk_file(path, part, google_crc32c.value(part).to_bytes(4, "little") if crc else b"")
    return True


def _only_fill(values: np.ndarray, fill: Any) -> bool:
    """Whether a chunk holds only the fill value, as Zarr decides: a float zero by its bits (a chunk of -0.0
    is stored), any other value by ``==``; the first and last values are looked at before all of them."""
    if values.dtype.kind == "f" and fill == 0:
        values, fill = values.view(f"u{values.itemsize}"), np.asarray(fill, values.dtype).view(f"u{values.itemsize}")
    return bool(values.flat[0] == fill and values.flat[-1] == fill and not np.any(values != fill))


#: Block size and address alignment of an ``O_DIRECT`` write (the logical block size of common disks).
DIRECT_BLOCK = 512


def _write_chunk_file(path: str, part: np.ndarray, checksum: bytes) -> None:
    """``part`` then ``checksum`` into ``path``, through a temporary file renamed into place; its aligned
    whole blocks with ``O_DIRECT`` where the file system takes it, the rest buffered."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = f"{path}.{uuid.uuid4().hex}.partial"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        done = 0
        direct = getattr(os, "O_DIRECT", 0)
        n_direct = len(part) // DIRECT_BLOCK * DIRECT_BLOCK
        if direct and n_direct and part.ctypes.data % DIRECT_BLOCK == 0:
            flags = fcntl.fcntl(fd, fcntl.F_GETFL)
            try:
                fcntl.fcntl(fd, fcntl.F_SETFL, flags | direct)
                view = memoryview(part)
                while done < n_direct:
                    done += os.pwrite(fd, view[done:n_direct], done)
            except OSError as exc:                      # no O_DIRECT here: the whole file buffered
                if exc.errno != errno.EINVAL:
                    raise
                done = 0
            fcntl.fcntl(fd, fcntl.F_SETFL, flags)
        for piece in (memoryview(part)[done:], memoryview(checksum)):       # the rest buffered, then the CRC
            end = done + len(piece)
            while done < end:
                done += os.pwrite(fd, piece[len(piece) - (end - done):], done)
        os.close(fd)
        fd = -1
        os.replace(tmp, path)
    except BaseException:
        if fd >= 0:
            os.close(fd)
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


#: Resume markers that say which chunks hold data: ``schema -> [(array, marker, axes)]``; marker
#: entry ``k`` (flattened) being 1 means every chunk whose index on ``axes`` (flattened) is ``k``
#: was written. A chunk holding only the fill value is not stored by Zarr, so only arrays whose
#: written chunks cannot be all fill value are listed (raw frames only with a black level > 0).
WRITTEN_RULES: dict[str, list[tuple[str, str, tuple[int, ...]]]] = {
    "btf-capture": [("raw", "written", (0, 1, 2))],         # not dark frames: all-zero ones are accepted
    "btf-texture": [("btf", "written", (0,)), ("roi", "written", (0,))],   # ingest (view), resample (target view)
    "btf-texture/reconstruct": [("btf", "written", (1,))],  # btf reconstruct: one marker per band
    "btf-texture/import": [("btf", "written", (0, 1))],     # btf import-btf: one marker per view x band
    "btf-measurement": [("measured", "written", (0,))],
}


def _rules(group: zarr.Group, attrs: dict[str, Any]) -> list[tuple[str, str, tuple[int, ...]]]:
    schema = attrs.get("schema")
    if schema == "btf-capture":
        black = attrs.get("black_level")
        return WRITTEN_RULES[schema] if isinstance(black, (int, float)) and black > 0 else []
    if schema == "btf-texture" and "reconstruct_hash" in attrs:
        return WRITTEN_RULES["btf-texture/reconstruct"]
    if schema == "btf-texture" and "import_hash" in attrs:
        return WRITTEN_RULES["btf-texture/import"]
    return WRITTEN_RULES.get(schema, [])


def missing_chunks(array: zarr.Array, marker: np.ndarray, axes: Sequence[int],
                   present: set[tuple[int, ...]] | None = None) -> list[tuple[int, ...]]:
    """Chunks of ``array`` that ``marker`` says were written but that have no file.

    Parameters
    ----------
    array : zarr.Array
        The data array.
    marker : ndarray
        Resume markers, one per chunk index on ``axes`` (flattened, row-major); 1 = written.
    axes : sequence of int
        Chunk-grid axes of ``array`` that the markers index.
    present : set of tuple, optional
        :func:`stored_chunks` of ``array`` if already listed.

    Returns
    -------
    list of tuple of int
        Missing chunk indices, row-major.
    """
    grid = tuple(int(n) for n in array.cdata_shape)
    sub = tuple(grid[a] for a in axes)
    flat = np.asarray(marker).reshape(-1)
    if flat.size != int(np.prod(sub)):
        return []                   # markers of another layout: the schema check reports the shapes
    present = stored_chunks(array) if present is None else present
    out = []
    for coords in np.ndindex(grid):
        k = int(np.ravel_multi_index(tuple(coords[a] for a in axes), sub)) if sub else 0
        if flat[k] == 1 and coords not in present:
            out.append(tuple(int(c) for c in coords))
    return out


def missing_problem(store: str, array: str, chunk: tuple[int, ...], marker: str, index: tuple[int, ...],
                    hint: str) -> ChunkProblem:
    """The :class:`ChunkProblem` of a chunk file missing although ``marker[index]`` says written."""
    return ChunkProblem(store, array, chunk, "missing",
                        f"chunk file missing although {marker}{list(index)} = 1 says it was written "
                        "(Zarr would read it as the fill value); the store was damaged after writing", hint)


# --------------------------------------------------------------------------- whole stores


def open_any_store(path: str | os.PathLike | zarr.Group) -> tuple[zarr.Group, str]:
    """Open a store read-only: ``(group, path)``; a ``btf build-db`` folder means its ``model.zarr``.

    Raises
    ------
    FileNotFoundError
        Nothing at ``path``.
    ValueError
        Not a Zarr v3 group.
    """
    if isinstance(path, zarr.Group):
        return path, _store_name(path.store)
    p = os.fspath(path)
    if "://" not in p:
        if not os.path.exists(p):
            raise FileNotFoundError(f"{p}: nothing there; check the path")
        if not os.path.isfile(os.path.join(p, "zarr.json")) and os.path.isdir(os.path.join(p, "model.zarr")):
            p = os.path.join(p, "model.zarr")
    try:
        return zarr.open_group(p, mode="r", zarr_format=3), p
    except Exception as e:  # noqa: BLE001 - any failure to open is the same answer
        raise ValueError(f"{p}: not a Zarr v3 store ({type(e).__name__}: {e}); give a store the pipeline "
                         "wrote (a .zarr folder)") from None


def store_kind(group: zarr.Group) -> str | None:
    """The root ``schema`` attribute (``"btf-capture"``, ``"btf-texture"``, ``"btf-measurement"``, ``"btf-model"``)."""
    schema = group.attrs.get("schema")
    return schema if isinstance(schema, str) else None


def _arrays(group: zarr.Group) -> list[tuple[str, zarr.Array]]:
    return sorted((name, node) for name, node in group.members(max_depth=None) if isinstance(node, zarr.Array))


def _chunk_region(array: zarr.Array, coords: tuple[int, ...]) -> tuple[slice, ...]:
    return tuple(slice(c * s, min((c + 1) * s, n)) for c, s, n in zip(coords, array.chunks, array.shape))


def nonfinite_problem(store: str, array_name: str, chunk: tuple[int, ...], data: np.ndarray, start: Sequence[int],
                      hint: str) -> ChunkProblem | None:
    """The :class:`ChunkProblem` of a chunk of a float array that holds NaN or Inf (``None``: all finite).

    Parameters
    ----------
    store, array_name : str
        Store path and array path inside it.
    chunk : tuple of int
        Chunk index.
    data : ndarray
        The chunk's values.
    start : sequence of int
        Index of the chunk's first element in the array (the first bad value is named in array indices).
    hint : str
        What to do.

    Returns
    -------
    ChunkProblem or None
        Kind ``"nonfinite"``: the counts of NaN and Inf and the first one's index; ``None`` for a
        chunk of finite values or of an integer array.
    """
    if data.dtype.kind not in "fc":
        return None
    nan, inf = np.isnan(data), np.isinf(data)
    counts = [(int(nan.sum()), "NaN"), (int(inf.sum()), "Inf")]
    if not any(n for n, _ in counts):
        return None
    first = np.unravel_index(int(np.argmax((nan | inf).reshape(-1))), data.shape)
    at = ", ".join(str(int(s) + int(i)) for s, i in zip(start, first))
    words = " and ".join(f"{n} {what}" for n, what in counts if n)
    return ChunkProblem(store, array_name, chunk, "nonfinite",
                        f"{words} value(s), first at {array_name}[{at}] (every value must be a finite number)", hint)


def verify_store(path: str | os.PathLike | zarr.Group, *, finite: bool = False) -> list[ChunkProblem]:
    """Read every chunk of every array of a store and list the damaged ones.

    Memory is bounded by one chunk: chunks are read one by one.

    Parameters
    ----------
    path : str, path-like or zarr.Group
        Any store the pipeline writes (a ``btf build-db`` folder means its ``model.zarr``).
    finite : bool
        Also count the NaN and Inf values of every stored chunk of every float array
        (:func:`nonfinite_problem`), in the same pass (``btf validate --deep``).

    Returns
    -------
    list of ChunkProblem
        Corrupt (checksum mismatch), truncated and unreadable chunks, chunks missing
        although the store's ``written`` markers say they were written (:data:`WRITTEN_RULES`),
        and with ``finite`` chunks holding NaN or Inf (kind ``"nonfinite"``), sorted by array
        and chunk. Empty when every chunk reads back as written.

    Raises
    ------
    FileNotFoundError, ValueError
        Nothing at ``path`` or not a Zarr v3 group (:func:`open_any_store`).
    """
    group, name = open_any_store(path)
    attrs = dict(group.attrs)
    hint = rerun_hint(attrs)
    problems: list[ChunkProblem] = []
    arrays = dict(_arrays(group))
    markers: dict[str, list[tuple[str, tuple[int, ...]]]] = {}
    for array_name, marker_name, axes in _rules(group, attrs):
        if array_name in arrays and marker_name in arrays:
            markers.setdefault(array_name, []).append((marker_name, axes))
    for array_name, array in arrays.items():
        present = stored_chunks(array)
        for marker_name, axes in markers.get(array_name, []):
            try:
                marker = np.asarray(arrays[marker_name][...])
            except CorruptChunkError:
                continue                                     # reported as that array's own problem
            sub = tuple(int(array.cdata_shape[a]) for a in axes)
            for chunk in missing_chunks(array, marker, axes, present):
                index = np.unravel_index(int(np.ravel_multi_index(tuple(chunk[a] for a in axes), sub)),
                                         marker.shape) if marker.ndim else ()
                problems.append(missing_problem(name, array_name, chunk, marker_name,
                                                tuple(int(i) for i in index), hint))
        floats = finite and _native_dtype(array.dtype).kind in "fc"     # integer frames hold no NaN
        for chunk in sorted(present):
            region = _chunk_region(array, chunk)
            try:
                data = array[region]
            except CorruptChunkError as e:
                problems.append(ChunkProblem(name, array_name, chunk, e.kind, e.problem, hint))
                continue
            except Exception as e:  # noqa: BLE001 - e.g. the pipeline was not installed
                problems.append(ChunkProblem(name, array_name, chunk, "unreadable",
                                             f"does not decode ({type(e).__name__}: {e})", hint))
                continue
            bad = nonfinite_problem(name, array_name, chunk, np.asarray(data), [r.start for r in region],
                                    hint) if floats else None
            if bad is not None:
                problems.append(bad)
    problems.sort(key=lambda p: (p.array, p.chunk))
    return problems


def unchecked_arrays(path: str | os.PathLike | zarr.Group) -> list[str]:
    """Arrays of a store whose chunks carry no checksum (written before checksums were added)."""
    group, _ = open_any_store(path)
    return [name for name, array in _arrays(group) if not has_checksums(array)]
