"""DFMF and FMF files: read lazily, write, rewrite byte-identically (docs/bonn-formats.md).

Both formats store an SVD of the BTF matrix: ``value = U[row] . SxV[texel]`` with rows
``l + n_l * v`` (view-major, light fastest) and texels ``x + width * y``. DFMF (``!DFMF08FCR``)
factorises each colour channel of a decorrelated colour space on its own; FMF (``!FMF12FCER``,
``!FMF06FCR``, ``!FMF06FC``) factorises all channels together, the channel fastest in U's rows.

:func:`read_factorised` returns :class:`Factorised`, whose U and SxV are ``np.memmap`` views into
the file: nothing big is read, and every size is checked against the file first.
"""

from __future__ import annotations

import dataclasses
import os
import struct
from dataclasses import dataclass, field
from typing import BinaryIO, Iterator, Sequence

import numpy as np

from tasks.bonn.header import (ByteReader, CommonHeader, open_reader, read_common_header,
                               read_signature, write_common_header)

#: Scalar size in bytes -> little-endian dtype of S, U and SxV.
SCALAR_DTYPES: dict[int, str] = {2: "<f2", 4: "<f4", 8: "<f8"}
#: Highest ``!FMF12FCER`` extended header version (btf.hh and btflib refuse 3 and above).
FMF_HEADER_VERSION_MAX = 2
#: Rows per block when writers convert U / SxV (bounds the writer's memory).
WRITE_BLOCK_ROWS = 1 << 16
_CORRUPT = "the file is corrupt or not what its signature says: export or download it again"


@dataclass
class Factorised:
    """A DFMF or FMF file, its big arrays left in the file.

    Attributes
    ----------
    path : str
    format : str
        ``"dfmf"`` or ``"fmf"``.
    header : CommonHeader
    colour_model : int
        DFMF colour model (see ``btfcore.bonn.COLOUR_MODELS``); FMF: 0 (RGB).
    colour_mean : ndarray, (3,) float32
        DFMF; FMF: zeros.
    colour_matrix : ndarray, (3, 3) float32
        DFMF (row-major as in the file); FMF: identity.
    dynamic_range_reduced : bool
        FMF12 extended header: the values are ``log(x + eps)`` (decode with
        ``btfcore.bonn.restore_dynamic_range``). Always False for DFMF.
    height_map : ndarray or None
        FMF12 extended header version 2: ``(size0, size1)`` float16 in file order.
    scalar_size : int
        2 (half), 4 (single) or 8 (double).
    S : list of ndarray
        Per channel ``(K_c,)`` singular values (informational; SxV has them multiplied in).
        FMF: the same array for every channel.
    U : list of ndarray
        Per channel ``(n_lv, K_c)`` read-only memmap views, row ``l + n_l * v``. FMF: strided
        views of the one U (its rows ``c + n_c * (l + n_l * v)``).
    SxV : list of ndarray
        Per channel ``(n_tx, K_c)`` read-only memmap views, texel ``x + width * y``. FMF: the same
        view for every channel.
    extra : dict
        What a byte-identical rewrite needs beyond the above: ``max_components`` (the leading
        component count field), FMF ``fmf_header_version``, ``height_map_size``,
        ``dynamic_range_value`` (the raw flag when not 0/1), ``U_full`` (FMF's one U).
    """

    path: str
    format: str
    header: CommonHeader
    colour_model: int
    colour_mean: np.ndarray
    colour_matrix: np.ndarray
    dynamic_range_reduced: bool
    height_map: np.ndarray | None
    scalar_size: int
    S: list[np.ndarray]
    U: list[np.ndarray]
    SxV: list[np.ndarray]
    extra: dict = field(default_factory=dict)

    @property
    def n_channels(self) -> int:
        return len(self.U)

    @property
    def components(self) -> list[int]:
        """K_c per channel."""
        return [int(u.shape[1]) for u in self.U]


def _colour_models() -> dict[int, str]:
    from btfcore.bonn.colour_models import COLOUR_MODELS
    return COLOUR_MODELS


def _scalar_size(reader: ByteReader, field_name: str) -> int:
    at = reader.offset
    size = reader.u8(field_name)
    if size not in SCALAR_DTYPES:
        raise reader.error(field_name, f"unknown scalar size {size}; known {sorted(SCALAR_DTYPES)} "
                                       "(2 half, 4 single, 8 double)", _CORRUPT, offset=at)
    return size


def _check_count(reader: ByteReader, field_name: str, at: int, got: int, want: int,
                 meaning: str) -> None:
    if got != want:
        raise reader.error(field_name, f"{got}, but the header gives {want} ({meaning})",
                           _CORRUPT, offset=at)


