"""OpenEXR export of BTF textures (``btf export-exr``)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np
import zarr


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


def export_exr(btf_path: str | os.PathLike, out_dir: str | os.PathLike, rows: Sequence[int] | None = None) -> list[Path]:
    """Write the selected textures of a BTF store as ``lv<index>_t<t>_c<c>_l<l>.exr`` (float32 RGB, ZIP);
    a resampled store's (``lv_order`` view, light) as ``lv<index>_v<v>_l<l>.exr``.

    Light and view directions go into each file's header (``btf_light_dir``,
    ``btf_view_dir``, sample frame) so a file is self-describing.
    """
    import OpenEXR

    group = zarr.open_group(str(btf_path), mode="r", zarr_format=3)
    if group.attrs.get("schema") != "btf-texture":
        raise ValueError(f"{btf_path}: not a BTF store (schema {group.attrs.get('schema')!r}); "
                         "give the output of `btf ingest`")
    btf = group["btf"]
    rows = list(range(btf.shape[0])) if rows is None else list(rows)
    light, view, index = group["light_dir"][...], group["view_dir"][...], group["lv_index"][...]
    order = group.attrs.get("lv_order", ["turntable", "camera", "light"])
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for row in rows:
        texture = np.ascontiguousarray(btf[row], dtype=np.float32)
        name = "_".join(f"{axis[0]}{int(i)}" for axis, i in zip(order, index[row]))
        path = out / f"lv{row:05d}_{name}.exr"
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                  "btf_light_dir": light[row].astype(np.float32).tolist().__repr__(),
                  "btf_view_dir": view[row].astype(np.float32).tolist().__repr__()}
        tmp = path.with_suffix(".exr.tmp")
        with OpenEXR.File(header, {"RGB": texture}) as f:
            f.write(str(tmp))
        tmp.replace(path)  # a finished file is never half-written
        written.append(path)
    return written
