"""PVF files (per-view factorisation): read lazily, decode rows; a small writer for tests.

A PVF file (``!PVF06FCR``, ``!PVF06FC``) stores one PCA per view ("view slot"): eigenvalues, the
subtracted mean, components ``Cs`` and weights ``Ws``. Two orientations exist (btflib's
``decode_pvf_texture``), told apart by the slot's dimension:

- ``dimension == n_c * n_l`` (light fields): ``Ws`` rows are texels, ``Cs``/mean rows
  ``c + n_c * l``; value(l, v, t, c) = ``Ws_v[t] . Cs_v[c + n_c l] + mean_v[c + n_c l]``;
- ``dimension == n_c * n_tx`` (images): ``Ws`` rows are lights, ``Cs``/mean rows
  ``c + n_c * t``; value(l, v, t, c) = ``Cs_v[c + n_c t] . Ws_v[l] + mean_v[c + n_c t]``.

Texels ``t = x + width * y`` as in DFMF. A legacy layout (int32 magic 301074 after the
signature) has no meta block: K, width, height, slot count, then the angular sampling.
"""

from __future__ import annotations

import dataclasses
import os
import struct
from dataclasses import dataclass
from typing import BinaryIO, Sequence

import numpy as np

from tasks.bonn.dfmf import SCALAR_DTYPES, _blocks, _check_end, _scalar_dtype, _scalar_size
from tasks.bonn.header import (CommonHeader, ByteReader, _read_sampling, make_header, open_reader,
                               read_common_header, read_signature, write_common_header)

#: int32 after the signature that marks the legacy PVF layout (btflib ``read_ubo_pvf``).
PVF_LEGACY_MAGIC = 301074
_CORRUPT = "the file is corrupt or not what its signature says: export or download it again"


@dataclass
class PvfSlot:
    """One view's PCA. Arrays are read-only memmaps (``eigenvalues`` and ``mean`` in memory).

    Attributes
    ----------
    scalar_size : int
    eigenvalues : (K,) array
    mean : (dimension,) array
    Cs : (dimension, K) array
    Ws : (n_weights, K) array
    """

    scalar_size: int
    eigenvalues: np.ndarray
    mean: np.ndarray
    Cs: np.ndarray
    Ws: np.ndarray


