"""Validating the model store (schema ``btf-model`` 1.0, docs/model-database.md) for ``btf validate``.

The store is written in :mod:`tasks.model` (:func:`~tasks.model.open_model_store`,
:func:`~tasks.model.write_basis`, :func:`~tasks.model.build_database`); this module checks what
they write and reads no more than the directions and each basis' ``sigma``. It is a module of its
own, as :mod:`tasks.stores.capture_validate` is for the capture store, because :mod:`tasks.model`
is near the size limit of a module (docs/architecture.md).
"""

from __future__ import annotations

import os

import numpy as np
import zarr

from tasks.integrity import open_any_store
from tasks.model import SCHEMA_NAME, SCHEMA_VERSION, rows_fingerprint
from tasks.stores.common import ROOT_ATTRS, WHOLE_STORE, Problem, listing, read_whole

__all__ = ["BASIS_PARENTS", "validate_model_store"]

#: Where basis groups are: top-level group -> depth of a basis group (``materials/<id>/<basis>``,
#: ``classes/<class>/<basis>``, ``global/<basis>``).
BASIS_PARENTS = {"materials": 3, "classes": 3, "global": 2}
#: What to do about a model store that does not hold what the schema says.
_REBUILD = "rebuild the model with `btf build-db` into a fresh --out folder"
_GIVE = "give the --out folder of `btf build-db`"


def validate_model_store(path: str | os.PathLike, *, require_complete: bool = True) -> list[Problem]:
    """Check a model store against the schema and list every problem (``btf validate``).

    Checks the root attributes of :func:`tasks.model.open_model_store` (``schema_version``,
    ``n_lv``, ``rows_id``, ``bases``); ``light_dir``/``view_dir`` ``(n_lv, 3)`` whose
    :func:`tasks.model.rows_fingerprint` is ``rows_id``; every basis group (:data:`BASIS_PARENTS`,
    :func:`tasks.model.write_basis`): float64 ``U`` ``(n_lv, k)`` (``abtf_log_y``: ``n_lv * patch**2``
    rows, ``patch`` of the attribute ``settings``) and ``sigma`` ``(k,)``, non-negative and
    non-increasing, and its ``key`` (written after the arrays); and that the groups of the materials
    and classes the attribute ``materials`` of a finished build lists are there, and ``complete``
    (written true by :func:`tasks.model.build_database` at its end; a store without it is accepted as
    one written before it was added). ``U`` is not read:
    its NaN/Inf values are found by ``btf validate --deep`` (:func:`tasks.integrity.verify_store`).

    Parameters
    ----------
    path : str or path-like
        ``model.zarr`` or the ``btf build-db`` folder holding it.
    require_complete : bool
        Report an unfinished build (``complete`` false, a basis without its ``key``) as a problem.

    Returns
    -------
    list of Problem
        Empty when the store is valid; each names the array (or group, or attribute) and the index.
        Content problems never raise.
    """
    try:
        group, _ = open_any_store(path)
    except (FileNotFoundError, ValueError) as e:
        return [Problem(WHOLE_STORE, None, "a model store (a Zarr v3 group)", str(e), f"check the path; {_GIVE}")]
    attrs = dict(group.attrs)
    if attrs.get("schema") != SCHEMA_NAME:
        return [Problem(ROOT_ATTRS, "schema", repr(SCHEMA_NAME), repr(attrs.get("schema")),
                        f"this is not a model store; {_GIVE}")]
    n_lv = attrs["n_lv"] if isinstance(attrs.get("n_lv"), int) and attrs["n_lv"] > 0 else None
    problems = [Problem(ROOT_ATTRS, key, want, repr(attrs[key]) if key in attrs else "nothing", _REBUILD)
                for key, want, ok in (
                    ("schema_version", repr(SCHEMA_VERSION), attrs.get("schema_version") == SCHEMA_VERSION),
                    ("n_lv", "a positive integer (light/view pairs)", n_lv is not None),
                    ("rows_id", "a string (the hash of light_dir and view_dir)", isinstance(attrs.get("rows_id"), str)),
                    ("bases", "a list of basis names", isinstance(attrs.get("bases"), list))) if not ok]
    _direction_problems(group, attrs, n_lv, problems)
    settings = attrs.get("settings")
    patch = settings.get("patch") if isinstance(settings, dict) else None
    for where, node in sorted(group.members(max_depth=None)):
        parts = where.split("/")
        if isinstance(node, zarr.Group) and len(parts) == BASIS_PARENTS.get(parts[0]):
            _basis_problems(where, node, n_lv, patch if isinstance(patch, int) else None, problems)
            if require_complete and "key" not in node.attrs:
                problems.append(Problem(where, "attrs key", "the basis' resume marker 'key' (written after U and "
                                        "sigma)", "nothing", "the build stopped while writing this basis; run "
                                        "`btf build-db` again with the same --out to finish it"))
    if "complete" in attrs and not isinstance(attrs["complete"], bool):
        problems.append(Problem(ROOT_ATTRS, "complete", "true or false", repr(attrs["complete"]), _REBUILD))
    elif require_complete and attrs.get("complete") is False:
        problems.append(Problem(ROOT_ATTRS, "complete", "true", "false", "the build is unfinished; run `btf build-db` "
                                "again with the same --out to resume it"))
    listed = attrs.get("materials") if isinstance(attrs.get("materials"), dict) else {}
    wanted = {f"materials/{m}" for m in listed} | {f"classes/{r['class']}" for r in listed.values()
                                                   if isinstance(r, dict) and isinstance(r.get("class"), str)}
    problems += [Problem(where, None, "a group (the attribute materials lists it)", "nothing", _REBUILD)
                 for where in sorted(wanted) if where not in group]
    return problems


