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
from typing import Any, Callable, TypeVar

import zarr

from tasks.faults import kill_point

T = TypeVar("T")


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


def output_refusal(out: str | os.PathLike, attrs: dict[str, Any], key_attr: str, key: str, kind: str,
                   other: str) -> FileExistsError:
    """The error for an ``--out`` that holds something other than this run (the ``refusal`` of
    :func:`staged_target` for stages keyed by ``key_attr``).

    Parameters
    ----------
    out : path-like
        The output path.
    attrs : dict
        Root attributes of what is at ``out`` (``{}``: no Zarr group).
    key_attr, key : str
        The content-key attribute and this run's key.
    kind : str
        What this stage writes, e.g. ``"resampled BTF store"``.
    other : str
        What a store of another key is of, e.g. ``"another source or sampling"``.
    """
    out = Path(out)
    if not attrs:
        what = "something that is not a Zarr store"
    elif key_attr not in attrs:
        article = "an" if kind[:1] in "aeiou" else "a"
        what = f"a Zarr store that is not {article} {kind} (schema {attrs.get('schema')!r})"
    else:
        state = "a complete" if attrs.get("complete") else "an unfinished"
        what = f"{state} {kind} of {other} ({key_attr} {attrs[key_attr]!r}, this run {key!r})"
    return FileExistsError(f"{out} holds {what}; choose another --out or pass --overwrite (the new store is then "
                           f"built in {staging_path(out)} and replaces {out.name} only once it is complete)")


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
    kill_point("commit-start")
    if out.exists():
        os.rename(out, trash)
    kill_point("commit-between-renames")
    os.rename(staging, out)
    shutil.rmtree(trash, ignore_errors=True)
    return out


def temporary_file(path: str | os.PathLike) -> Path:
    """Where :func:`write_file` writes ``path`` first: ``.STEM.tmp.SUFFIX`` beside it (hidden; the suffix kept
    for writers that go by it, such as OpenCV and OpenEXR)."""
    path = Path(path)
    return path.with_name(f".{path.stem}.tmp{path.suffix}")


