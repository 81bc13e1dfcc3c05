"""Replace a finished output only once its replacement is complete: staging store, resume and swap.

A run keyed by an attribute of its Zarr store (``ingest_hash`` for ``btf ingest``,
``resample_hash`` for ``btf resample``) that replaces another output at ``X.zarr``
writes ``X.partial.zarr`` beside it (:func:`staging_path`); the staging store resumes
like any output, and :func:`commit_staged` renames it over ``X.zarr`` once it is
complete: ``X.zarr`` -> ``X.replaced.zarr``, ``X.partial.zarr`` -> ``X.zarr``, then
``X.replaced.zarr`` deleted. A commit killed between the renames is finished (or
undone) by the next run into ``X.zarr`` (:func:`staged_target`). docs/btf-store.md,
"Overwrite"; docs/decisions.md, "Issue 3, bad input".
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any, Callable

import zarr


def staging_path(out: str | os.PathLike) -> Path:
    """Where a run that replaces the output at ``out`` is built: ``X.partial.zarr`` beside
    ``X.zarr`` (same folder, so that :func:`commit_staged` is a rename)."""
    out = Path(out)
    return out.with_name(f"{out.stem}.partial{out.suffix}")


def trash_path(out: str | os.PathLike) -> Path:
    """Where :func:`commit_staged` moves the replaced output until the new one is in place."""
    out = Path(out)
    return out.with_name(f"{out.stem}.replaced{out.suffix}")


def store_attrs(path: str | os.PathLike) -> dict[str, Any] | None:
    """The attributes of the Zarr group at ``path``; ``None`` if nothing is there, ``{}`` if it is no group."""
    if not Path(path).exists():
        return None
    try:
        return dict(zarr.open_group(str(path), mode="r", zarr_format=3).attrs)
    except (OSError, ValueError, TypeError):  # a file, a folder without zarr.json, an array
        return {}


def finish_interrupted_commit(out: str | os.PathLike) -> None:
    """Complete (or undo) a :func:`commit_staged` that was killed between its renames."""
    out = Path(out)
    trash, staging = trash_path(out), staging_path(out)
    if not trash.exists():
        return
    if not out.exists():
        # the old output was moved aside: put the complete replacement in, or else the old one back
        if (store_attrs(staging) or {}).get("complete"):
            os.rename(staging, out)
        else:
            os.rename(trash, out)
    shutil.rmtree(trash, ignore_errors=True)


def staged_target(out: str | os.PathLike, key_attr: str, key: str, overwrite: bool,
                  refusal: Callable[[dict[str, Any]], Exception]) -> tuple[Path, bool]:
    """The store a run keyed ``key_attr == key`` writes, and whether it is the staging store of a replacement.

    First an interrupted commit into ``out`` is finished. Then: the staging store when it holds
    this run (a killed replacement resumes, with or without ``overwrite``) or when ``overwrite``
    replaces whatever is at ``out`` (recomputed in full, even an output of this run); else ``out``
    itself when nothing is there or it holds this run (resumed, or left alone when complete).

    Raises
    ------
    Exception
        ``refusal(attrs)`` (the attributes of what is at ``out``, ``{}`` if it is no Zarr group)
        when ``out`` holds something else and not ``overwrite``.
    """
    out = Path(out)
    finish_interrupted_commit(out)
    attrs, staging = store_attrs(out), staging_path(out)
    if (store_attrs(staging) or {}).get(key_attr) == key:
        return staging, True
    if attrs is None:
        return out, False
    if overwrite:
        return staging, True
    if attrs.get(key_attr) == key:
        return out, False
    raise refusal(attrs)


def commit_staged(out: str | os.PathLike, command: str) -> Path:
    """Put the complete staging store of ``out`` (:func:`staging_path`) in place of ``out``.

    The old output is renamed aside, the staging store renamed to ``out``, and then the old one
    deleted, so that at every moment one of them is whole; a commit killed in between is
    finished by the next run into ``out`` (:func:`staged_target`). ``command`` (``"ingest"``,
    ``"resample"``) names the run in the messages.

    Raises
    ------
    FileNotFoundError
        No staging store beside ``out``.
    RuntimeError
        The staging store is not complete (resume the run first).
    """
    out = Path(out)
    staging, trash = staging_path(out), trash_path(out)
    attrs = store_attrs(staging)
    if attrs is None:
        raise FileNotFoundError(f"{staging}: no staged {command} to put in place of {out}")
    if not attrs.get("complete"):
        raise RuntimeError(f"{staging}: the staged {command} is unfinished; run `btf {command}` again to resume it")
    shutil.rmtree(trash, ignore_errors=True)        # left over from an earlier, interrupted commit
    if out.exists():
        os.rename(out, trash)
    os.rename(staging, out)
    shutil.rmtree(trash, ignore_errors=True)
    return out
