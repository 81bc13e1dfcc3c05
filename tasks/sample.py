"""Sparse sampling of a model-store basis (``btf sample``): read the basis, choose rows, write JSON.

The numerics are :mod:`btfcore.acquisition.sampling`; this module reads a class basis
from a ``btf-model`` store (``btf build-db``), builds the camera-parallel
groups from the store's light/view sampling (or a device's row order), runs
the sampler and writes the result as a ``btf-samples`` JSON file that
``btf plan --samples`` reads back. See ``docs/sampling.md``.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from btfcore.acquisition.sampling import SAMPLING_METHODS, select_samples
from btfcore.dome import Device
from tasks.staging import write_file
from tasks.model import SCHEMA_NAME, read_basis

__all__ = [
    "SAMPLES_SCHEMA",
    "SAMPLING_BASES",
    "camera_parallel_groups",
    "open_model",
    "read_class_basis",
    "read_samples",
    "sample_model",
    "write_samples",
]

#: Schema name and version of the JSON written by :func:`write_samples`.
SAMPLES_SCHEMA = ("btf-samples", "1.0")

#: Bases ``btf sample`` accepts: log Y (paper 1), its 3x3 ABTF patch basis, the ALS basis (paper 4).
SAMPLING_BASES: tuple[str, ...] = ("log_y", "abtf_log_y", "als")

#: Light directions closer than this (sample frame, unit vectors) are one (turntable, LED) pair.
_LIGHT_TOL = 1e-6


def open_model(path: str | os.PathLike) -> tuple[zarr.Group, Path]:
    """Open a model store: ``MODEL_DIR`` (holding ``model.zarr``, from ``btf build-db``) or the store itself.

    Raises
    ------
    ValueError
        If nothing is there, or it is not a ``btf-model`` store (names the path and what to give).
    """
    path = Path(path)
    store = path / "model.zarr" if (path / "model.zarr").is_dir() else path
    if not store.exists():
        raise ValueError(f"{path}: no such model directory or store; give the --out folder of `btf build-db` "
                         "(it holds model.zarr)")
    try:
        group = zarr.open_group(str(store), mode="r", zarr_format=3)
    except Exception as exc:  # noqa: BLE001 - any unreadable store is bad input
        raise ValueError(f"{store}: not a readable Zarr group ({exc}); give the --out folder of `btf build-db`") \
            from None
    if group.attrs.get("schema") != SCHEMA_NAME:
        raise ValueError(f"{store}: schema {group.attrs.get('schema')!r}, not a model store ({SCHEMA_NAME!r}); "
                         "give the --out folder of `btf build-db`")
    return group, store


def _members(group: zarr.Group, where: str) -> list[str]:
    try:
        return sorted(name for name, _ in group[where].groups())
    except KeyError:
        return []


def read_class_basis(group: zarr.Group, store: Path, cls: str, basis: str) -> tuple[np.ndarray, np.ndarray, int]:
    """The class basis ``classes/<cls>/<basis>`` with its singular values and patch size.

    Returns
    -------
    U : (p * p * n_lv, k) ndarray
    sigma : (k,) ndarray
    patch : int
        ``p`` (3 for ``abtf_log_y``, 1 otherwise), from the row count.

    Raises
    ------
    ValueError
        Naming the store, the missing class or basis and the ones present;
        or a basis whose rows do not fit the store's light/view sampling.
    """
    if basis not in SAMPLING_BASES:
        raise ValueError(f"basis {basis!r} cannot be sampled; choose one of {', '.join(SAMPLING_BASES)}")
    classes = _members(group, "classes")
    if cls not in classes:
        raise ValueError(f"{store}: no class {cls!r} in the model store (classes/: "
                         f"{', '.join(classes) or 'none'}); pass one of them as --class")
    where = f"classes/{cls}/{basis}"
    try:
        finished = "U" in group[where] and group[where].attrs.get("key") is not None
    except KeyError:
        finished = False
    if not finished:
        raise ValueError(f"{store}: no finished basis {where} (class {cls!r} has "
                         f"{', '.join(_members(group, f'classes/{cls}')) or 'none'}); rerun `btf build-db` "
                         "or choose another --basis")
    model = read_basis(group, where)
    U = np.asarray(model.U, dtype=np.float64)
    n_lv = int(group["light_dir"].shape[0])
    if U.shape[0] % n_lv:
        raise ValueError(f"{store}: {where}/U has {U.shape[0]} rows, not a multiple of the store's {n_lv} "
                         "light/view pairs (light_dir); the basis belongs to another sampling, rebuild the database")
    p = int(round(np.sqrt(U.shape[0] // n_lv)))
    if p * p * n_lv != U.shape[0]:
        raise ValueError(f"{store}: {where}/U has {U.shape[0]} rows = {U.shape[0] // n_lv} x {n_lv} pairs, "
                         "not a square patch; rebuild the database")
    if not np.isfinite(U).all():
        i, j = (int(v) for v in np.argwhere(~np.isfinite(U))[0])
        raise ValueError(f"{store}: {where}/U[{i}, {j}] = {U[i, j]!r} is not finite; rebuild the database")
    return U, np.asarray(model.sigma, dtype=np.float64), p


def camera_parallel_groups(light_dir: np.ndarray, view_dir: np.ndarray, device: Device | None = None
                           ) -> tuple[np.ndarray, str, np.ndarray | None]:
    """Group ids of the light/view rows for camera-parallel sampling (paper 4, §5.2).

    Parameters
    ----------
    light_dir, view_dir : (n_lv, 3) ndarray
        Light and view direction of every row in the sample frame.
    device : Device, optional
        When given, its ``n_turn * n_cam * n_leds`` must equal ``n_lv``: the
        rows are in the ingest order ``(turntable, camera, light)`` (the
        ``lv_order`` of ``docs/btf-store.md``) and the group of a row is
        ``turntable * n_leds + light``.

    Returns
    -------
    groups : (n_lv,) ndarray of int64
    how : str
        ``'device'``, ``'row_order'`` or ``'light_dir'``.
    pairs : (n_groups, 2) ndarray of int or None
        With a device, the (turntable, LED) pair of every group id.

    Notes
    -----
    Without a device the row order is read from the directions: lights run
    fastest, so a *view block* is a run of rows with one view direction, and
    consecutive view blocks lit by the same light directions (in the sample
    frame they depend on the turntable position only) belong to one turntable
    position; the group of a row is (turntable block, light index). This also
    holds for a resampled store (every light with every view: one block of
    lights, so a group is one light with all views). When the rows have no
    such structure, rows lit from the same direction form a group (a
    symmetric dome may then merge pairs whose turntable rotation maps one LED
    onto another).
    """
    L = np.asarray(light_dir, dtype=np.float64)
    V = np.asarray(view_dir, dtype=np.float64)
    n_lv = L.shape[0]
    if device is not None:
        n = device.n_turn * device.n_cam * device.n_leds
        if n != n_lv:
            raise ValueError(f"device {device.name!r} has {device.n_turn} x {device.n_cam} x {device.n_leds} = {n} "
                             f"(turntable, camera, LED) rows, the model store {n_lv}; the model is resampled or "
                             "from another device: drop --device (groups then come from the rows' directions)")
        row = np.arange(n_lv)
        turn, light = row // (device.n_cam * device.n_leds), row % device.n_leds
        groups = turn * device.n_leds + light
        pairs = np.stack(np.divmod(np.arange(device.n_turn * device.n_leds), device.n_leds), axis=1)
        return groups.astype(np.int64), "device", pairs
    same_view = np.all(np.abs(V[1:] - V[:-1]) <= _LIGHT_TOL, axis=1)
    n_l = int(np.argmin(same_view)) + 1 if not same_view.all() else n_lv
    if n_lv % n_l == 0:
        blocks_v = V.reshape(-1, n_l, 3)
        blocks_l = L.reshape(-1, n_l, 3)
        if np.all(np.abs(blocks_v - blocks_v[:, :1]) <= _LIGHT_TOL):
            new_turn = np.concatenate([[True], np.any(np.abs(blocks_l[1:] - blocks_l[:-1]) > _LIGHT_TOL, axis=(1, 2))])
            turn = np.cumsum(new_turn) - 1                     # turntable block of every view block
            groups = (turn[:, None] * n_l + np.arange(n_l)[None, :]).reshape(-1)
            return groups.astype(np.int64), "row_order", None
    key = np.round(L / _LIGHT_TOL).astype(np.int64)
    _, groups = np.unique(key, axis=0, return_inverse=True)
    return groups.reshape(-1).astype(np.int64), "light_dir", None


def _history_summary(history: np.ndarray, points: int = 32) -> dict[str, Any]:
    h = np.asarray(history, dtype=np.float64)
    if h.size == 0:
        return {"start": None, "final": None, "steps": 0, "sampled": []}
    at = np.unique(np.linspace(0, h.size - 1, min(points, h.size)).round().astype(int))
    return {"start": float(h[0]), "final": float(h[-1]), "steps": int(h.size - 1),
            "sampled": [[int(i), float(h[i])] for i in at]}


def sample_model(model: str | os.PathLike, cls: str, basis: str = "log_y", n: int | None = None, *,
                 method: str = "greedy", camera_parallel: bool = False, device: Device | None = None,
                 seed: int = 0, max_steps: int | None = None,
                 progress: Callable[[str, int, float], None] | None = None) -> dict[str, Any]:
    """Choose the rows of a sparse measurement for a class basis of a model store.

    Parameters
    ----------
    model : path
        ``btf build-db`` output folder or its ``model.zarr``.
    cls : str
        Material class (``classes/<cls>``).
    basis : {'log_y', 'abtf_log_y', 'als'}
    n : int or None
        Rows to select, or (camera-parallel) (turntable, LED) groups; None
        only for ``'parabolic_map'``.
    method : {'greedy', 'random_swap', 'parabolic_map'}
    camera_parallel : bool
        Select whole groups (:func:`camera_parallel_groups`).
    device : Device, optional
        Row order of an unresampled model; adds the (turntable, LED) pairs
        that ``btf plan --samples`` needs.
    seed : int
    max_steps : int, optional
        Passed to the sampler (random swap default: 10,000 trial swaps).
    progress : callable, optional
        ``progress(phase, step, kappa)`` (greedy: accepted steps; random swap:
        every 1,000 trial swaps, after the run).

    Returns
    -------
    doc : dict
        The ``btf-samples`` document (:func:`write_samples`).

    Raises
    ------
    ValueError
        Bad store, class, basis or parameters (names which and what to do).
    """
    if method not in SAMPLING_METHODS:
        raise ValueError(f"unknown sampling method {method!r}; choose one of {', '.join(SAMPLING_METHODS)}")
    group, store = open_model(model)
    U, sigma, patch = read_class_basis(group, store, cls, basis)
    light_dir = np.asarray(group["light_dir"][...], dtype=np.float64)
    view_dir = np.asarray(group["view_dir"][...], dtype=np.float64)
    groups = pairs = None
    how = None
    if camera_parallel or device is not None:
        g, how, pairs = camera_parallel_groups(light_dir, view_dir, device)
        groups = g if camera_parallel else None
    if method == "parabolic_map":
        if camera_parallel:
            raise ValueError("--camera-parallel does not apply to the parabolic map (it keeps the same views for "
                             "every light already); drop it or choose greedy/random_swap")
        kwargs: dict[str, Any] = {"light_dirs": light_dir, "view_dirs": view_dir}
    else:
        if n is None:
            raise ValueError(f"method {method!r} needs the number of samples: pass --n N")
        kwargs = {"seed": seed}
        if max_steps is not None:
            kwargs["max_steps"] = max_steps
        if method == "greedy" and progress is not None:
            kwargs["progress"] = progress
    t0 = time.perf_counter()
    try:
        res = select_samples(U, n, method, groups=groups, patch=patch if patch > 1 else None, **kwargs)
    except ValueError as exc:
        raise ValueError(f"{store}: classes/{cls}/{basis} (U {U.shape[0]} x {U.shape[1]}): {exc}") from None
    seconds = time.perf_counter() - t0
    if progress is not None and method == "random_swap":
        for step in range(0, res.history.size, 1000):
            progress("random-swap", step, float(res.history[step]))
    doc: dict[str, Any] = {
        "schema": SAMPLES_SCHEMA[0], "schema_version": SAMPLES_SCHEMA[1],
        "model": str(store.resolve()), "rows_id": group.attrs.get("rows_id"), "n_lv": int(light_dir.shape[0]),
        "class": cls, "basis": basis, "k": int(U.shape[1]), "patch": int(patch),
        "method": res.method, "camera_parallel": bool(camera_parallel), "groups_from": how,
        "device": device.name if device is not None else None,
        "n_s": res.n_s, "n_rows": int(res.rows.size),
        "kappa": float(res.kappa), "kappa_history": _history_summary(res.history),
        "steps": int(res.steps), "accepted": int(res.accepted), "converged": bool(res.converged),
        "settings": res.settings, "seconds": round(seconds, 3),
        "rows": res.rows.tolist(),
        "units": res.units.tolist() if camera_parallel else None,
    }
    if pairs is not None:
        sel_groups = np.unique(camera_parallel_groups(light_dir, view_dir, device)[0][res.rows])
        doc["pairs"] = pairs[sel_groups].tolist()              # (turntable, LED) to capture, all cameras
    return doc


def write_samples(doc: dict[str, Any], path: str | os.PathLike) -> Path:
    """Write a ``btf-samples`` document atomically (a temporary file, then a rename)."""
    path = Path(path)
    write_file(path, lambda tmp: tmp.write_text(json.dumps(doc, indent=1)))
    return path


def read_samples(path: str | os.PathLike) -> dict[str, Any]:
    """Read a ``btf-samples`` file.

    Raises
    ------
    ValueError
        Missing file, not JSON, or another schema (names the file and what to give).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such samples file; write one with `btf sample ... --out {path.name}`")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not JSON ({exc}); write it with `btf sample`") from None
    if not isinstance(doc, dict) or doc.get("schema") != SAMPLES_SCHEMA[0]:
        raise ValueError(f"{path}: schema {doc.get('schema') if isinstance(doc, dict) else None!r}, expected "
                         f"{SAMPLES_SCHEMA[0]!r}; write it with `btf sample`")
    for i, pair in enumerate(doc.get("pairs") or []):
        if not (isinstance(pair, list) and len(pair) == 2
                and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in pair)):
            raise ValueError(f"{path}: pairs[{i}] = {pair!r} is not a (turntable, LED) pair of two non-negative "
                             "integers; write the file again with `btf sample ... --device DEVICE`")
    return doc
