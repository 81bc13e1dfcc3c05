"""Issue 13, silent corruption: a changed byte or a missing chunk file is an error that names the store,
the array and the chunk, from `btf validate --deep` and from the stage that reads it, never a result.

Real stores written by the pipeline (the session's tiny capture and its ingested BTF store, a model store
written by tasks.model's writers), the real command line (`run_btf`).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from flows.cli import EXIT_BAD_INPUT
from tasks.integrity import has_checksums


def all_checksummed(path: Path) -> list[str]:
    group = zarr.open_group(str(path), mode="r")
    arrays = [(name, a) for name, a in group.members(max_depth=None) if isinstance(a, zarr.Array)]
    assert arrays
    return [name for name, a in arrays if not has_checksums(a)]


@pytest.fixture(scope="module")
def stores(tiny_btf, tmp_path_factory) -> dict[str, Path]:
    """The session's capture, its BTF store and a model store (class ``leather``, k = 8) fitted on it."""
    from btfcore.model._lowrank import TruncatedSVD
    from tasks.model import discover, open_model_store, write_basis

    capture = next(p for p in tiny_btf.parent.glob("*.zarr")
                   if zarr.open_group(str(p), mode="r").attrs.get("schema") == "btf-capture")
    model_dir = tmp_path_factory.mktemp("model")
    [material] = discover(tiny_btf.parent, min_per_class=1)
    group = open_model_store(model_dir / "model.zarr", [material])
    B = np.asarray(zarr.open_group(str(tiny_btf), mode="r")["btf"][...], dtype=np.float64)
    U, s, _ = np.linalg.svd(B.reshape(B.shape[0], -1), full_matrices=False)
    write_basis(group, "classes/leather/als", TruncatedSVD(U[:, :8], s[:8], "merge"), "full-svd")
    return {"capture": capture, "btf": tiny_btf, "model": model_dir}


@pytest.fixture()
def copies(stores, tmp_path) -> dict[str, Path]:
    return {kind: Path(shutil.copytree(path, tmp_path / path.name)) for kind, path in stores.items()}


def test_every_store_kind_is_written_with_chunk_checksums(stores, run_btf, tmp_path):
    for kind in ("capture", "btf"):
        assert all_checksummed(stores[kind]) == [], kind
    assert all_checksummed(stores["model"] / "model.zarr") == []
    code, _, err = run_btf("reconstruct", stores["btf"], "--model", stores["model"], "--class", "leather",
                           "--out", tmp_path / "rec.zarr")
    assert code == 0, err
    assert all_checksummed(tmp_path / "rec.zarr") == []
    for kind, path in stores.items():
        code, out, _ = run_btf("validate", "--deep", path)
        assert code == 0 and "problem" not in out and "note:" not in out, (kind, out)


def test_a_flipped_raw_byte_is_named_by_validate_and_by_ingest(copies, run_btf, tmp_path, chunk_files):
    capture = copies["capture"]
    chunk_files.flip_byte(chunk_files.path(capture, "raw", (0, 1, 3, 0, 0, 0)), offset=1000)
    named = "array raw, chunk (0, 1, 3, 0, 0, 0): checksum mismatch (the chunk file was changed after it was written)"
    code, out, _ = run_btf("validate", "--deep", capture)
    assert code == EXIT_BAD_INPUT and f"{capture}: 1 problem(s)" in out and named in out, out
    code, _, err = run_btf("ingest", capture, "--out", tmp_path / "out.zarr")
    assert code == EXIT_BAD_INPUT, err
    assert f"{capture}: {named}" in err and err.count("chunk (0, 1, 3, 0, 0, 0)") == 1, err


def test_a_missing_raw_chunk_is_named_not_taken_for_an_unusable_bracket(copies, run_btf, tmp_path, chunk_files):
    capture = copies["capture"]
    chunk_files.path(capture, "raw", (0, 1, 3, 0, 0, 0)).unlink()
    for args in (["validate", capture], ["ingest", capture, "--out", tmp_path / "out.zarr"]):
        code, out, err = run_btf(*args)
        assert code == EXIT_BAD_INPUT, (args, out, err)
        said = out + err
        assert str(capture) in said and "raw[chunk (0, 1, 3, 0, 0, 0)]" in said and "chunk file missing" in said \
            and "damaged after writing" in said, (args, out, err)
        assert "usable pixel" not in out + err
    assert not (tmp_path / "out.zarr").exists()


def test_a_flipped_btf_byte_is_named_by_validate_and_by_reconstruct(copies, run_btf, tmp_path, chunk_files):
    btf = copies["btf"]
    chunk_files.flip_byte(chunk_files.path(btf, "btf", (2, 0, 0, 0)))
    named = "array btf, chunk (2, 0, 0, 0): checksum mismatch"
    code, out, _ = run_btf("validate", "--deep", btf)
    assert code == EXIT_BAD_INPUT and named in out and "btf ingest --overwrite" in out, out
    code, _, err = run_btf("reconstruct", btf, "--model", copies["model"], "--class", "leather",
                           "--out", tmp_path / "rec.zarr")
    assert code == EXIT_BAD_INPUT, err
    assert f"{btf}: {named}" in err, err


def test_a_flipped_model_byte_is_named_by_validate_and_by_reconstruct(copies, run_btf, tmp_path, chunk_files):
    model = copies["model"]
    chunk_files.flip_byte(chunk_files.path(model / "model.zarr", "classes/leather/als/U", (0, 0)))
    named = "array classes/leather/als/U, chunk (0, 0): checksum mismatch"
    code, out, _ = run_btf("validate", "--deep", model)            # a build-db folder means its model.zarr
    assert code == EXIT_BAD_INPUT and named in out and "btf build-db" in out, out
    code, _, err = run_btf("reconstruct", copies["btf"], "--model", model, "--class", "leather",
                           "--out", tmp_path / "rec.zarr")
    assert code == EXIT_BAD_INPUT, err
    assert f"{model / 'model.zarr'}: {named}" in err, err