def write_file(path: str | os.PathLike, write: Callable[[Path], T]) -> T:
    """Put a single-file output at ``path`` whole or not at all, and return what ``write`` returns.

    ``write(tmp)`` writes the file at :func:`temporary_file` beside ``path``, which is then renamed over
    ``path`` (the folder is created). The kill points ``file-writing`` (the output computed, nothing
    written) and ``file-replace`` (written beside ``path``, not yet renamed) sit between; a ``write``
    that raises leaves no temporary file, and a finished file at ``path`` is only ever replaced whole.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_file(path)
    try:
        kill_point("file-writing")
        result = write(tmp)
        kill_point("file-replace")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return result


def seed_staging(out: str | os.PathLike) -> Path:
    """Make the staging store of ``out`` a copy of ``out`` whose files are hard links to ``out``'s.

    For a stage that updates a store rather than rebuilding it (``btf build-db`` adding materials to
    its model store): the copy costs a link per file, and writing into it never changes ``out``,
    because Zarr's local store writes every file whole to a temporary name and renames it over the
    old one (a new inode; ``zarr.storage.LocalStore``) and deletes by unlinking. Where the file
    system has no hard links, files are copied. The copy is built at the staging store's
    :func:`creating_path` and renamed into place, so a kill leaves no half-made staging store.
    """
    out = Path(out)
    staging = staging_path(out)
    building = creating_path(staging)
    shutil.rmtree(building, ignore_errors=True)

    def link(src: str, dst: str) -> None:
        try:
            os.link(src, dst)
        except OSError:
            shutil.copy2(src, dst)

    shutil.copytree(out, building, copy_function=link)
    kill_point("store-creating")
    os.rename(building, staging)
    return staging


# --------------------------------------------------------------------------
# Outputs: never an input, in a place that can be written, never half-made
# --------------------------------------------------------------------------


def _overlap(out: Path, inp: Path) -> str | None:
    """How ``out`` would touch ``inp`` (both resolved), or ``None``."""
    if out == inp:
        return "is"
    if out in inp.parents:
        return "contains"
    if inp in out.parents:
        return "is inside"
    return None


def refuse_inputs_as_outputs(outputs: dict[str, str | os.PathLike | None],
                             inputs: dict[str, str | os.PathLike | None], *,
                             folders: tuple[str, ...] = ()) -> None:
    """The one guard of every command: no output is, contains or lies inside one of its inputs.

    Parameters
    ----------
    outputs, inputs : dict
        ``{option name (e.g. "--out"): path}``; ``None`` values are ignored, and so are
        inputs that do not exist (a preset name such as ``ubo2014`` is no path).
    folders : tuple of str
        Names of inputs that are folders of inputs (the raw files of ``btf import-raw``,
        the database of ``btf build-db``): a new output may lie inside such a folder
        (``raws/capture.zarr``), but not be or contain it; the files it holds that the
        run reads are passed as inputs of their own.

    Raises
    ------
    FileExistsError
        Naming both options and paths, before anything is written: with or without
        ``--overwrite``, a run never replaces, deletes or writes into what it reads.
    """
    ins = {name: Path(p).resolve() for name, p in inputs.items() if p is not None and Path(p).exists()}
    for out_name, out in outputs.items():
        if out is None:
            continue
        out_path = Path(out).resolve()
        for in_name, inp in ins.items():
            how = _overlap(out_path, inp)
            if how and not (how == "is inside" and in_name in folders):
                raise FileExistsError(
                    f"{out_name} {out} {how} the input {in_name} {inp}; a run never writes into what it reads "
                    f"(not even with --overwrite): choose an {out_name} outside it")


def check_output_location(path: str | os.PathLike, option: str = "--out") -> None:
    """Refuse an output that cannot be created, before any run starts.

    The nearest existing folder above ``path`` must be a writable directory: a regular
    file on the way (``out.zarr/x`` under a file ``out.zarr``), a read-only or
    permission-denied folder are named with the option and the path. An existing output
    folder must hold no symbolic link, at any depth, to a place outside it, which the run
    would write through (a crafted ``exr/lv00000....exr -> /elsewhere``, or a chunk folder
    ``out.zarr/btf/c -> /elsewhere`` that a resumed run would write into).

    Raises
    ------
    NotADirectoryError, PermissionError, ValueError
        One line naming ``option``, the path and what to do.
    """
    path = Path(path)
    if _is_url(path):
        return
    parent = path.absolute().parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise NotADirectoryError(f"{option} {path}: {parent} is a file, not a folder; choose an {option} whose "
                                 "folders are folders")
    if path.exists() and not path.is_dir() and not os.access(path, os.W_OK):
        raise PermissionError(f"{option} {path}: the file is not writable; choose another {option}")
    if path.is_dir():                   # a run writes inside its output only, never through a link out of it
        link = _link_out_of(path)
        if link is not None:
            name, target = link
            raise ValueError(f"{option} {path}: {name} is a symbolic link to {target}, outside the "
                             f"output; a run writes only inside its output: remove the link or choose another "
                             f"{option}")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise PermissionError(f"{option} {path}: the folder {parent} is not writable (permissions or a read-only "
                              f"file system); choose another {option}")


def _link_out_of(folder: Path) -> tuple[str, Path] | None:
    """The first symbolic link at any depth below ``folder`` (its path relative to it) that resolves outside
    ``folder``, with its target; links are not followed. One directory listing per folder of the output."""
    root = folder.resolve()
    pending = [str(folder)]
    while pending:
        with os.scandir(pending.pop()) as listing:
            entries = sorted(listing, key=lambda e: e.name)
        for entry in entries:           # the file type comes with the listing: no stat per file
            if entry.is_symlink():
                target = Path(entry.path).resolve()
                if target != root and root not in target.parents:
                    return str(Path(entry.path).relative_to(folder)), target
            elif entry.is_dir(follow_symlinks=False):
                pending.append(entry.path)
    return None


def _is_url(path: str | os.PathLike) -> bool:
    return "://" in os.fspath(path)


def creating_path(path: str | os.PathLike) -> Path:
    """Where :func:`begin_store` builds the store ``X.zarr``: ``.X.zarr.creating`` beside it (hidden, and no
    ``.zarr`` name, so that no folder listing of a database takes it for a store)."""
    path = Path(path)
    return path.with_name(f".{path.name}.creating")


def begin_store(path: str | os.PathLike) -> zarr.Group:
    """An empty Zarr v3 group in which a new store for ``path`` is built (its arrays and attributes).

    Every store kind is created this way: the skeleton is built at :func:`creating_path`
    and :func:`finish_store` renames it to ``path``. A run killed while creating leaves
    only the hidden ``.X.zarr.creating`` folder, which the next run deletes and builds
    again, so ``path`` itself is never a half-made store (a rerun resumes without
    ``--overwrite``). A URL (fsspec) store is created in place.
    """
    if _is_url(path):
        return zarr.open_group(os.fspath(path), mode="w", zarr_format=3)
    building = creating_path(path)
    shutil.rmtree(building, ignore_errors=True)      # left by a run killed while creating
    return zarr.open_group(str(building), mode="w", zarr_format=3)


def finish_store(path: str | os.PathLike, group: zarr.Group) -> zarr.Group:
    """Put the store built by :func:`begin_store` in place at ``path`` (replacing what the
    caller decided to replace there) and return it opened ``r+``."""
    if _is_url(path):
        return group
    path = Path(path)
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()
    kill_point("store-creating")
    os.rename(creating_path(path), path)
    kill_point("store-created")
    return zarr.open_group(str(path), mode="r+", zarr_format=3)
