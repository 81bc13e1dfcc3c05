"""OpenEXR export of BTF textures (``btf export-exr``).

A texture with NaN or Inf texels is refused, before any file is written,
unless the caller asks to keep them (``--keep-nonfinite``): an EXR viewer or
renderer shows them as black or white holes, and nothing downstream says so.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np
import zarr

from tasks.staging import write_file
from tasks.stores.btf import BtfStore, open_btf_store


def parse_selection(text: str | None, n_lv: int) -> list[int]:
    """Rows to export from ``"all"``/``None`` or a comma list of indices and ``a-b`` ranges."""
    if text in (None, "", "all"):
        return list(range(n_lv))
    rows: list[int] = []
    for part in text.split(","):
        part = part.strip()
        try:
            if "-" in part:
                a, b = (int(v) for v in part.split("-", 1))
                rows.extend(range(a, b + 1))
            else:
                rows.append(int(part))
        except ValueError:
            raise ValueError(f"--lv {text!r}: {part!r} is neither an index nor a range a-b") from None
    bad = [r for r in rows if not 0 <= r < n_lv]
    if bad:
        raise ValueError(f"--lv {text!r}: indices {bad[:5]} are outside 0..{n_lv - 1}")
    return rows


class _RowReader:
    """Rows of the ``btf`` array read one chunk of rows at a time (a chunk is a view's LEDs: reading one
    row reads its whole chunk, so consecutive rows share a read)."""

    def __init__(self, btf: zarr.Array) -> None:
        self.btf, self.step = btf, int(btf.chunks[0])
        self.start, self.block = -1, None

    def __call__(self, row: int) -> np.ndarray:
        start = row - row % self.step
        if start != self.start:
            self.start, self.block = start, self.btf[start:start + self.step]
        return self.block[row - start]


def nonfinite_texels(btf_path: str | os.PathLike, rows: Sequence[int]) -> dict[int, int]:
    """``{row: texels with a NaN or Inf channel}`` of the rows of a BTF store that have any.

    Parameters
    ----------
    btf_path : path
        A ``btf-texture`` store.
    rows : sequence of int
        Rows of its ``btf`` array (n_lv, h, w, C) to check; read a chunk of
        rows at a time.
    """
    btf = BtfStore(btf_path).btf
    read, bad = _RowReader(btf), {}
    for row in sorted(set(rows)):
        count = int((~np.isfinite(read(row))).any(axis=-1).sum())
        if count:
            bad[row] = count
    return bad


def export_exr(btf_path: str | os.PathLike, out_dir: str | os.PathLike, rows: Sequence[int] | None = None, *,
               keep_nonfinite: bool = False) -> list[Path]:
    """Write the selected textures of a BTF store as ``lv<index>_t<t>_c<c>_l<l>.exr`` (float32 RGB, ZIP);
    a resampled store's (``lv_order`` view, light) as ``lv<index>_v<v>_l<l>.exr``.

    Light and view directions go into each file's header (``btf_light_dir``,
    ``btf_view_dir``, sample frame) so a file is self-describing.

    Parameters
    ----------
    btf_path : path
        A ``btf-texture`` store; ``btf`` is (n_lv, h, w, 3).
    out_dir : path
        Folder of the files (created).
    rows : sequence of int, optional
        Rows to export (default all).
    keep_nonfinite : bool
        Write textures with NaN or Inf texels as they are. Without it every
        selected row is checked first (:func:`nonfinite_texels`, one more
        read of the rows) and such a row is refused before any file is
        written or the folder created.

    Raises
    ------
    ValueError
        Not a BTF store, or non-finite texels: one line naming the store,
        the first rows and their counts of non-finite texels, and
        ``--keep-nonfinite``.
    """
    import OpenEXR

    store = open_btf_store(btf_path, require_complete=False, produced_by="`btf ingest`")
    group, btf = store.group, store.btf
    rows = list(range(btf.shape[0])) if rows is None else list(rows)
    if not keep_nonfinite:
        bad = nonfinite_texels(btf_path, rows)
        if bad:
            h, w = btf.shape[1:3]
            listed = ", ".join(f"row {r}: {n} of {h * w} texels" for r, n in list(bad.items())[:5])
            more = f" and {len(bad) - 5} more rows" if len(bad) > 5 else ""
            raise ValueError(f"{btf_path}: btf has NaN or Inf texels in {len(bad)} of the {len(rows)} selected rows "
                             f"({listed}{more}); nothing was written: leave those rows out with --lv, rebuild the "
                             "store with the command that wrote it, or export them as they are with --keep-nonfinite")
    light, view, index = group["light_dir"][...], group["view_dir"][...], group["lv_index"][...]
    order = group.attrs.get("lv_order", ["turntable", "camera", "light"])
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    read = _RowReader(btf)
    for row in rows:
        texture = np.ascontiguousarray(read(row), dtype=np.float32)
        name = "_".join(f"{axis[0]}{int(i)}" for axis, i in zip(order, index[row]))
        path = out / f"lv{row:05d}_{name}.exr"
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                  "btf_light_dir": light[row].astype(np.float32).tolist().__repr__(),
                  "btf_view_dir": view[row].astype(np.float32).tolist().__repr__()}

        def write(tmp: Path) -> None:
            with OpenEXR.File(header, {"RGB": texture}) as f:
                f.write(str(tmp))
        write_file(path, write)  # a finished file is never half-written
        written.append(path)
    return written
