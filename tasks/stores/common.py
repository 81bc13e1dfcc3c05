"""What every store kind shares: problems and the "list every problem" error, plain-JSON attributes,
whole-chunk writes and store paths (docs/architecture.md, "Storage contract").

Each store kind (:mod:`tasks.stores.capture`, :mod:`tasks.stores.btf`, :mod:`tasks.stores.measurement`)
reports what is wrong with a store as :class:`Problem` records and raises them all at once in a
subclass of :class:`StoreProblemsError`.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import zarr

from tasks.integrity import CorruptChunkError, write_chunks_directly

#: How many offending indices a problem lists before summarising.
MAX_LISTED = 10
#: ``Problem.array`` of a problem with the store as a whole (missing, unreadable).
WHOLE_STORE = "<store>"
#: ``Problem.array`` of a problem with the root attributes.
ROOT_ATTRS = "attrs"


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a store.

    Parameters
    ----------
    array : str
        Array path inside the store (``"raw"``, ``"truth/btf"``), ``"attrs"``
        (:data:`ROOT_ATTRS`) for root attributes or ``"<store>"`` (:data:`WHOLE_STORE`) for the store as a whole.
    index : str or None
        Offending index, attribute key or axis, e.g. ``"(t, c, i)=(1, 0, 2)"``.
    expected : str
        What the schema requires.
    found : str
        What the store holds.
    hint : str
        What to do about it.
    """

    array: str
    index: str | None
    expected: str
    found: str
    hint: str

    def __str__(self) -> str:
        where = self.array if self.index is None else f"{self.array}[{self.index}]"
        return f"{where}: expected {self.expected}; found {self.found}. Fix: {self.hint}"


class StoreProblemsError(ValueError):
    """A store (or the metadata for one) violates its schema; every problem is listed, not only the first.

    Subclasses name the store kind (``kind``) and its schema (``schema``) for the message's head line.

    Parameters
    ----------
    path : str
        Store path or URL.
    problems : list of Problem
        Every problem found.
    """

    kind = "store"
    schema = ""

    def __init__(self, path: Any, problems: Sequence[Problem]) -> None:
        self.path = str(path)
        self.problems: list[Problem] = list(problems)
        super().__init__(self._format())

    def _format(self) -> str:
        n = len(self.problems)
        schema = f" ({self.schema})" if self.schema else ""
        head = f"{self.kind} {self.path!r}{schema} has {n} problem{'s' if n != 1 else ''}:"
        return "\n".join([head] + [f"  - {self.path}: {p}" for p in self.problems])

    def __reduce__(self):  # picklable across Dask / Prefect process boundaries
        return (type(self), (self.path, self.problems))


def to_json_attr(value: Any, where: str = "attrs") -> Any:
    """Convert a value into plain JSON for Zarr attributes.

    numpy scalars and arrays become Python numbers and lists, tuples become
    lists. NaN and infinities are refused, since they serialise to
    non-standard JSON (docs/architecture.md, "Storage contract").

    Parameters
    ----------
    value : Any
        Nested dicts / lists / tuples of str, bool, int, float, None and numpy
        scalars or arrays.
    where : str
        Key path used in error messages.

    Returns
    -------
    Any
        A value that :func:`json.dumps` accepts with ``allow_nan=False``.

    Raises
    ------
    ValueError
        For NaN / Inf, naming the key path.
    TypeError
        For values that have no JSON form, naming the key path.
    """
    if isinstance(value, np.ndarray):
        return [to_json_attr(v, f"{where}[{k}]") for k, v in enumerate(value.tolist())]
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(
                f"{where} is {value!r}; attributes must be finite JSON numbers "
                "(store null for unknown values)"
            )
        return float(value)
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise TypeError(f"{where} has a non-string key {k!r}; JSON keys must be str")
            out[k] = to_json_attr(v, f"{where}[{k!r}]")
        return out
    if isinstance(value, (list, tuple)):
        return [to_json_attr(v, f"{where}[{k}]") for k, v in enumerate(value)]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"{where} is a {type(value).__name__}, which has no JSON form")


def fmt_idx(idx: Sequence[int]) -> str:
    """``(1, 0, 2)``."""
    return "(" + ", ".join(str(int(i)) for i in idx) + ")"


def listing(indices: np.ndarray, limit: int = MAX_LISTED) -> str:
    """Format the first ``limit`` rows of an ``(n, ndim)`` index array."""
    n = len(indices)
    shown = ", ".join(fmt_idx(i) for i in indices[:limit])
    return shown + (f" (+{n - limit} more, {n} in all)" if n > limit else "")


def is_url(path: Any) -> bool:
    """Whether ``path`` is an fsspec URL (``"s3://..."``) rather than a local path."""
    return isinstance(path, str) and "://" in path


def store_arg(path: Any) -> Any:
    """``path`` as Zarr's ``open_group`` takes it: a URL as is, a local path as ``str``."""
    return path if is_url(path) else os.fspath(path)


