"""Bonn bidirectional image files (BDI, signature ``!BDIF06R2!``): read lazily, write band by band.

A BDI stores the full BTF tensor ABRDF by ABRDF, in chunks of a few scan lines, raw, bzip2-compressed
or sparse (only the ABRDFs the mask marks as present). The byte layout, and which of btflib's
readings of the mask was chosen, is in docs/bonn-formats.md, "BDI".

Texel ``(x, y)`` is ABRDF ``x + width * y`` of the file and ``texture[:, y, x]`` here (no flip); an
ABRDF holds ``n_lv * n_ch`` half floats, channel fastest, then light, then view, so the row of a
value is ``l + n_l * v``, the row order of every other Bonn format.

Absent ABRDFs (mask 0) decode as 0, in every compression mode, as btflib's texture decoder does;
:attr:`Bdi.mask` says which texels are absent.
"""

from __future__ import annotations

import bz2
import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from tasks.bonn.errors import BonnFormatError
from tasks.bonn.header import (
    SIGNATURES,
    ByteReader,
    CommonHeader,
    read_common_header,
    read_signature,
    write_common_header,
)

__all__ = [
    "BDI_SIGNATURE",
    "BZIP2_LEVEL",
    "COMPRESSIONS",
    "RAW",
    "BZIP2",
    "SPARSE",
    "Bdi",
    "read_bdi",
    "write_bdi",
    "rewrite_bdi",
]

BDI_SIGNATURE = "!BDIF06R2!"
RAW, BZIP2, SPARSE = 0, 1, 2
#: compression code -> name (btflib: BDI_FULL_UNCOMPRESSED, BDI_FULL_BZIP, BDI_SPARSE_UNCOMPRESSED)
COMPRESSIONS: dict[int, str] = {RAW: "raw", BZIP2: "bzip2", SPARSE: "sparse"}
#: bzip2 block size of the writer: fixed, so that a file is written byte for byte the same each time
BZIP2_LEVEL = 9
_HALF = np.dtype("<f2")
#: a chunk's uint32 byte count cannot say more
_MAX_CHUNK_BYTES = 2**32 - 1

TextureSource = Callable[[int, int], np.ndarray]


def _fix_file() -> str:
    return "the file is damaged or not a BDI; write it again or get an intact copy"


