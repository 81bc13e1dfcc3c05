"""Signature and common header of the Bonn BTF formats (docs/bonn-formats.md, "File layout").

Every Bonn format (DFMF, FMF, BDI and the current PVF) starts with a signature string, then the
common header: the meta block (strings, scale factors, cosine flag, XML, channel names), the
angular sampling, the texture size and, when the signature ends in ``R``, a rotations block.

All reads go through :class:`ByteReader`, which checks every count against the bytes left in the
file *before* reading or allocating, so a crafted header fails fast with a
:class:`~tasks.bonn.errors.BonnFormatError` naming the file, the byte offset and the field.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import struct
from dataclasses import dataclass, field
from typing import BinaryIO, Iterator, Sequence

import numpy as np

from tasks.bonn.errors import BonnFormatError

#: Signature string -> format. The longest match wins (``!FMF06FCR`` over ``!FMF06FC``).
SIGNATURES: dict[str, str] = {
    "!DFMF08FCR": "dfmf",
    "!FMF12FCER": "fmf12",
    "!FMF06FCR": "fmf",
    "!FMF06FC": "fmf",
    "!PVF06FCR": "pvf",
    "!PVF06FC": "pvf",
    "!BDIF06R2!": "bdi",
}
#: Meta block versions this reader knows (btflib writes 4).
META_VERSIONS = (1, 2, 3, 4)
#: The three fixed-length NUL-padded strings of the meta block.
STRING_BYTES = 80
_TRUNCATED_FIX = ("the file is truncated or this field is corrupt: copy or export the file again "
                  "and compare its size with the source")


class ByteReader:
    """Little-endian reads from a binary file that never go past its end.

    Parameters
    ----------
    f : binary file object
        Open for reading, seekable.
    path : str or os.PathLike
        The file's name, for error messages.
    size : int
        The file's size in bytes.

    Attributes
    ----------
    offset : int
        Byte offset of the next read.
    """

    def __init__(self, f: BinaryIO, path: str | os.PathLike, size: int) -> None:
        self.f = f
        self.path = os.fspath(path)
        self.size = int(size)
        self.offset = int(f.tell())

    @property
    def left(self) -> int:
        """Bytes between :attr:`offset` and the end of the file."""
        return self.size - self.offset

    def error(self, field: str, message: str, fix: str, offset: int | None = None) -> BonnFormatError:
        """A :class:`BonnFormatError` for this file at ``offset`` (default: the current offset)."""
        return BonnFormatError(self.path, self.offset if offset is None else offset, field,
                               message, fix)

    def require(self, field: str, nbytes: int, at: int | None = None) -> None:
        """Raise (truncated) unless ``nbytes`` are left; reads and allocates nothing.

        ``at``: the offset to name in the error (default: the current one), e.g. that of the
        count field that claimed ``nbytes``.
        """
        nbytes = int(nbytes)
        if nbytes < 0 or nbytes > self.left:
            raise self.error(field, f"needs {nbytes} bytes from byte {self.offset} but only "
                                    f"{self.left} are left (file is {self.size} bytes)",
                             _TRUNCATED_FIX, offset=at)

    def read(self, field: str, nbytes: int) -> bytes:
        """``nbytes`` raw bytes (checked first)."""
        self.require(field, nbytes)
        if self.f.tell() != self.offset:
            self.f.seek(self.offset)
        data = self.f.read(nbytes)
        if len(data) != nbytes:  # the file shrank under us
            raise self.error(field, f"read {len(data)} of {nbytes} bytes", _TRUNCATED_FIX)
        self.offset += nbytes
        return data

    def skip(self, field: str, nbytes: int) -> None:
        """Move ``nbytes`` forward (checked first)."""
        self.require(field, nbytes)
        self.offset += int(nbytes)

    def seek(self, offset: int) -> None:
        """Move to absolute ``offset`` (checked against the file size)."""
        if not 0 <= offset <= self.size:
            raise self.error("offset", f"offset {offset} is outside the file ({self.size} bytes)",
                             _TRUNCATED_FIX)
        self.offset = int(offset)

    def u8(self, field: str) -> int:
        return self.read(field, 1)[0]

    def u32(self, field: str) -> int:
        return struct.unpack("<I", self.read(field, 4))[0]

    def i32(self, field: str) -> int:
        return struct.unpack("<i", self.read(field, 4))[0]

    def f32(self, field: str, n: int = 1) -> float | np.ndarray:
        """One float32 as a Python float (``n == 1``) or an ``(n,)`` float32 array."""
        values = np.frombuffer(self.read(field, 4 * n), dtype="<f4")
        return float(values[0]) if n == 1 else values.astype(np.float32)

    def bytes(self, field: str, n: int) -> bytes:
        """``n`` raw bytes (alias of :meth:`read`)."""
        return self.read(field, n)

    def string(self, field: str, n: int) -> str:
        """``n`` bytes decoded latin-1, NULs stripped from the end (raw bytes: :meth:`bytes`)."""
        return _decode_padded(self.read(field, n))

    def array(self, field: str, dtype, count: int) -> np.ndarray:
        """``count`` scalars of ``dtype`` read into memory (only for small, checked arrays)."""
        dtype = np.dtype(dtype).newbyteorder("<")
        count = int(count)
        if count < 0:
            raise self.error(field, f"negative count {count}", _TRUNCATED_FIX)
        return np.frombuffer(self.read(field, dtype.itemsize * count), dtype=dtype).copy()

    def memmap(self, field: str, dtype, shape: Sequence[int]) -> np.ndarray:
        """A read-only ``np.memmap`` of ``shape`` at the current offset, then skip past it.

        The byte count is checked against the file size first; nothing is read.
        """
        dtype = np.dtype(dtype).newbyteorder("<")
        shape = tuple(int(s) for s in shape)
        nbytes = dtype.itemsize * int(np.prod(shape, dtype=object))
        self.require(field, nbytes)
        if nbytes == 0:
            out = np.zeros(shape, dtype=dtype)
        else:
            out = np.memmap(self.path, dtype=dtype, mode="r", offset=self.offset, shape=shape)
        self.offset += nbytes
        return out


@contextlib.contextmanager
def open_reader(path: str | os.PathLike) -> Iterator[ByteReader]:
    """Open ``path`` for reading and yield a :class:`ByteReader` at byte 0."""
    path = os.fspath(path)
    with open(path, "rb") as f:
        yield ByteReader(f, path, os.fstat(f.fileno()).st_size)


def _decode_padded(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("latin-1") if b"\0" in raw else raw.decode("latin-1")


def _decode_text(raw: bytes) -> str:
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def sph_to_dir(angles: np.ndarray) -> np.ndarray:
    """(theta, phi) radians ``(..., 2)`` -> unit vectors ``(..., 3)`` float64, z = normal."""
    a = np.asarray(angles, dtype=np.float64)
    t, p = a[..., 0], a[..., 1]
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)


@dataclass(frozen=True, eq=False)
class CommonHeader:
    """Meta block, angular sampling, texture size and rotations of a Bonn BTF file.

    Attributes
    ----------
    signature : str
        E.g. ``"!DFMF08FCR"`` (a key of :data:`SIGNATURES`).
    version : int
        Meta block version (1-4); fields 5-7 of the meta block exist from versions 2, 3, 4 on.
    measurement_setup, image_sensor, light_source : str
        The three 80-byte NUL-padded strings, decoded latin-1.
    ppmm : float
        Pixels per millimetre.
    rgb_scale_factor : tuple of 3 float
    cosine_flag : bool
        Set: the data has cos(theta_l) multiplied in (readers divide by it).
    xml : str
        Measurement XML (version >= 3), decoded UTF-8 (latin-1 when not UTF-8).
    channel_names : tuple of str
        ``("R", "G", "B")`` when version <= 3.
    view_angles : ndarray, (n_v, 2) float32
        (theta, phi) radians per view.
    light_angles : tuple of ndarray
        Per view, ``(n_l, 2)`` float32 (theta, phi) radians.
    width, height : int
        Texture size in texels; texel (x, y) has index ``x + width * y``.
    rotations : ndarray or None
        ``(n_rot, 3, 3)`` float32, the 9 floats of each rotation in file order (C order); ``None``
        when the signature has no rotations block.
    raw : dict
        Raw bytes of the strings as read (NUL padding and what follows it), so that writing back
        is byte-identical; used only while the decoded value is unchanged.
    """

    signature: str
    version: int
    measurement_setup: str
    image_sensor: str
    light_source: str
    ppmm: float
    rgb_scale_factor: tuple[float, float, float]
    cosine_flag: bool
    xml: str
    channel_names: tuple[str, ...]
    view_angles: np.ndarray
    light_angles: tuple[np.ndarray, ...]
    width: int
    height: int
    rotations: np.ndarray | None
    raw: dict = field(default_factory=dict, repr=False)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CommonHeader):
            return NotImplemented
        for f in dataclasses.fields(self):
            if f.name == "raw":
                continue
            a, b = getattr(self, f.name), getattr(other, f.name)
            if f.name == "light_angles":
                if len(a) != len(b) or not all(np.array_equal(x, y) for x, y in zip(a, b)):
                    return False
            elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if a is None or b is None or not np.array_equal(a, b):
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]

    @property
    def n_v(self) -> int:
        return int(self.view_angles.shape[0])

    @property
    def n_l(self) -> int:
        """Lights per view; raises ValueError when the views differ."""
        counts = {int(a.shape[0]) for a in self.light_angles}
        if len(counts) > 1:
            raise ValueError(f"views have different light counts {sorted(counts)}: this BTF has no "
                             "single n_l (every Bonn reader requires one)")
        return counts.pop() if counts else 0

    @property
    def n_lv(self) -> int:
        return self.n_l * self.n_v

    @property
    def n_tx(self) -> int:
        return self.width * self.height

    @property
    def n_channels(self) -> int:
        return len(self.channel_names)

    def light_dir(self) -> np.ndarray:
        """``(n_lv, 3)`` float64 unit light directions, row ``l + n_l * v``."""
        self.n_l  # noqa: B018  (raises when the views differ)
        if not self.light_angles:
            return np.zeros((0, 3))
        return sph_to_dir(np.concatenate(self.light_angles, axis=0))

    def view_dir(self) -> np.ndarray:
        """``(n_lv, 3)`` float64 unit view directions, row ``l + n_l * v``."""
        return np.repeat(sph_to_dir(self.view_angles), self.n_l, axis=0)


def make_header(view_angles: np.ndarray, light_angles: np.ndarray | Sequence[np.ndarray],
                width: int, height: int, *, signature: str = "!DFMF08FCR",
                channel_names: Sequence[str] = ("R", "G", "B"), cosine_flag: bool = False,
                xml: str = "", measurement_setup: str = "", image_sensor: str = "",
                light_source: str = "", ppmm: float = 0.0,
                rgb_scale_factor: Sequence[float] = (1.0, 1.0, 1.0),
                rotations: np.ndarray | None = None, version: int = 4) -> CommonHeader:
    """A :class:`CommonHeader` from angles; one ``(n_l, 2)`` light array is used for every view.

    Parameters
    ----------
    view_angles : (n_v, 2) array
        (theta, phi) radians.
    light_angles : (n_l, 2) array or sequence of n_v such arrays
    width, height : int
    rotations : (n_rot, 3, 3) array or None
        ``None`` and a signature ending in ``R`` write an empty rotations block.
    """
    views = np.ascontiguousarray(view_angles, dtype=np.float32).reshape(-1, 2)
    if isinstance(light_angles, np.ndarray) and light_angles.ndim == 2:
        lights = tuple(np.ascontiguousarray(light_angles, dtype=np.float32)
                       for _ in range(views.shape[0]))
    else:
        lights = tuple(np.ascontiguousarray(a, dtype=np.float32).reshape(-1, 2) for a in light_angles)
    if signature not in SIGNATURES:
        raise ValueError(f"unknown signature {signature!r}; known: {sorted(SIGNATURES)}")
    if rotations is not None:
        rotations = np.ascontiguousarray(rotations, dtype=np.float32).reshape(-1, 3, 3)
    elif signature.endswith("R"):
        rotations = np.zeros((0, 3, 3), np.float32)
    return CommonHeader(signature=signature, version=int(version),
                        measurement_setup=measurement_setup, image_sensor=image_sensor,
                        light_source=light_source, ppmm=float(np.float32(ppmm)),
                        rgb_scale_factor=tuple(float(np.float32(v)) for v in rgb_scale_factor),
                        cosine_flag=bool(cosine_flag), xml=xml,
                        channel_names=tuple(channel_names), view_angles=views,
                        light_angles=lights, width=int(width), height=int(height),
                        rotations=rotations)


def read_signature(reader: ByteReader) -> str:
    """Read the signature at the reader's offset; the longest known one that matches wins.

    Raises
    ------
    BonnFormatError
        When no known signature starts the file.
    """
    start = reader.offset
    longest = max(len(s) for s in SIGNATURES)
    head = reader.read("signature", min(longest, reader.left)) if reader.left else b""
    matches = [s for s in SIGNATURES if head.startswith(s.encode("ascii"))]
    if not matches:
        raise reader.error("signature", f"unknown signature {head!r}; known: {sorted(SIGNATURES)}",
                           "this is not a Bonn BTF file (DFMF, FMF, PVF, BDI) or its first bytes "
                           "are damaged", offset=start)
    signature = max(matches, key=len)
    reader.seek(start + len(signature))
    return signature


def _check_meta_room(reader: ByteReader, end: int, field_name: str, nbytes: int, size: int,
                     start: int, at: int | None) -> None:
    if reader.offset + nbytes > end:
        raise reader.error(field_name, f"the meta block's size field (byte {start}) says {size} "
                                       f"bytes, but {nbytes} bytes from byte {reader.offset} "
                                       f"reach past its end {end}",
                           "the meta size does not add up: the header is corrupt", offset=at)


def _read_meta(reader: ByteReader) -> dict:
    start = reader.offset
    size = reader.u32("meta.size")
    if size < 4:
        raise reader.error("meta.size", f"size {size} is smaller than the size field itself",
                           "the meta size does not add up: the header is corrupt", offset=start)
    reader.require("meta.size", size - 4, at=start)  # the whole meta block lies in the file
    end = start + size

    def room(name: str, nbytes: int, at: int | None = None) -> None:
        _check_meta_room(reader, end, name, nbytes, size, start, at)

    room("meta.version", 4)
    version_at = reader.offset
    version = reader.u32("meta.version")
    if version not in META_VERSIONS:
        raise reader.error("meta.version", f"unknown meta block version {version}; known "
                                           f"{list(META_VERSIONS)}",
                           "the header is corrupt or newer than this reader", offset=version_at)
    out: dict = {"version": version, "raw": {}}
    room("meta.strings", 3 * STRING_BYTES + 16)
    for name in ("measurement_setup", "image_sensor", "light_source"):
        raw = reader.bytes(f"meta.{name}", STRING_BYTES)
        out[name] = _decode_padded(raw)
        out["raw"][name] = raw
    out["ppmm"] = reader.f32("meta.ppmm")
    out["rgb_scale_factor"] = tuple(float(v) for v in reader.f32("meta.rgb_scale_factor", 3))
    out["cosine_flag"] = False
    if version > 1:
        room("meta.cosine_flag", 4)
        value = reader.u32("meta.cosine_flag")
        out["cosine_flag"] = bool(value)
        if value not in (0, 1):
            out["raw"]["cosine_flag"] = value
    out["xml"] = ""
    if version > 2:
        room("meta.xml_length", 4)
        at = reader.offset
        n = reader.u32("meta.xml_length")
        room("meta.xml_length", n, at=at)
        raw = reader.bytes("meta.xml", n)
        out["xml"] = _decode_text(raw)
        out["raw"]["xml"] = raw
    out["channel_names"] = ("R", "G", "B")
    if version > 3:
        room("meta.n_channels", 4)
        at = reader.offset
        n_ch = reader.u32("meta.n_channels")
        if n_ch == 0:
            raise reader.error("meta.n_channels", "the file declares 0 colour channels",
                               "the header is corrupt", offset=at)
        room("meta.n_channels", 4 * n_ch, at=at)
        names, raws = [], []
        for c in range(n_ch):
            room(f"meta.channel_names[{c}].length", 4)
            at = reader.offset
            n = reader.u32(f"meta.channel_names[{c}].length")
            room(f"meta.channel_names[{c}].length", n, at=at)
            raw = reader.bytes(f"meta.channel_names[{c}]", n)
            names.append(_decode_text(raw))
            raws.append(raw)
        out["channel_names"] = tuple(names)
        out["raw"]["channel_names"] = tuple(raws)
    if reader.offset != end:
        raise reader.error("meta.size", f"the size field says {size} bytes but the meta block of "
                                        f"version {version} takes {reader.offset - start}",
                           "the meta size does not add up: the header is corrupt", offset=start)
    return out


def _read_angles(reader: ByteReader, field_name: str, n: int) -> np.ndarray:
    at = reader.offset
    a = reader.array(field_name, "<f4", 2 * n).reshape(n, 2)
    if not np.all(np.isfinite(a)):
        bad = int(np.argwhere(~np.isfinite(a))[0, 0])
        raise reader.error(field_name, f"angle pair {bad} is not finite ({a[bad].tolist()})",
                           "the angular sampling is corrupt", offset=at + 8 * bad)
    return a.astype(np.float32)


def _read_sampling(reader: ByteReader) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    at = reader.offset
    n_v = reader.u32("sampling.n_v")
    reader.require("sampling.n_v", 12 * n_v, at=at)  # per view: 2 float32 + uint32 at least
    views = np.empty((n_v, 2), np.float32)
    lights: list[np.ndarray] = []
    for v in range(n_v):
        views[v] = _read_angles(reader, f"sampling.view_angles[{v}]", 1)[0]
        at = reader.offset
        n_l = reader.u32(f"sampling.n_l[{v}]")
        reader.require(f"sampling.n_l[{v}]", 8 * n_l, at=at)
        if lights and n_l != lights[0].shape[0]:
            raise reader.error(f"sampling.n_l[{v}]",
                               f"view {v} has {n_l} lights, view 0 has {lights[0].shape[0]}",
                               "every Bonn format needs the same light count per view", offset=at)
        lights.append(_read_angles(reader, f"sampling.light_angles[{v}]", n_l))
    return views, tuple(lights)


def read_common_header(reader: ByteReader, signature: str) -> CommonHeader:
    """Read the meta block, angular sampling, width, height and (``...R``) the rotations.

    ``reader`` stands right after the signature (:func:`read_signature`).

    Raises
    ------
    BonnFormatError
        Truncation, a meta size that does not add up, unknown meta version, differing light
        counts per view, non-finite angles.
    """
    meta = _read_meta(reader)
    views, lights = _read_sampling(reader)
    width = reader.u32("width")
    height = reader.u32("height")
    rotations = None
    if signature.endswith("R"):
        at = reader.offset
        n_rot = reader.u32("rotations.n_rot")
        reader.require("rotations.n_rot", 36 * n_rot, at=at)
        rotations = reader.array("rotations", "<f4", 9 * n_rot).reshape(n_rot, 3, 3)
    return CommonHeader(signature=signature, version=meta["version"],
                        measurement_setup=meta["measurement_setup"],
                        image_sensor=meta["image_sensor"], light_source=meta["light_source"],
                        ppmm=meta["ppmm"], rgb_scale_factor=meta["rgb_scale_factor"],
                        cosine_flag=meta["cosine_flag"], xml=meta["xml"],
                        channel_names=meta["channel_names"], view_angles=views,
                        light_angles=lights, width=width, height=height, rotations=rotations,
                        raw=meta["raw"])


def _padded(header: CommonHeader, name: str) -> bytes:
    text = getattr(header, name)
    raw = header.raw.get(name)
    if raw is not None and _decode_padded(raw) == text:
        return raw
    data = text.encode("latin-1")
    if len(data) > STRING_BYTES:
        raise ValueError(f"{name} {text!r} is longer than {STRING_BYTES} bytes")
    return data.ljust(STRING_BYTES, b"\0")


def _text(raw: bytes | None, text: str) -> bytes:
    if raw is not None and _decode_text(raw) == text:
        return raw
    return text.encode("utf-8")


def meta_bytes(header: CommonHeader) -> bytes:
    """The meta block of ``header``, size field included."""
    if header.version not in META_VERSIONS:
        raise ValueError(f"meta version {header.version} is not one of {list(META_VERSIONS)}")
    body = [struct.pack("<I", header.version)]
    body += [_padded(header, n) for n in ("measurement_setup", "image_sensor", "light_source")]
    body.append(struct.pack("<4f", header.ppmm, *header.rgb_scale_factor))
    if header.version > 1:
        flag = header.raw.get("cosine_flag")
        body.append(struct.pack("<I", flag if flag is not None and header.cosine_flag
                                else int(header.cosine_flag)))
    if header.version > 2:
        xml = _text(header.raw.get("xml"), header.xml)
        body += [struct.pack("<I", len(xml)), xml]
    if header.version > 3:
        raws = header.raw.get("channel_names") or ()
        body.append(struct.pack("<I", len(header.channel_names)))
        for c, name in enumerate(header.channel_names):
            data = _text(raws[c] if c < len(raws) else None, name)
            body += [struct.pack("<I", len(data)), data]
    elif header.channel_names != ("R", "G", "B"):
        raise ValueError(f"meta version {header.version} cannot store channel names "
                         f"{header.channel_names}: use version 4")
    blob = b"".join(body)
    return struct.pack("<I", len(blob) + 4) + blob


def write_common_header(f: BinaryIO, header: CommonHeader) -> None:
    """Write signature, meta block, sampling, width, height and (``...R``) rotations.

    The exact inverse of :func:`read_signature` + :func:`read_common_header`. A signature not
    ending in ``R`` writes no rotations (BDI writes its rotations after the mask itself).
    """
    if header.signature not in SIGNATURES:
        raise ValueError(f"unknown signature {header.signature!r}; known: {sorted(SIGNATURES)}")
    if len(header.light_angles) != header.n_v:
        raise ValueError(f"{header.n_v} views but {len(header.light_angles)} light arrays")
    parts = [header.signature.encode("ascii"), meta_bytes(header),
             struct.pack("<I", header.n_v)]
    for v in range(header.n_v):
        lights = np.ascontiguousarray(header.light_angles[v], dtype="<f4").reshape(-1, 2)
        parts += [np.ascontiguousarray(header.view_angles[v], dtype="<f4").tobytes(),
                  struct.pack("<I", lights.shape[0]), lights.tobytes()]
    parts.append(struct.pack("<II", header.width, header.height))
    if header.signature.endswith("R"):
        rot = (np.zeros((0, 3, 3), "<f4") if header.rotations is None
               else np.ascontiguousarray(header.rotations, dtype="<f4").reshape(-1, 3, 3))
        parts += [struct.pack("<I", rot.shape[0]), rot.tobytes()]
    f.write(b"".join(parts))