@dataclass
class Pvf:
    """A PVF file: header, one :class:`PvfSlot` per view, the orientation of the slots.

    Attributes
    ----------
    path : str
    header : CommonHeader
        For the legacy layout a header with ``version == 0`` (no meta block), RGB channels.
    slots : list of PvfSlot
        Slot ``v`` is view ``v``.
    orientation : str
        ``"lights"`` (dimension n_c n_l, Ws over texels) or ``"texels"`` (dimension n_c n_tx,
        Ws over lights).
    legacy : bool
        The legacy layout (magic 301074).
    extra : dict
        ``max_components`` (the file's leading K) for a byte-identical rewrite.
    """

    path: str
    header: CommonHeader
    slots: list[PvfSlot]
    orientation: str
    legacy: bool
    extra: dict

    def decode_rows(self, rows: Sequence[int] | slice | np.ndarray,
                    texels: Sequence[int] | slice | np.ndarray = slice(None)) -> np.ndarray:
        """Decode BTF rows (``l + n_l * v``) at ``texels`` (indices ``x + width * y``).

        Returns
        -------
        ndarray, (n_rows, n_sel_texels, n_channels) float32
            The stored values (no colour transform: PVF has none).
        """
        h = self.header
        n_l, n_c = h.n_l, h.n_channels
        rows = np.arange(h.n_lv)[rows] if isinstance(rows, slice) else np.asarray(rows, np.int64)
        tx = np.arange(h.n_tx)[texels] if isinstance(texels, slice) else np.asarray(texels, np.int64)
        if rows.size and (rows.min() < 0 or rows.max() >= h.n_lv):
            raise IndexError(f"rows outside 0..{h.n_lv - 1}")
        if tx.size and (tx.min() < 0 or tx.max() >= h.n_tx):
            raise IndexError(f"texels outside 0..{h.n_tx - 1}")
        out = np.empty((rows.size, tx.size, n_c), np.float32)
        chans = np.arange(n_c)
        for v in np.unique(rows // n_l):
            where = np.nonzero(rows // n_l == v)[0]
            lights = rows[where] % n_l
            s = self.slots[int(v)]
            if self.orientation == "lights":
                idx = (chans[None, :] + n_c * lights[:, None]).ravel()       # (n_sel_l * n_c,)
                w = np.asarray(s.Ws[tx], np.float32)                          # (n_tx_sel, K)
                c = np.asarray(s.Cs[idx], np.float32)                         # (n_sel_l n_c, K)
                val = w @ c.T + np.asarray(s.mean[idx], np.float32)[None, :]
                out[where] = val.reshape(tx.size, lights.size, n_c).transpose(1, 0, 2)
            else:
                idx = (chans[None, :] + n_c * tx[:, None]).ravel()           # (n_tx_sel * n_c,)
                w = np.asarray(s.Ws[lights], np.float32)                      # (n_sel_l, K)
                c = np.asarray(s.Cs[idx], np.float32)                         # (n_tx_sel n_c, K)
                val = w @ c.T + np.asarray(s.mean[idx], np.float32)[None, :]
                out[where] = val.reshape(lights.size, tx.size, n_c)
        return out


def _read_legacy_header(reader: ByteReader,
                        signature: str) -> tuple[CommonHeader, int, int, int]:
    """After the magic: K, width, height, slot count, sampling (no meta, no rotations)."""
    k = reader.u32("pvf.max_components")
    width = reader.u32("width")
    height = reader.u32("height")
    slots_at = reader.offset
    n_slots = reader.u32("pvf.n_slots")
    views, lights = _read_sampling(reader)
    header = make_header(views, lights, width, height, signature=signature, version=1)
    header = dataclasses.replace(header, version=0, rotations=None)
    return header, k, n_slots, slots_at


def _read_slot(reader: ByteReader, v: int, header: CommonHeader) -> PvfSlot:
    p = f"slot[{v}]."
    size = _scalar_size(reader, p + "scalar_size")
    dtype = SCALAR_DTYPES[size]
    k_at = reader.offset
    k = reader.u32(p + "components")
    n_w = reader.u32(p + "n_weights")
    dim = reader.u32(p + "dimension")
    reader.require(p + "components", size * (k + dim + k * dim + k * n_w), at=k_at)
    n_c, n_l, n_tx = header.n_channels, header.n_l, header.n_tx
    if not ((dim == n_c * n_l and n_w == n_tx) or (dim == n_c * n_tx and n_w == n_l)):
        raise reader.error(p + "dimension", f"dimension {dim} with {n_w} weights fits neither "
                                            f"n_c * n_l = {n_c * n_l} with n_tx = {n_tx} weights "
                                            f"nor n_c * n_tx = {n_c * n_tx} with n_l = {n_l}",
                           _CORRUPT, offset=k_at + 8)
    return PvfSlot(scalar_size=size, eigenvalues=reader.array(p + "eigenvalues", dtype, k),
                   mean=reader.array(p + "mean", dtype, dim),
                   Cs=reader.memmap(p + "Cs", dtype, (dim, k)),
                   Ws=reader.memmap(p + "Ws", dtype, (n_w, k)))


def read_pvf(path: str | os.PathLike) -> Pvf:
    """Read a PVF file (current or legacy layout); Cs and Ws stay in the file as memmaps.

    Raises
    ------
    BonnFormatError
        Wrong signature, truncation, slot count other than n_v, a slot whose dimension fits
        neither orientation, slots of different orientation, trailing bytes.
    """
    with open_reader(path) as reader:
        signature = read_signature(reader)
        if not signature.startswith("!PVF"):
            raise reader.error("signature", f"{signature} is not a PVF file",
                               "open DFMF/FMF with tasks.bonn.dfmf.read_factorised", offset=0)
        legacy = reader.i32("pvf.magic") == PVF_LEGACY_MAGIC
        if legacy:
            header, k, n_slots, slots_at = _read_legacy_header(reader, signature)
        else:
            reader.seek(reader.offset - 4)  # no magic: the common header starts here
            header = read_common_header(reader, signature)
            k = reader.u32("pvf.max_components")
            slots_at = reader.offset
            n_slots = reader.u32("pvf.n_slots")
        if n_slots != header.n_v:
            raise reader.error("pvf.n_slots", f"{n_slots} view slots for {header.n_v} views",
                               _CORRUPT, offset=slots_at)
        slots = [_read_slot(reader, v, header) for v in range(n_slots)]
        _check_end(reader)
    n_c = header.n_channels
    kinds = {"lights" if s.Cs.shape[0] == n_c * header.n_l and s.Ws.shape[0] == header.n_tx
             else "texels" for s in slots}
    if len(kinds) > 1:
        raise BonnFormatError(path, None, "slot[*].dimension", "slots mix both orientations",
                              _CORRUPT)
    return Pvf(path=os.fspath(path), header=header, slots=slots,
               orientation=kinds.pop() if kinds else "lights", legacy=legacy,
               extra={"max_components": k})


def write_pvf(path_or_file: str | os.PathLike | BinaryIO, header: CommonHeader,
              slots: Sequence[PvfSlot], *, legacy: bool = False,
              max_components: int | None = None) -> None:
    """Write a PVF file (for tests and round trips; see :class:`Pvf` for the orientations).

    ``header.signature`` becomes ``!PVF06FCR`` when ``header.rotations`` is not None, else
    ``!PVF06FC``; the legacy layout keeps a PVF signature and writes no meta block and no
    rotations.
    """
    if legacy:
        signature = header.signature if header.signature.startswith("!PVF") else "!PVF06FC"
    else:
        signature = "!PVF06FCR" if header.rotations is not None else "!PVF06FC"
    header = dataclasses.replace(header, signature=signature)
    if len(slots) != header.n_v:
        raise ValueError(f"{len(slots)} slots for {header.n_v} views")
    k_max = max((int(s.Cs.shape[1]) for s in slots), default=0)
    k_max = k_max if max_components is None else max_components
    own = isinstance(path_or_file, (str, os.PathLike))
    f = open(path_or_file, "wb") if own else path_or_file
    try:
        if legacy:
            f.write(signature.encode("ascii"))
            f.write(struct.pack("<iIIII", PVF_LEGACY_MAGIC, k_max, header.width, header.height,
                                header.n_v))
            f.write(struct.pack("<I", header.n_v))
            for v in range(header.n_v):
                lights = np.ascontiguousarray(header.light_angles[v], "<f4")
                f.write(np.ascontiguousarray(header.view_angles[v], "<f4").tobytes())
                f.write(struct.pack("<I", lights.shape[0]) + lights.tobytes())
        else:
            write_common_header(f, header)
            f.write(struct.pack("<II", k_max, header.n_v))
        for v, s in enumerate(slots):
            dtype = _scalar_dtype(s.scalar_size)
            dim, k = s.Cs.shape
            f.write(struct.pack("<BIII", s.scalar_size, k, s.Ws.shape[0], dim))
            f.write(np.ascontiguousarray(s.eigenvalues, dtype).tobytes())
            f.write(np.ascontiguousarray(s.mean, dtype).tobytes())
            for name, a in ((f"Cs[{v}]", s.Cs), (f"Ws[{v}]", s.Ws)):
                for block in _blocks(a, dtype, name):
                    f.write(block)
    finally:
        if own:
            f.close()


def rewrite_pvf(pvf: Pvf, path: str | os.PathLike | BinaryIO) -> None:
    """Write ``pvf`` back in its own layout: byte-identical to what was read."""
    write_pvf(path, pvf.header, pvf.slots, legacy=pvf.legacy,
              max_components=pvf.extra.get("max_components"))