def _read_matrices(reader: ByteReader, prefix: str, k_at: int, k: int, rows: int, cols: int,
                   size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """S (k,), U (rows, k), SxV (cols, k) at the reader's offset; sizes checked first."""
    dtype = SCALAR_DTYPES[size]
    reader.require(f"{prefix}components", size * k * (1 + rows + cols), at=k_at)
    S = reader.array(f"{prefix}S", dtype, k)
    U = reader.memmap(f"{prefix}U", dtype, (rows, k))
    SxV = reader.memmap(f"{prefix}SxV", dtype, (cols, k))
    return S, U, SxV


def _check_end(reader: ByteReader) -> None:
    if reader.left:
        raise reader.error("end_of_data", f"{reader.left} bytes follow the last matrix (file is "
                                          f"{reader.size} bytes, the data ends at byte "
                                          f"{reader.offset})",
                           "the file has trailing garbage or its header undercounts the data "
                           "(btf.hh refuses such files too)")


def _read_dfmf_body(reader: ByteReader, header: CommonHeader) -> dict:
    max_k = reader.u32("dfmf.max_components")
    at = reader.offset
    model = reader.i32("dfmf.colour_model")
    models = _colour_models()
    if model not in models:
        raise reader.error("dfmf.colour_model", f"unknown colour model {model}; supported: "
                                                f"{dict(sorted(models.items()))}",
                           "the file uses a colour model this reader does not decode, or the "
                           "field is corrupt", offset=at)
    mean = reader.f32("dfmf.colour_mean", 3)
    matrix = reader.f32("dfmf.colour_matrix", 9).reshape(3, 3)
    n_lv, n_tx = header.n_lv, header.n_tx
    S, U, SxV, sizes = [], [], [], []
    for c in range(header.n_channels):
        p = f"channel[{c}]."
        sizes.append(_scalar_size(reader, p + "scalar_size"))
        if sizes[-1] != sizes[0]:
            raise reader.error(p + "scalar_size", f"{sizes[-1]} differs from channel 0's "
                                                  f"{sizes[0]}", "btf.hh refuses mixed precision; "
                                                  "rewrite the file with one scalar size",
                               offset=reader.offset - 1)
        k_at = reader.offset
        k = reader.u32(p + "components")
        at = reader.offset
        rows = reader.u32(p + "rows")
        _check_count(reader, p + "rows", at, rows, n_lv,
                     f"n_l * n_v = {header.n_l} * {header.n_v}")
        cols = reader.u32(p + "cols")
        _check_count(reader, p + "cols", at + 4, cols, n_tx,
                     f"width * height = {header.width} * {header.height}")
        s, u, sxv = _read_matrices(reader, p, k_at, k, rows, cols, sizes[0])
        S.append(s), U.append(u), SxV.append(sxv)
    _check_end(reader)
    return dict(colour_model=model, colour_mean=mean, colour_matrix=matrix,
                dynamic_range_reduced=False, height_map=None,
                scalar_size=sizes[0] if sizes else 2, S=S, U=U, SxV=SxV,
                extra={"max_components": max_k})


def _read_fmf_extended(reader: ByteReader, extra: dict) -> tuple[bool, np.ndarray | None]:
    at = reader.offset
    version = reader.u8("fmf.header_version")
    if version > FMF_HEADER_VERSION_MAX:
        raise reader.error("fmf.header_version", f"extended header version {version}; known up "
                                                 f"to {FMF_HEADER_VERSION_MAX}",
                           "the file is newer than this reader (btf.hh refuses it too) or "
                           "corrupt", offset=at)
    extra["fmf_header_version"] = version
    reduced, height_map = False, None
    if version >= 1:
        flag = reader.u32("fmf.dynamic_range_reduction")
        reduced = bool(flag)
        if flag not in (0, 1):
            extra["dynamic_range_value"] = flag
    if version >= 2:
        at = reader.offset
        size = (reader.u32("fmf.height_map_size"), reader.u32("fmf.height_map_size"))
        extra["height_map_size"] = size
        if size[0] * size[1] > 0:
            reader.require("fmf.height_map_size", 2 * size[0] * size[1], at=at)
            height_map = reader.array("fmf.height_map", "<f2", size[0] * size[1]).reshape(size)
    return reduced, height_map


def _read_fmf_body(reader: ByteReader, header: CommonHeader, extended: bool) -> dict:
    extra: dict = {}
    reduced, height_map = _read_fmf_extended(reader, extra) if extended else (False, None)
    extra["max_components"] = reader.u32("fmf.max_components")
    size = _scalar_size(reader, "fmf.scalar_size")
    k_at = reader.offset
    k = reader.u32("fmf.components")
    n_c = header.n_channels
    at = reader.offset
    rows = reader.u32("fmf.rows")
    _check_count(reader, "fmf.rows", at, rows, n_c * header.n_lv,
                 f"n_channels * n_l * n_v = {n_c} * {header.n_l} * {header.n_v}")
    cols = reader.u32("fmf.cols")
    _check_count(reader, "fmf.cols", at + 4, cols, header.n_tx,
                 f"width * height = {header.width} * {header.height}")
    s, u, sxv = _read_matrices(reader, "fmf.", k_at, k, rows, cols, size)
    _check_end(reader)
    per_lv = u.reshape(header.n_lv, n_c, k)
    extra["U_full"] = u
    return dict(colour_model=0, colour_mean=np.zeros(3, np.float32),
                colour_matrix=np.eye(3, dtype=np.float32), dynamic_range_reduced=reduced,
                height_map=height_map, scalar_size=size, S=[s] * n_c,
                U=[per_lv[:, c, :] for c in range(n_c)], SxV=[sxv] * n_c, extra=extra)


def read_factorised(path: str | os.PathLike) -> Factorised:
    """Read a DFMF or FMF file (by its signature); U and SxV stay in the file as memmaps.

    Raises
    ------
    BonnFormatError
        Unknown signature, truncation, a count that does not match the header (rows must be
        ``n_l * n_v`` per DFMF channel, ``n_channels * n_l * n_v`` for FMF; cols
        ``width * height``), unknown scalar size or colour model, trailing bytes.
    """
    with open_reader(path) as reader:
        signature = read_signature(reader)
        kind = {"!DFMF08FCR": "dfmf", "!FMF12FCER": "fmf12", "!FMF06FCR": "fmf",
                "!FMF06FC": "fmf"}.get(signature)
        if kind is None:
            raise reader.error("signature", f"{signature} is not a factorised (DFMF/FMF) file",
                               "open PVF files with tasks.bonn.pvf.read_pvf and BDI files with "
                               "tasks.bonn.bdi.read_bdi", offset=0)
        header = read_common_header(reader, signature)
        try:
            header.n_l
        except ValueError as e:  # pragma: no cover - read_common_header refuses it already
            raise reader.error("sampling", str(e), _CORRUPT) from None
        body = (_read_dfmf_body(reader, header) if kind == "dfmf"
                else _read_fmf_body(reader, header, extended=kind == "fmf12"))
    return Factorised(path=os.fspath(path), format="dfmf" if kind == "dfmf" else "fmf",
                      header=header, **body)


# ----------------------------------------------------------------------------------- writers


def _blocks(a: np.ndarray, dtype: str, name: str) -> Iterator[bytes]:
    """``a`` converted to ``dtype`` block by block; refuses values the dtype cannot hold."""
    for i in range(0, a.shape[0], WRITE_BLOCK_ROWS):
        block = np.asarray(a[i:i + WRITE_BLOCK_ROWS])
        with np.errstate(over="ignore", invalid="ignore"):
            out = np.ascontiguousarray(block, dtype=dtype)
        if block.dtype != out.dtype:
            overflow = ~np.isfinite(out) & np.isfinite(block)
            if overflow.any():
                row = i + int(np.argwhere(overflow)[0][0])
                raise ValueError(f"{name} row {row} holds {block[overflow].ravel()[0]!r}, beyond "
                                 f"the range of {np.dtype(dtype).name}: write with a larger "
                                 "scalar_size (4 single)")
        yield out.tobytes()


def _scalar_dtype(scalar_size: int) -> str:
    if scalar_size not in SCALAR_DTYPES:
        raise ValueError(f"scalar_size {scalar_size}: use 2 (half), 4 (single) or 8 (double)")
    return SCALAR_DTYPES[scalar_size]


def _open_out(path_or_file):
    if isinstance(path_or_file, (str, os.PathLike)):
        return open(path_or_file, "wb"), True
    return path_or_file, False


def _check_matrix(name: str, a: np.ndarray, rows: int, k: int | None = None) -> None:
    if a.ndim != 2 or a.shape[0] != rows or (k is not None and a.shape[1] != k):
        want = f"({rows}, {'K' if k is None else k})"
        raise ValueError(f"{name} has shape {a.shape}, expected {want}")


def write_dfmf(path_or_file: str | os.PathLike | BinaryIO, header: CommonHeader,
               colour_model: int, colour_mean: np.ndarray, colour_matrix: np.ndarray,
               S: Sequence[np.ndarray], U: Sequence[np.ndarray], SxV: Sequence[np.ndarray],
               scalar_size: int = 2, *, max_components: int | None = None) -> None:
    """Write a DFMF file (signature ``!DFMF08FCR``, rotations block always present).

    Parameters
    ----------
    header : CommonHeader
        Its signature is replaced by ``!DFMF08FCR``; ``rotations`` None writes ``n_rot = 0``.
    colour_model : int
        Model id of ``btfcore.bonn.COLOUR_MODELS`` that produced the channels.
    colour_mean : (3,) array; colour_matrix : (3, 3) array (written row-major)
    S, U, SxV : per channel ``(K_c,)``, ``(n_l * n_v, K_c)``, ``(width * height, K_c)`` floats
        (memmaps fine: converted block by block).
    scalar_size : int
        2 (half), 4 (single) or 8 (double).
    max_components : int, optional
        The leading component count field (default: max K_c).
    """
    dtype = _scalar_dtype(scalar_size)
    header = dataclasses.replace(header, signature="!DFMF08FCR")
    n_c = header.n_channels
    if not len(S) == len(U) == len(SxV) == n_c:
        raise ValueError(f"{n_c} channels in the header, {len(S)}/{len(U)}/{len(SxV)} S/U/SxV")
    ks = [int(np.shape(u)[1]) for u in U]
    for c in range(n_c):
        _check_matrix(f"U[{c}]", U[c], header.n_lv, ks[c])
        _check_matrix(f"SxV[{c}]", SxV[c], header.n_tx, ks[c])
        if np.shape(S[c]) != (ks[c],):
            raise ValueError(f"S[{c}] has shape {np.shape(S[c])}, expected ({ks[c]},)")
    f, own = _open_out(path_or_file)
    try:
        write_common_header(f, header)
        f.write(struct.pack("<Ii", max(ks, default=0) if max_components is None
                            else max_components, colour_model))
        f.write(np.asarray(colour_mean, dtype="<f4").reshape(3).tobytes())
        f.write(np.asarray(colour_matrix, dtype="<f4").reshape(3, 3).tobytes())
        for c in range(n_c):
            f.write(struct.pack("<BIII", scalar_size, ks[c], header.n_lv, header.n_tx))
            f.write(np.ascontiguousarray(S[c], dtype=dtype).tobytes())
            for name, a in ((f"U[{c}]", U[c]), (f"SxV[{c}]", SxV[c])):
                for block in _blocks(a, dtype, name):
                    f.write(block)
    finally:
        if own:
            f.close()


def _fmf_parts(header: CommonHeader, S, U, SxV) -> tuple[np.ndarray, np.ndarray, object]:
    """(S, SxV, U) with U either the one ``(n_c * n_lv, K)`` array or a per-channel list."""
    n_c = header.n_channels
    S0 = S[0] if isinstance(S, (list, tuple)) else S
    SxV0 = SxV[0] if isinstance(SxV, (list, tuple)) else SxV
    if isinstance(SxV, (list, tuple)) and any(s is not SxV0 and not np.array_equal(s, SxV0)
                                              for s in SxV[1:]):
        raise ValueError("FMF shares one SxV between the channels; the channels' SxV differ")
    k = int(np.shape(SxV0)[1])
    _check_matrix("SxV", SxV0, header.n_tx, k)
    if np.shape(S0) != (k,):
        raise ValueError(f"S has shape {np.shape(S0)}, expected ({k},)")
    if isinstance(U, (list, tuple)):
        if len(U) != n_c:
            raise ValueError(f"{n_c} channels in the header, {len(U)} U matrices")
        for c, u in enumerate(U):
            _check_matrix(f"U[{c}]", u, header.n_lv, k)
    else:
        _check_matrix("U", U, n_c * header.n_lv, k)
    return S0, SxV0, U


def _fmf_u_blocks(U, n_c: int, dtype: str) -> Iterator[bytes]:
    if not isinstance(U, (list, tuple)):
        yield from _blocks(U, dtype, "U")
        return
    step = max(1, WRITE_BLOCK_ROWS // n_c)
    n_lv, k = U[0].shape
    for i in range(0, n_lv, step):
        inter = np.stack([np.asarray(u[i:i + step]) for u in U], axis=1).reshape(-1, k)
        yield from _blocks(inter, dtype, f"U rows {i}..")


def write_fmf(path_or_file: str | os.PathLike | BinaryIO, header: CommonHeader,
              S: np.ndarray | Sequence[np.ndarray], U: np.ndarray | Sequence[np.ndarray],
              SxV: np.ndarray | Sequence[np.ndarray], scalar_size: int = 2,
              dynamic_range_reduced: bool = False, height_map: np.ndarray | None = None,
              extended: bool = True, *, header_version: int | None = None,
              max_components: int | None = None, dynamic_range_value: int | None = None,
              height_map_size: tuple[int, int] | None = None) -> None:
    """Write an FMF file: one factorisation of all channels.

    Parameters
    ----------
    header : CommonHeader
        Signature set here: ``!FMF12FCER`` when ``extended``, else ``!FMF06FCR`` when
        ``header.rotations`` is not None, else ``!FMF06FC``.
    S : (K,) array (or a per-channel list of the same array)
    U : (n_c * n_l * n_v, K) array, rows ``c + n_c * (l + n_l * v)``; or a list of n_c
        ``(n_l * n_v, K)`` arrays (interleaved here, block by block)
    SxV : (width * height, K) array (or a per-channel list of the same array)
    scalar_size : int
        2 (half), 4 (single) or 8 (double).
    dynamic_range_reduced : bool
        The values are ``log(x + eps)`` (needs ``extended``).
    height_map : (size0, size1) array or None
        Written as half floats (needs ``extended``; sets header version 2).
    header_version, max_components, dynamic_range_value, height_map_size
        Raw field values for a byte-identical rewrite (defaults: version 2 with a height map,
        else 1; max_components K).
    """
    dtype = _scalar_dtype(scalar_size)
    if not extended and (dynamic_range_reduced or height_map is not None):
        raise ValueError("dynamic_range_reduced and height_map need the extended FMF12 header")
    signature = ("!FMF12FCER" if extended else
                 "!FMF06FCR" if header.rotations is not None else "!FMF06FC")
    header = dataclasses.replace(header, signature=signature)
    S0, SxV0, U = _fmf_parts(header, S, U, SxV)
    k = int(SxV0.shape[1])
    if header_version is None:
        header_version = 2 if height_map is not None else 1
    if not 0 <= header_version <= FMF_HEADER_VERSION_MAX:
        raise ValueError(f"FMF12 header version {header_version} is not 0..2")
    if height_map is not None and header_version < 2:
        raise ValueError("a height map needs FMF12 header version 2")
    f, own = _open_out(path_or_file)
    try:
        write_common_header(f, header)
        if extended:
            f.write(struct.pack("<B", header_version))
            if header_version >= 1:
                flag = (dynamic_range_value if dynamic_range_value is not None
                        and dynamic_range_reduced else int(bool(dynamic_range_reduced)))
                f.write(struct.pack("<I", flag))
            if header_version >= 2:
                hm = None if height_map is None else np.asarray(height_map, dtype="<f2")
                size = (height_map_size if height_map_size is not None and hm is None
                        else (0, 0) if hm is None else hm.shape)
                f.write(struct.pack("<II", *size))
                if hm is not None:
                    f.write(np.ascontiguousarray(hm).tobytes())
        f.write(struct.pack("<IBIII", k if max_components is None else max_components,
                            scalar_size, k, header.n_channels * header.n_lv, header.n_tx))
        f.write(np.ascontiguousarray(S0, dtype=dtype).tobytes())
        for block in _fmf_u_blocks(U, header.n_channels, dtype):
            f.write(block)
        for block in _blocks(SxV0, dtype, "SxV"):
            f.write(block)
    finally:
        if own:
            f.close()


def rewrite(fact: Factorised, path: str | os.PathLike | BinaryIO) -> None:
    """Write ``fact`` back in its own format and precision: byte-identical to what was read."""
    if fact.format == "dfmf":
        write_dfmf(path, fact.header, fact.colour_model, fact.colour_mean, fact.colour_matrix,
                   fact.S, fact.U, fact.SxV, fact.scalar_size,
                   max_components=fact.extra.get("max_components"))
        return
    if fact.format != "fmf":
        raise ValueError(f"unknown format {fact.format!r}")
    extended = fact.header.signature == "!FMF12FCER"
    write_fmf(path, fact.header, fact.S, fact.extra.get("U_full", fact.U), fact.SxV,
              fact.scalar_size, fact.dynamic_range_reduced, fact.height_map, extended,
              header_version=fact.extra.get("fmf_header_version"),
              max_components=fact.extra.get("max_components"),
              dynamic_range_value=fact.extra.get("dynamic_range_value"),
              height_map_size=fact.extra.get("height_map_size"))
