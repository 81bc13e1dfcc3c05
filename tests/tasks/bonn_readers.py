"""Run one independent Bonn BTF reader on a file and save what it returns, raw, to an ``.npz``.

Not a test module: ``tests/tasks/test_bonn_independent.py`` runs it with the python of the readers'
venv (``make test`` builds ``.venv-readers``; numpy < 2, which the project's venv cannot hold), and
``benchmarks/bench_bonn_decode.py`` times btf-extractor with it. It imports nothing of the project.

Usage::

    python bonn_readers.py btf-extractor FILE OUT.npz [--time-only]
    python bonn_readers.py pysmtb FILE OUT.npz

What is saved is what the reader returns, quirks included (docs/bonn-formats.md, "Independent readers");
the test undoes them, never this script:

* ``btf-extractor``: ``btf_extractor.Ubo2014(FILE)`` (btf.hh's ``LoadBTF``), then
  ``_angleindex_to_image_unsafe(l, v)`` for every light ``l`` and view ``v``: ``images`` ``(n_v, n_l, h, w,
  3)`` float32 exactly as returned (BGR, rows flipped), ``img_shape`` as it reports it, its angle table
  ``angle_keys`` ``(N, 4)`` (theta_l, phi_l, theta_v, phi_v in degrees, rounded to 0.1 by the reader) with
  ``angle_index`` ``(N, 2)`` (light, view), ``load_s`` and ``decode_s`` (the seconds of the constructor and of the
  decoding calls, summed call by call). ``--time-only`` decodes every image but keeps none (``images``
  is then empty and ``checksum`` the float64 sum of the squares of all values, taken outside the
  timed calls).
* ``pysmtb``: ``pysmtb.btf.read_ubo_btf_dfmf(FILE)`` -> ``(meta, data)``: every ``meta`` field as
  ``meta.<name>`` (bytes as uint8 arrays, lists of equal-shaped arrays stacked, per-item otherwise as
  ``meta.<name>.<i>``), ``data.S.<c>``, ``data.U.<c>``, ``data.SxV.<c>`` per channel in the file's dtype.

A reader that raises makes the script exit 1 with the traceback on stderr; btf-extractor on a file its
``LoadBTF`` rejects dereferences a null pointer (the process dies by a signal).
"""

from __future__ import annotations

import sys
import time

import numpy as np


def btf_extractor(path: str, out: str, time_only: bool = False) -> None:
    """Decode every (light, view) image with btf-extractor and save them as returned."""
    from btf_extractor import Ubo2014

    start = time.perf_counter()
    btf = Ubo2014(path)
    load_s = time.perf_counter() - start
    index = btf.angles_vs_index_dict                   # (tl, pl, tv, pv) degrees -> (light, view)
    keys = np.array(list(index.keys()), dtype=np.float64).reshape(-1, 4)
    values = np.array(list(index.values()), dtype=np.int64).reshape(-1, 2)
    # the pair (n_l - 1, n_v - 1) comes last in its table, so it survives keys that collide
    n_l, n_v = (int(values[:, 0].max()) + 1, int(values[:, 1].max()) + 1) if len(values) else (0, 0)
    first = btf._angleindex_to_image_unsafe(0, 0)
    images = np.empty((0,) + first.shape, np.float32) if time_only \
        else np.empty((n_v, n_l) + first.shape, np.float32)
    checksum, decode_s = 0.0, 0.0
    for v in range(n_v):
        for l in range(n_l):
            start = time.perf_counter()
            img = btf._angleindex_to_image_unsafe(l, v)
            decode_s += time.perf_counter() - start
            if time_only:
                checksum += float(np.square(img, dtype=np.float64).sum())
            else:
                images[v, l] = img
    np.savez(out, images=images, img_shape=np.array(btf.img_shape), angle_keys=keys, angle_index=values,
             n_l=n_l, n_v=n_v, load_s=load_s, decode_s=decode_s, checksum=checksum)


def _raw(value) -> np.ndarray | list[np.ndarray]:
    """A field of pysmtb's ``meta`` as an array (bytes as uint8), or a list when it will not stack."""
    if isinstance(value, (bytes, bytearray)):
        return np.frombuffer(bytes(value), dtype=np.uint8)
    if isinstance(value, (list, tuple)) and value and isinstance(value[0], (bytes, bytearray)):
        return [np.frombuffer(bytes(v), dtype=np.uint8) for v in value]
    if isinstance(value, (list, tuple)) and value and isinstance(value[0], (np.ndarray, tuple, list)):
        items = [np.asarray(v) for v in value]
        if all(item.shape == items[0].shape for item in items):
            return np.stack(items)
        return items
    return np.asarray(value)


def pysmtb(path: str, out: str) -> None:
    """Read the file with pysmtb and save ``meta`` and the per-channel factors as returned."""
    from pysmtb.btf import read_ubo_btf_dfmf

    start = time.perf_counter()
    meta, data = read_ubo_btf_dfmf(path)
    arrays = {"load_s": np.float64(time.perf_counter() - start)}
    for name, value in meta.items():
        raw = _raw(value)
        if isinstance(raw, list):
            arrays.update({f"meta.{name}.{i}": item for i, item in enumerate(raw)})
            arrays[f"meta.{name}.count"] = np.int64(len(raw))
        else:
            arrays[f"meta.{name}"] = raw
    for name in ("S", "U", "SxV"):
        for c, array in enumerate(data[name]):
            arrays[f"data.{name}.{c}"] = np.asarray(array)
    np.savez(out, **arrays)


def main(argv: list[str]) -> int:
    if len(argv) < 3 or argv[0] not in {"btf-extractor", "pysmtb"}:
        print(__doc__, file=sys.stderr)
        return 2
    reader, path, out = argv[:3]
    if reader == "btf-extractor":
        btf_extractor(path, out, time_only="--time-only" in argv[3:])
    else:
        pysmtb(path, out)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