def _normalise_selection(array: zarr.Array, selection: Any) -> tuple[tuple[slice, ...], tuple[int, ...]]:
    if not isinstance(selection, tuple):
        selection = (selection,)
    if any(s is Ellipsis for s in selection):
        k = selection.index(Ellipsis)
        fill = array.ndim - (len(selection) - 1)
        selection = selection[:k] + (slice(None),) * fill + selection[k + 1:]
    if len(selection) > array.ndim:
        raise ValueError(f"selection {selection!r} has more entries than {array.ndim} dimensions")
    selection = selection + (slice(None),) * (array.ndim - len(selection))
    out, dropped = [], []
    for ax, (s, n) in enumerate(zip(selection, array.shape)):
        if isinstance(s, (int, np.integer)):
            i = int(s) + (n if s < 0 else 0)
            if not 0 <= i < n:
                raise IndexError(f"index {s} out of range for axis {ax} of length {n}")
            out.append(slice(i, i + 1))
            dropped.append(ax)
        elif isinstance(s, slice):
            start, stop, step = s.indices(n)
            if step != 1:
                raise ValueError(f"axis {ax}: step {step} is not a contiguous block")
            out.append(slice(start, stop))
        else:
            raise ValueError(f"axis {ax}: only ints and contiguous slices are chunk-aligned, got {s!r}")
    return tuple(out), tuple(dropped)


def write_chunk_aligned(array: zarr.Array, selection: Any, data: np.ndarray) -> None:
    """Write ``data`` into ``array[selection]`` only if it covers whole chunks.

    Parallel writers that share a chunk silently lose data (each rewrites the
    whole chunk from what it read), so every write must cover whole chunks
    (docs/architecture.md, "Storage contract"). Where Zarr adds only copies,
    the chunk files are written directly, past the page cache
    (:func:`tasks.integrity.write_chunks_directly`).

    Parameters
    ----------
    array : zarr.Array
        Target array (not sharded).
    selection : int, slice, Ellipsis or tuple of those
        A block: ints and slices with step 1.
    data : ndarray
        Values, broadcastable to the selection.

    Raises
    ------
    ValueError
        If a block edge does not fall on a chunk boundary (or the array end),
        naming the axis, the edges and the chunk length.
    """
    sel, dropped = _normalise_selection(array, selection)
    for ax, (s, c, n) in enumerate(zip(sel, array.chunks, array.shape)):
        if s.start % c or (s.stop % c and s.stop != n) or s.stop <= s.start:
            raise ValueError(
                f"write to {array.path or array.name}{list(zip([x.start for x in sel], [x.stop for x in sel]))} "
                f"is not chunk-aligned on axis {ax}: [{s.start}, {s.stop}) with chunk length {c} "
                f"(array length {n}); writers must own whole chunks, so write the whole block "
                f"[{s.start // c * c}, {min(n, -(-s.stop // c) * c)})")
    full = tuple(s.stop - s.start for s in sel)
    natural = tuple(n for ax, n in enumerate(full) if ax not in dropped)
    data = np.asarray(data)
    if data.shape != full:
        try:
            data = np.broadcast_to(data, natural).reshape(full)
        except ValueError as e:
            raise ValueError(
                f"data of shape {data.shape} does not fit the block of shape {natural}") from e
    if not write_chunks_directly(array, sel, data):
        array[sel] = data


def read_whole(name: str, array: zarr.Array, problems: list[Problem]) -> np.ndarray | None:
    """A small array, read whole; a chunk that does not read back is a problem (``None``)."""
    try:
        return np.asarray(array[...])
    except CorruptChunkError as e:
        problems.append(Problem(name, f"chunk {e.chunk}", "a chunk that reads back as written", e.problem, e.hint))
        return None


def root_attr_problems(attrs: Mapping[str, Any], required: Sequence[str], schema: str, version: str,
                       rewrite: str) -> list[Problem]:
    """The root attributes of ``required`` that a store lacks, and a ``schema_version`` other than ``version``
    (``rewrite``: how to write the store again, e.g. ``"write the store again with `btf ingest`"``)."""
    problems = [Problem(ROOT_ATTRS, key, f"attribute {key!r}", "nothing", f"the store is incomplete; {rewrite}")
                for key in required if key not in attrs]
    if "schema_version" in attrs and attrs["schema_version"] != version:
        problems.append(Problem(ROOT_ATTRS, "schema_version", repr(version), repr(attrs["schema_version"]),
                                f"this code reads {schema} {version}; use the btf-pipeline version that wrote the "
                                "store or write it again"))
    return problems


def json_key(payload: Any) -> str:
    """The content key of a plain-JSON ``payload``: the first 16 hex digits of the SHA-256 of its JSON with
    sorted keys (values JSON cannot hold by their ``str``). Every stage's resumption key (``ingest_hash``,
    ``config_hash``, a basis' ``key``, ...) is one."""
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]