@dataclass(eq=False)
class Bdi:
    """An opened BDI: header, mask and chunk table; the ABRDFs stay in the file until asked for.

    Attributes
    ----------
    path : str
        The file.
    header : CommonHeader
        Meta block, angular sampling, width, height and the rotations (read after the mask in a BDI).
    lines_per_chunk : int
        Scan lines per chunk (btflib's writers use 4). In a sparse file a chunk holds
        ``width * lines_per_chunk`` *stored* ABRDFs, which need not be whole scan lines.
    compression : int
        0 raw, 1 bzip2, 2 sparse (:data:`COMPRESSIONS`).
    mask_values : np.ndarray
        (height, width) uint8, the mask bytes as stored: nonzero = ABRDF present.
    chunk_offsets : np.ndarray
        (n_chunks,) int64, byte offset of each chunk's uint32 byte count; the data follow it.
    chunk_nbytes : np.ndarray
        (n_chunks,) int64, the stored (for bzip2: compressed) bytes of each chunk.
    field_offsets : dict[str, int]
        Byte offset of each BDI field after the common header (``"scan lines per chunk"``,
        ``"compression"``, ``"mask"``, ``"rotations"``, ``"chunks"``).
    n_stored : int
        ABRDFs stored in the chunks: every texel, or (sparse) those the mask marks present.
    """

    path: str
    header: CommonHeader
    lines_per_chunk: int
    compression: int
    mask_values: np.ndarray
    chunk_offsets: np.ndarray
    chunk_nbytes: np.ndarray
    field_offsets: dict[str, int]
    n_stored: int
    _cache: tuple[int, np.ndarray] | None = field(default=None, repr=False, compare=False)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_cache"] = None
        return state

    # ------------------------------------------------------------------ geometry
    @property
    def width(self) -> int:
        return int(self.header.width)

    @property
    def height(self) -> int:
        return int(self.header.height)

    @property
    def n_lv(self) -> int:
        return int(self.header.n_lv)

    @property
    def n_channels(self) -> int:
        return int(self.header.n_channels)

    @property
    def mask(self) -> np.ndarray:
        """(height, width) bool: True where the file holds an ABRDF."""
        return self.mask_values != 0

    @property
    def abrdfs_per_chunk(self) -> int:
        return self.width * self.lines_per_chunk

    @property
    def n_chunks(self) -> int:
        return int(self.chunk_offsets.size)

    @property
    def abrdf_nbytes(self) -> int:
        return self.n_lv * self.n_channels * _HALF.itemsize

    def chunk_abrdfs(self, k: int) -> int:
        """ABRDFs chunk ``k`` holds (the last chunk may hold fewer than :attr:`abrdfs_per_chunk`)."""
        return min(self.abrdfs_per_chunk, self.n_stored - k * self.abrdfs_per_chunk)

    def _chunk_sizes_allowed(self, k: int) -> tuple[int, ...]:
        """Uncompressed byte sizes chunk ``k`` may have: exact, or (last chunk) padded to full."""
        exact = self.chunk_abrdfs(k) * self.abrdf_nbytes
        full = self.abrdfs_per_chunk * self.abrdf_nbytes
        return (exact, full) if k == self.n_chunks - 1 and full != exact else (exact,)

    # ------------------------------------------------------------------ chunks
    def read_chunk(self, k: int) -> np.ndarray:
        """The ABRDFs of chunk ``k``, as stored.

        Returns
        -------
        np.ndarray
            (chunk_abrdfs(k), n_lv, n_ch) float16: a read-only memmap view for raw and sparse files,
            the decompressed chunk for bzip2 files. Padding of a padded last chunk is cut off.
        """
        if not 0 <= k < self.n_chunks:
            raise IndexError(f"{self.path}: chunk {k} does not exist (the file has {self.n_chunks})")
        cache = self._cache                     # one read: another thread may replace it
        if cache is not None and cache[0] == k:
            return cache[1]
        data_offset = int(self.chunk_offsets[k]) + 4
        nbytes = int(self.chunk_nbytes[k])
        shape = (self.chunk_abrdfs(k), self.n_lv, self.n_channels)
        if nbytes == 0 or self.abrdf_nbytes == 0:
            return np.zeros(shape, _HALF)
        if self.compression != BZIP2:
            flat = np.memmap(self.path, dtype=_HALF, mode="r", offset=data_offset,
                             shape=(nbytes // _HALF.itemsize,))
            return flat[: int(np.prod(shape))].reshape(shape)
        with open(self.path, "rb") as f:
            f.seek(data_offset)
            packed = f.read(nbytes)
        if len(packed) != nbytes:
            raise BonnFormatError(self.path, data_offset, f"chunk {k} data",
                                  f"the file ended after {len(packed)} of {nbytes} bytes (it shrank "
                                  "since it was opened?)", "open the file again")
        raw = _bunzip(packed, self._chunk_sizes_allowed(k), self.path, data_offset, k)
        chunk = np.frombuffer(raw, _HALF)[: int(np.prod(shape))].reshape(shape)
        self._cache = (k, chunk)
        return chunk

    def last_chunk_padded(self) -> bool:
        """Whether the last chunk is stored padded to :attr:`abrdfs_per_chunk` ABRDFs.

        btflib writes a padded last chunk from a BDI built in memory and a short one otherwise; its
        reader takes both. For a bzip2 file this decompresses the last chunk.
        """
        if self.n_chunks == 0:
            return False
        k = self.n_chunks - 1
        full = self.abrdfs_per_chunk * self.abrdf_nbytes
        if self.chunk_abrdfs(k) * self.abrdf_nbytes == full:
            return False
        if self.compression != BZIP2:
            return int(self.chunk_nbytes[k]) == full
        data_offset = int(self.chunk_offsets[k]) + 4
        with open(self.path, "rb") as f:
            f.seek(data_offset)
            packed = f.read(int(self.chunk_nbytes[k]))
        return len(_bunzip(packed, self._chunk_sizes_allowed(k), self.path, data_offset, k)) == full

    def _stored_before(self, logical: int) -> int:
        """Stored ABRDFs before texel ``logical`` (``x + width * y``); counted, not tabulated, so
        opening a file allocates nothing per texel beyond the mask."""
        if self.compression != SPARSE:
            return logical
        return int(np.count_nonzero(self.mask_values.reshape(-1)[:logical]))

    def _chunks_for_stored(self, s0: int, s1: int) -> range:
        """Chunks holding the stored ABRDFs ``s0 .. s1 - 1``."""
        if s1 <= s0:
            return range(0)
        return range(s0 // self.abrdfs_per_chunk, (s1 - 1) // self.abrdfs_per_chunk + 1)

    def chunks_for_rows(self, y0: int, y1: int) -> range:
        """Indices of the chunks that hold scan lines ``y0 .. y1 - 1``."""
        w = self.width
        return self._chunks_for_stored(self._stored_before(y0 * w), self._stored_before(y1 * w))

    def _stored(self, s0: int, s1: int) -> np.ndarray:
        """Stored ABRDFs ``s0 .. s1 - 1`` as (s1 - s0, n_lv, n_ch) float16, possibly a read-only
        view. Every chunk is read (bzip2: decompressed, its size checked) before anything of the
        header's sizes is allocated."""
        a = self.abrdfs_per_chunk
        pieces = [self.read_chunk(k)[max(s0, k * a) - k * a:min(s1, (k + 1) * a) - k * a]
                  for k in self._chunks_for_stored(s0, s1)]
        if not pieces:
            return np.zeros((0, self.n_lv, self.n_channels), _HALF)
        return pieces[0] if len(pieces) == 1 else np.concatenate(pieces)

    # ------------------------------------------------------------------ decoding
    def read_texture_rows(self, y0: int, y1: int, *, dtype=np.float32,
                          apply_mask: bool = True) -> np.ndarray:
        """Scan lines ``y0 .. y1 - 1`` of every texture, decoding only the chunks that hold them.

        Parameters
        ----------
        y0, y1 : int
            First and one-past-last scan line, ``0 <= y0 <= y1 <= height``.
        dtype : numpy dtype, optional
            float32 (default) or float16 (the stored bits, for a lossless rewrite).
        apply_mask : bool, optional
            Set absent texels (mask 0) to 0 (default). Without it, a raw or bzip2 file gives what it
            stores there; a sparse file stores nothing there, so 0 either way.

        Returns
        -------
        np.ndarray
            (n_lv, y1 - y0, width, n_ch) of ``dtype``; row ``l + n_l * v``.
        """
        h, w = self.height, self.width
        y0, y1 = int(y0), int(y1)
        if not 0 <= y0 <= y1 <= h:
            raise IndexError(f"{self.path}: scan lines {y0}..{y1} outside 0..{h}")
        stored = self._stored(self._stored_before(y0 * w), self._stored_before(y1 * w))
        present = self.mask_values[y0:y1] != 0                          # (y1 - y0, w)
        if self.compression == SPARSE:
            out = np.zeros((self.n_lv, y1 - y0, w, self.n_channels), dtype)
            out[:, present] = stored.transpose(1, 0, 2)                 # present texels in x + w y order
            return out
        rows = stored.reshape(y1 - y0, w, self.n_lv, self.n_channels).transpose(2, 0, 1, 3)
        out = np.array(rows, dtype=dtype, order="C")                      # always a copy
        if apply_mask and not present.all():
            out[:, ~present] = 0
        return out

    def read_abrdfs(self, x, y, *, dtype=np.float32) -> np.ndarray:
        """The ABRDFs of texels ``(x[i], y[i])``; absent texels give 0.

        Raw and sparse files read only those ABRDFs' bytes; a bzip2 file decompresses each chunk
        involved once.

        Parameters
        ----------
        x, y : array_like of int
            (n,) texel columns and scan lines.
        dtype : numpy dtype, optional

        Returns
        -------
        np.ndarray
            (n_lv, n, n_ch) of ``dtype``.
        """
        x = np.asarray(x, dtype=np.int64).reshape(-1)
        y = np.asarray(y, dtype=np.int64).reshape(-1)
        if x.shape != y.shape:
            raise ValueError(f"x and y differ in length: {x.size} and {y.size}")
        bad = (x < 0) | (x >= self.width) | (y < 0) | (y >= self.height)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise IndexError(f"{self.path}: texel ({x[i]}, {y[i]}) outside {self.width} x {self.height}")
        logical = x + self.width * y
        present = self.mask_values.reshape(-1)[logical] != 0
        out = np.zeros((x.size, self.n_lv, self.n_channels), _HALF)
        if self.compression == SPARSE:
            storage = np.searchsorted(np.flatnonzero(self.mask_values.reshape(-1)), logical)
        else:
            storage = logical
        a = self.abrdfs_per_chunk
        chunk_of = storage // a
        for k in np.unique(chunk_of[present]):
            sel = np.flatnonzero(present & (chunk_of == k))
            out[sel] = self.read_chunk(int(k))[storage[sel] - int(k) * a]
        return np.ascontiguousarray(out.transpose(1, 0, 2), dtype=dtype)


# ---------------------------------------------------------------------------------------- reading
def _bunzip(packed: bytes, sizes: tuple[int, ...], path: str, offset: int, k: int) -> bytes:
    """Decompress one bzip2 chunk whose result must be one of ``sizes`` bytes, never inflating more."""
    field_name = f"chunk {k} data"
    limit = max(sizes)
    dec = bz2.BZ2Decompressor()
    try:
        raw = dec.decompress(packed, max_length=limit + 1)
        # the output limit was reached with input left: one more byte, or the end of the stream
        while len(raw) <= limit and not dec.eof and not dec.needs_input:
            more = dec.decompress(b"", max_length=limit + 1 - len(raw))
            if not more and not dec.eof:
                break
            raw += more
    except (OSError, ValueError, EOFError) as err:
        raise BonnFormatError(path, offset, field_name, f"bzip2 data fail to decompress ({err})",
                              _fix_file()) from None
    if len(raw) > limit:
        raise BonnFormatError(path, offset, field_name,
                              f"decompresses to more than the {limit} bytes the chunk should hold "
                              f"({_sizes_text(sizes)})", _fix_file())
    if not dec.eof:
        raise BonnFormatError(path, offset, field_name,
                              f"the bzip2 stream ends early ({len(raw)} bytes decompressed, "
                              f"{_sizes_text(sizes)} expected)", _fix_file())
    if dec.unused_data:
        raise BonnFormatError(path, offset, field_name,
                              f"{len(dec.unused_data)} bytes follow the end of the bzip2 stream "
                              "inside the chunk", _fix_file())
    if len(raw) not in sizes:
        raise BonnFormatError(path, offset, field_name,
                              f"decompresses to {len(raw)} bytes, expected {_sizes_text(sizes)}",
                              _fix_file())
    return raw


def _read_header_prefix(r: ByteReader, signature: str) -> CommonHeader:
    """Meta block, sampling, width and height (the BDI signature does not end in ``R``, so the
    common header reader stops before the rotations, which a BDI stores after the mask)."""
    return read_common_header(r, signature)


def _read_rotations(r: ByteReader) -> np.ndarray:
    """uint32 n_rot, then n_rot x 9 float32: (n_rot, 3, 3) float32 (each rotation in C order)."""
    at = r.offset
    n_rot = r.u32("rotations.n_rot")
    r.require("rotations.n_rot", 36 * n_rot, at=at)
    return r.array("rotations", "<f4", 9 * n_rot).reshape(n_rot, 3, 3).astype(np.float32)


def _write_header_prefix(f, header: CommonHeader) -> None:
    """Signature, meta block, sampling, width, height: the common header without rotations."""
    write_common_header(f, header)


def _write_rotations(f, rotations: np.ndarray | None) -> None:
    rot = (np.zeros((0, 3, 3), "<f4") if rotations is None
           else np.ascontiguousarray(rotations, dtype="<f4").reshape(-1, 3, 3))
    f.write(np.array([rot.shape[0]], "<u4").tobytes())
    f.write(rot.tobytes())


def _sizes_text(sizes: tuple[int, ...]) -> str:
    return " or ".join(str(s) for s in sizes) + " bytes (ABRDFs x n_lv x n_ch x 2)"


def read_bdi(path: str | os.PathLike) -> Bdi:
    """Open a BDI: parse the header, the mask and the chunk table, decompressing nothing.

    Every size is checked against the bytes left in the file before it is read or allocated; each
    chunk's uint32 byte count is checked against the bytes left before the walk skips over it, and
    for raw and sparse files against the size its ABRDFs need.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    Bdi

    Raises
    ------
    BonnFormatError
        On anything that does not parse: the message names the file, the byte offset and the field.
    """
    path = os.fspath(path)
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        r = ByteReader(f, path, size)
        signature = read_signature(r)
        if SIGNATURES.get(signature) != "bdi":
            raise BonnFormatError(path, 0, "signature",
                                  f"{signature!r} is a {SIGNATURES.get(signature)} file, not a BDI",
                                  "open it with the reader of its format (tasks.bonn)")
        header = _read_header_prefix(r, signature)
        offsets: dict[str, int] = {}
        offsets["scan lines per chunk"] = r.offset
        lines = r.u32("scan lines per chunk")
        if lines == 0:
            raise BonnFormatError(path, offsets["scan lines per chunk"], "scan lines per chunk",
                                  "is 0 (a chunk holds at least one scan line)", _fix_file())
        offsets["compression"] = r.offset
        compression = r.u8("compression")
        if compression not in COMPRESSIONS:
            raise BonnFormatError(path, offsets["compression"], "compression",
                                  f"unknown code {compression} (known: {COMPRESSIONS})",
                                  "the file is damaged, or of a BDI variant this reader does not know")
        w, h = int(header.width), int(header.height)
        offsets["mask"] = r.offset
        r.require("mask", w * h)
        mask = np.asarray(r.array("mask", np.uint8, w * h)).reshape(h, w)
        offsets["rotations"] = r.offset
        header = dataclasses.replace(header, rotations=_read_rotations(r))
        offsets["chunks"] = r.offset
        bdi = Bdi(path=path, header=header, lines_per_chunk=int(lines), compression=int(compression),
                  mask_values=mask, chunk_offsets=np.zeros(0, np.int64),
                  chunk_nbytes=np.zeros(0, np.int64), field_offsets=offsets,
                  n_stored=int(np.count_nonzero(mask)) if compression == SPARSE else w * h)
        _walk_chunks(bdi, r, size)
    return bdi


def _walk_chunks(bdi: Bdi, r: ByteReader, size: int) -> None:
    """Fill ``bdi.chunk_offsets`` and ``bdi.chunk_nbytes`` by walking the uint32 byte counts."""
    path, a = bdi.path, bdi.abrdfs_per_chunk
    n_chunks = -(-bdi.n_stored // a) if a else 0
    left = size - r.offset
    if 4 * n_chunks > left:
        raise BonnFormatError(path, r.offset, "chunk table",
                              f"{bdi.n_stored} ABRDFs in chunks of {a} make {n_chunks} chunks, whose "
                              f"byte counts alone need {4 * n_chunks} bytes, but only {left} are left",
                              "the file is truncated; get a complete copy")
    if bdi.compression != BZIP2 and bdi.n_stored * bdi.abrdf_nbytes > left:
        raise BonnFormatError(path, r.offset, "chunk table",
                              f"{bdi.n_stored} ABRDFs of {bdi.abrdf_nbytes} bytes need "
                              f"{bdi.n_stored * bdi.abrdf_nbytes} bytes, but only {left} are left",
                              "the file is truncated; get a complete copy")
    offsets = np.empty(n_chunks, np.int64)
    nbytes = np.empty(n_chunks, np.int64)
    bdi.chunk_offsets, bdi.chunk_nbytes = offsets, nbytes
    for k in range(n_chunks):
        offsets[k] = r.offset
        count = r.u32(f"chunk {k} byte count")
        left = size - r.offset
        if count > left:
            raise BonnFormatError(path, int(offsets[k]), f"chunk {k} byte count",
                                  f"says {count} bytes follow, but only {left} are left in the file",
                                  "the file is truncated or the count is damaged; get a complete copy")
        nbytes[k] = count
        if bdi.compression != BZIP2 and count not in bdi._chunk_sizes_allowed(k):
            raise BonnFormatError(path, int(offsets[k]), f"chunk {k} byte count",
                                  f"says {count} bytes, but its {bdi.chunk_abrdfs(k)} ABRDFs take "
                                  f"{_sizes_text(bdi._chunk_sizes_allowed(k))}",
                                  "the count or the header (size, sampling, channels, mask) is damaged")
        r.skip(f"chunk {k} data", count)
    if r.offset != size:
        raise BonnFormatError(path, r.offset, "end of file",
                              f"{size - r.offset} bytes follow the last of the {n_chunks} chunks",
                              "the header (size, scan lines, mask) does not match the chunks, or "
                              "data were appended; get an intact copy")


# ---------------------------------------------------------------------------------------- writing
def write_bdi(path: str | os.PathLike, header: CommonHeader, textures: np.ndarray | TextureSource,
              *, compression: int = RAW, lines_per_chunk: int = 4, mask: np.ndarray | None = None,
              pad_last_chunk: bool = False, zero_absent: bool = True) -> None:
    """Write a BDI, scan-line band by band, as half floats.

    Parameters
    ----------
    path : str or os.PathLike
        Written through a temporary file beside it, renamed at the end.
    header : CommonHeader
        Meta block, sampling, width, height, rotations (``None``: none); the signature is set to
        :data:`BDI_SIGNATURE`.
    textures : array_like or callable
        (n_lv, height, width, n_ch) values (a NumPy, Zarr or Dask array: sliced band by band), or
        ``textures(y0, y1)`` returning (n_lv, y1 - y0, width, n_ch) for scan lines ``y0 .. y1 - 1``,
        so a store larger than memory is written with one band of ``lines_per_chunk`` scan lines
        in memory at a time. Row ``l + n_l * v``.
    compression : int, optional
        0 raw (default), 1 bzip2 (level :data:`BZIP2_LEVEL`, deterministic), 2 sparse.
    lines_per_chunk : int, optional
        Scan lines per chunk (btflib writes 4).
    mask : array_like, optional
        (height, width) bool or uint8, nonzero = ABRDF present; ``None``: all present.
    pad_last_chunk : bool, optional
        Pad a short last chunk with zeros to ``width * lines_per_chunk`` ABRDFs, as btflib does
        when it writes a BDI built in memory (default: a short last chunk).
    zero_absent : bool, optional
        Write 0 for absent texels of raw and bzip2 files (default); ``False`` writes what
        ``textures`` holds there (a lossless rewrite of a file that stores values there).

    Raises
    ------
    ValueError
        A shape that does not match the header, an unknown compression, a chunk over 4 GiB, or a
        finite value beyond the half-float range (65504).
    """
    path = Path(path)
    header = dataclasses.replace(header, signature=BDI_SIGNATURE)
    n_lv, h, w, n_ch = int(header.n_lv), int(header.height), int(header.width), int(header.n_channels)
    if compression not in COMPRESSIONS:
        raise ValueError(f"compression {compression!r} unknown; use one of {COMPRESSIONS}")
    if int(lines_per_chunk) < 1:
        raise ValueError(f"lines_per_chunk is {lines_per_chunk}; it must be at least 1")
    lines = int(lines_per_chunk)
    chunk_bytes = w * lines * n_lv * n_ch * _HALF.itemsize
    if chunk_bytes > _MAX_CHUNK_BYTES:
        raise ValueError(f"a chunk of {lines} scan lines holds {chunk_bytes} bytes, more than its "
                         "uint32 byte count can say; use fewer lines_per_chunk")
    mask_values = _mask_values(mask, h, w)
    expected = (n_lv, h, w, n_ch)
    if not callable(textures) and tuple(np.shape(textures)) != expected:
        raise ValueError(f"textures have shape {tuple(np.shape(textures))}; the header says "
                         f"(n_lv, height, width, n_ch) = {expected}")

    def band(y0: int, y1: int) -> np.ndarray:
        values = textures(y0, y1) if callable(textures) else textures[:, y0:y1]
        values = np.asarray(values)
        if values.shape != (n_lv, y1 - y0, w, n_ch):
            raise ValueError(f"textures({y0}, {y1}) returned shape {values.shape}, expected "
                             f"{(n_lv, y1 - y0, w, n_ch)}")
        with np.errstate(over="ignore"):
            half = values.astype(_HALF)
        if values.dtype != _HALF and np.any(np.isinf(half) & np.isfinite(values)):
            raise ValueError(f"scan lines {y0}..{y1 - 1} hold finite values beyond the half-float "
                             "range (65504); scale the textures (and rgb_scale_factor) down")
        # ABRDF-major: (texels of the band, n_lv, n_ch), channel fastest, then row l + n_l * v
        return np.ascontiguousarray(half.transpose(1, 2, 0, 3)).reshape((y1 - y0) * w, n_lv, n_ch)

    tmp = path.with_name(path.name + ".partial")
    try:
        with open(tmp, "wb") as f:
            _write_header_prefix(f, header)
            f.write(np.array([lines], "<u4").tobytes())
            f.write(np.array([compression], np.uint8).tobytes())
            f.write(mask_values.tobytes())
            _write_rotations(f, header.rotations)
            chunks = (_sparse_chunks(band, mask_values, lines, pad_last_chunk) if compression == SPARSE
                      else _full_chunks(band, mask_values, lines, pad_last_chunk, zero_absent))
            for payload in chunks:
                if compression == BZIP2:
                    payload = bz2.compress(payload, BZIP2_LEVEL)
                if len(payload) > _MAX_CHUNK_BYTES:
                    raise ValueError("a compressed chunk exceeds 4 GiB; use fewer lines_per_chunk")
                f.write(np.array([len(payload)], "<u4").tobytes())
                f.write(payload)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _mask_values(mask, h: int, w: int) -> np.ndarray:
    """(h, w) uint8 mask bytes: 1 where an ABRDF is present (a bool mask), or the given bytes."""
    if mask is None:
        return np.ones((h, w), np.uint8)
    mask = np.asarray(mask)
    if mask.shape != (h, w):
        raise ValueError(f"mask has shape {mask.shape}; expected (height, width) = {(h, w)}")
    if mask.dtype == np.bool_:
        return mask.astype(np.uint8)
    if not np.issubdtype(mask.dtype, np.integer) or mask.min(initial=0) < 0 or mask.max(initial=0) > 255:
        raise ValueError("mask must be bool, or integers 0..255 (nonzero = ABRDF present)")
    return np.ascontiguousarray(mask, dtype=np.uint8)


def _full_chunks(band, mask_values: np.ndarray, lines: int, pad: bool, zero_absent: bool):
    """Payloads of a raw or bzip2 file: one chunk per band of ``lines`` scan lines."""
    h, w = mask_values.shape
    for y0 in range(0, h, lines):
        y1 = min(h, y0 + lines)
        abrdfs = band(y0, y1)
        if zero_absent:
            absent = mask_values[y0:y1].reshape(-1) == 0
            if absent.any():
                abrdfs[absent] = 0
        payload = abrdfs.tobytes()
        if pad and y1 - y0 < lines:
            payload += bytes((lines - (y1 - y0)) * w * abrdfs[0].nbytes)
        yield payload


def _sparse_chunks(band, mask_values: np.ndarray, lines: int, pad: bool):
    """Payloads of a sparse file: the present ABRDFs, ``width * lines`` to a chunk."""
    h, w = mask_values.shape
    per_chunk = w * lines
    pending: list[np.ndarray] = []
    n_pending = 0
    abrdf_nbytes = 0
    for y0 in range(0, h, lines):
        y1 = min(h, y0 + lines)
        present = mask_values[y0:y1].reshape(-1) != 0
        if not present.any():
            continue
        abrdfs = band(y0, y1)[present]
        abrdf_nbytes = abrdfs[0].nbytes
        pending.append(abrdfs)
        n_pending += len(abrdfs)
        while n_pending >= per_chunk:
            joined = np.concatenate(pending) if len(pending) > 1 else pending[0]
            yield joined[:per_chunk].tobytes()
            rest = joined[per_chunk:]
            pending, n_pending = ([rest], len(rest)) if len(rest) else ([], 0)
    if n_pending:
        payload = np.concatenate(pending).tobytes()
        if pad:
            payload += bytes((per_chunk - n_pending) * abrdf_nbytes)
        yield payload


def rewrite_bdi(bdi: Bdi, path: str | os.PathLike) -> None:
    """Write what :func:`read_bdi` read, byte for byte (the stored half floats, mask bytes, padding)."""
    write_bdi(path, bdi.header,
              lambda y0, y1: bdi.read_texture_rows(y0, y1, dtype=_HALF, apply_mask=False),
              compression=bdi.compression, lines_per_chunk=bdi.lines_per_chunk,
              mask=bdi.mask_values, pad_last_chunk=bdi.last_chunk_padded(), zero_absent=False)