def _direction_problems(group: zarr.Group, attrs: dict, n_lv: int | None, problems: list[Problem]) -> None:
    """``light_dir`` and ``view_dir``: ``(n_lv, 3)`` floats whose hash is ``rows_id``."""
    dirs = []
    for name in ("light_dir", "view_dir"):
        node = group.get(name)
        if not isinstance(node, zarr.Array):
            problems.append(Problem(name, None, f"array {name!r} ({n_lv or 'n_lv'}, 3)",
                                    "nothing" if node is None else "a group", _REBUILD))
        elif node.ndim != 2 or node.shape[1] != 3 or node.shape[0] != (n_lv or node.shape[0]) or \
                np.dtype(node.dtype).kind != "f":
            axis = "axis 0 (n_lv)" if node.ndim == 2 and node.shape[1] == 3 else None
            problems.append(Problem(name, axis, f"floats of shape ({n_lv or 'n_lv'}, 3) (attribute n_lv)",
                                    f"{node.dtype} of shape {node.shape}", _REBUILD))
        elif (data := read_whole(name, node, problems)) is not None:
            dirs.append(data)
    rows_id = attrs.get("rows_id")
    if len(dirs) == 2 and isinstance(rows_id, str) and (fp := rows_fingerprint(*dirs)) != rows_id:
        problems.append(Problem(ROOT_ATTRS, "rows_id", f"{fp!r}, the hash of light_dir and view_dir (the "
                                "directions were changed after the build)", repr(rows_id), _REBUILD))


def _basis_problems(where: str, group: zarr.Group, n_lv: int | None, patch: int | None,
                    problems: list[Problem]) -> None:
    """One basis group: float64 ``U`` ``(rows, k)`` and ``sigma`` ``(k,)``, non-negative and non-increasing."""
    U, sigma = group.get("U"), group.get("sigma")
    for name, node in (("U", U), ("sigma", sigma)):
        if not isinstance(node, zarr.Array):
            problems.append(Problem(f"{where}/{name}", None, f"array {name!r} of the basis",
                                    "nothing" if node is None else "a group", _REBUILD))
    if not (isinstance(U, zarr.Array) and isinstance(sigma, zarr.Array)):
        return
    if where.rsplit("/", 1)[-1] == "abtf_log_y":          # patch x patch ABTF rows per light/view pair
        p = patch if patch is not None else round((U.shape[0] / (n_lv or 1)) ** 0.5) if U.ndim else 0
        rows, words = ((n_lv * p * p, f"n_lv * patch**2 = {n_lv} * {p}**2") if n_lv else (None, "n_lv * patch**2"))
    else:
        rows, words = n_lv, "n_lv"
    if U.ndim != 2 or str(U.dtype) != "float64":
        problems.append(Problem(f"{where}/U", None, f"float64 of shape ({words}, k)", f"{U.dtype} of shape {U.shape}",
                                _REBUILD))
        return
    if rows is not None and U.shape[0] != rows:
        problems.append(Problem(f"{where}/U", "axis 0 (rows)", f"{rows} rows ({words})", f"{U.shape[0]} rows",
                                _REBUILD))
    if sigma.shape != (U.shape[1],) or str(sigma.dtype) != "float64":
        problems.append(Problem(f"{where}/sigma", "axis 0", f"float64 of shape ({U.shape[1]},): one value per column "
                                f"of U {U.shape}", f"{sigma.dtype} of shape {sigma.shape}", _REBUILD))
        return
    s = read_whole(f"{where}/sigma", sigma, problems)
    if s is None:
        return
    for bad, want in ((np.flatnonzero(s < 0), "non-negative values"),
                      (np.flatnonzero(s[1:] > s[:-1] * (1 + 1e-12)) + 1, "non-increasing values (sigma[i] <= "
                                                                          "sigma[i - 1])")):
        if len(bad):
            problems.append(Problem(f"{where}/sigma", listing(bad[:, None]), want,
                                    f"{len(bad)} other value(s), the first {float(s[bad[0]])!r}", _REBUILD))
