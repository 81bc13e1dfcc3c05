"""Chunk checksums (tasks/integrity.py): a changed, truncated or missing chunk is named, never read as numbers.

Real Zarr v3 stores on disk, written by the pipeline's own writers; no cluster.
"""

from __future__ import annotations

import ast
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from flows.cli import EXIT_BAD_INPUT, main
from tasks import integrity
from tasks.integrity import CHECKSUM_NOTE, CorruptChunkError, create_array, has_checksums, verify_store
from tasks.stores import (CaptureStore, create_capture_store, open_capture_store, validate_capture_store,
                          write_chunk_aligned)

ROOT = Path(__file__).resolve().parents[2]


def write_capture(path: Path, *, black_level: int | None = None) -> Path:
    """A complete single-turntable capture of the `tiny` dome (random frames), written by the store's writers."""
    from dataclasses import replace

    from tasks.simulate import SimulationConfig, capture_metadata, material_plan

    config = SimulationConfig(device="tiny", n_materials=1, seed=1, classes=("leather",), n_turntable=1,
                              texture_size=8)
    meta = capture_metadata(config, material_plan(config)[0], config.build_device())
    if black_level is not None:
        meta = replace(meta, black_level=black_level)
    store = create_capture_store(path, meta)
    rng = np.random.default_rng(0)
    rows, cols = meta.roi_shape
    for t, c in store.pending_views():
        frames = rng.integers(meta.black_level + 1, 4000, (store.n_illum, store.n_exp, rows, cols), dtype=np.uint16)
        store.write_bracket(t, c, frames, np.tile(np.geomspace(1e-3, 1e-1, store.n_exp), (store.n_illum, 1)))
    store.write_dark_frames(np.full((store.n_cam, store.n_dark, rows, cols), meta.black_level + 2, np.uint16))
    store.mark_complete()
    return path


@pytest.fixture(scope="module")
def capture_template(tmp_path_factory) -> Path:
    return write_capture(tmp_path_factory.mktemp("integrity") / "capture.zarr")


@pytest.fixture()
def capture(capture_template, tmp_path) -> Path:
    return Path(shutil.copytree(capture_template, tmp_path / "capture.zarr"))


def validate(capsys, *args) -> tuple[int, str]:
    code = main(["validate", *map(str, args)])
    return code, capsys.readouterr().out


# --------------------------------------------------------------------------- one home

ZARR_CREATORS = {"create", "create_array", "array", "zeros", "ones", "full", "empty", "open_array", "from_array"}


def test_every_array_is_created_through_the_checksum_helper():
    """No module of tasks/ calls zarr's create_array itself: tasks.integrity.create_array is the one home."""
    bad = []
    for path in sorted((ROOT / "tasks").rglob("*.py")):
        if path.name == "integrity.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Attribute):
                continue
            zarr_call = isinstance(node.value, ast.Name) and node.value.id == "zarr" and node.attr in ZARR_CREATORS
            if node.attr in ("create_array", "create_dataset", "require_array") or zarr_call:
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno} .{node.attr}(")
    assert not bad, "arrays created without tasks.integrity.create_array:\n" + "\n".join(bad)


def test_the_helper_appends_crc32c_after_any_compressor(tmp_path):
    from zarr.codecs import Crc32cCodec, ZstdCodec

    group = zarr.open_group(str(tmp_path / "s.zarr"), mode="w", zarr_format=3)
    plain = create_array(group, "plain", shape=(4,), dtype="f4", compressors=None)
    packed = create_array(group, "packed", shape=(4,), dtype="f4", compressors=[ZstdCodec(level=1)])
    assert plain.compressors == (Crc32cCodec(),)
    assert isinstance(packed.compressors[0], ZstdCodec) and packed.compressors[-1] == Crc32cCodec()
    assert len(integrity.checksummed([Crc32cCodec()])) == 1                  # never two checksums


def test_every_array_of_a_capture_store_has_checksums(capture):
    group = zarr.open_group(str(capture), mode="r")
    arrays = [(name, a) for name, a in group.members(max_depth=None) if isinstance(a, zarr.Array)]
    assert len(arrays) == 13 and all(has_checksums(a) for _, a in arrays), \
        [name for name, a in arrays if not has_checksums(a)]


def test_every_array_of_a_measurement_store_has_checksums(tmp_path, chunk_files):
    from tasks.stores.measurement import write_measurement

    rng = np.random.default_rng(1)
    G = np.eye(4, dtype=np.float32)
    dirs = np.tile([0.0, 0.0, 1.0], (4, 1))
    write_measurement(tmp_path / "m.zarr", rng.random((4, 3, 3, 3)), G, dirs, dirs, (1, 1, 4))
    group = zarr.open_group(str(tmp_path / "m.zarr"), mode="r")
    assert all(has_checksums(a) for _, a in group.arrays())
    chunk_files.flip_byte(chunk_files.path(tmp_path / "m.zarr", "measured", (0, 0, 0, 0)))
    [problem] = verify_store(tmp_path / "m.zarr")
    assert (problem.array, problem.chunk, problem.kind) == ("measured", (0, 0, 0, 0), "corrupt")
    assert "btf ingest --overwrite" in problem.hint


# --------------------------------------------------------------------------- a changed byte


def test_a_flipped_byte_is_named_by_the_reader_and_by_verify_store(capture, chunk_files):
    chunk_files.flip_byte(chunk_files.path(capture, "raw", (0, 1, 3, 0, 0, 0)), offset=1000)
    store = open_capture_store(capture)                        # the frames are not read when opening
    with pytest.raises(CorruptChunkError) as ei:
        store.read_bracket(0, 1, 3)
    e = ei.value
    assert (e.store, e.array, e.chunk) == (str(capture), "raw", (0, 1, 3, 0, 0, 0))
    assert str(e).startswith(f"{capture}: array raw, chunk (0, 1, 3, 0, 0, 0): checksum mismatch (the chunk file "
                             "was changed after it was written); write the capture again")
    assert pickle.loads(pickle.dumps(e)).args == e.args          # crosses Dask / Prefect process boundaries
    assert store.read_bracket(0, 1, 2)[0].shape[0] == store.n_exp   # the other brackets still read
    [problem] = verify_store(capture)
    assert (problem.array, problem.chunk, problem.kind) == ("raw", (0, 1, 3, 0, 0, 0), "corrupt")
    assert str(problem) == str(e)


def test_a_truncated_chunk_is_named_as_truncated(capture, chunk_files):
    path = chunk_files.path(capture, "dark_frames", (1, 0, 0, 0))
    size = path.stat().st_size
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(CorruptChunkError, match=rf"array dark_frames, chunk \(1, 0, 0, 0\): truncated "
                                                rf"\(100 of {size} bytes"):
        CaptureStore(capture).dark_frames[1]
    [problem] = verify_store(capture)
    assert (problem.array, problem.chunk, problem.kind) == ("dark_frames", (1, 0, 0, 0), "truncated")


def test_a_corrupt_small_array_is_a_validation_problem_not_a_crash(capture, chunk_files):
    chunk_files.flip_byte(chunk_files.path(capture, "exposure_time", (0, 2, 0, 0)))
    [problem] = validate_capture_store(capture)
    assert (problem.array, problem.index) == ("exposure_time", "chunk (0, 2, 0, 0)")
    assert problem.found.startswith("checksum mismatch")


# --------------------------------------------------------------------------- a missing chunk


def test_a_missing_chunk_of_a_written_bracket_is_named_not_read_as_zeros(capture, chunk_files):
    chunk_files.path(capture, "raw", (0, 1, 3, 0, 0, 0)).unlink()
    [problem] = validate_capture_store(capture)
    assert (problem.array, problem.index) == ("raw", "chunk (0, 1, 3, 0, 0, 0)")
    assert "chunk file missing" in problem.found and "damaged after writing" in problem.hint
    store = CaptureStore(capture)                                 # unvalidated: the reader checks too
    with pytest.raises(CorruptChunkError, match=r"array raw, chunk \(0, 1, 3, 0, 0, 0\): chunk file missing "
                                                r"although written\[0, 1, 3\] = 1 says it was written"):
        store.read_bracket(0, 1, 3)
    [deep] = verify_store(capture)
    assert (deep.array, deep.chunk, deep.kind) == ("raw", (0, 1, 3, 0, 0, 0), "missing")


def test_an_unwritten_bracket_is_not_a_missing_chunk(tmp_path):
    from tasks.simulate import SimulationConfig, capture_metadata, material_plan

    config = SimulationConfig(device="tiny", n_materials=1, seed=1, classes=("leather",), n_turntable=1,
                              texture_size=8)
    create_capture_store(tmp_path / "c.zarr", capture_metadata(config, material_plan(config)[0],
                                                              config.build_device()))
    assert verify_store(tmp_path / "c.zarr") == []
    assert not any("missing" in p.found for p in validate_capture_store(tmp_path / "c.zarr", require_complete=False))


def test_with_black_level_0_an_absent_chunk_may_be_all_zeros(tmp_path, chunk_files):
    """Zarr does not store a chunk that is all fill value; with black level 0 a black bracket is one."""
    path = write_capture(tmp_path / "c.zarr", black_level=0)
    chunk_files.path(path, "raw", (0, 0, 0, 0, 0, 0)).unlink()
    assert validate_capture_store(path) == [] and verify_store(path) == []


# --------------------------------------------------------------------------- btf validate


def test_validate_deep_names_the_array_and_chunk(capture, capsys, chunk_files):
    chunk_files.flip_byte(chunk_files.path(capture, "raw", (0, 2, 5, 0, 0, 0)))
    code, out = validate(capsys, capture)
    assert code == 0 and out.startswith(f"{capture}: valid"), out           # without --deep: frames unread
    code, out = validate(capsys, capture, "--deep")
    assert code == EXIT_BAD_INPUT, out
    assert f"{capture}: 1 problem(s)" in out
    assert "array raw, chunk (0, 2, 5, 0, 0, 0): checksum mismatch" in out and "note:" not in out


def test_validate_deep_lists_each_missing_chunk_once(capture, capsys, chunk_files):
    chunk_files.path(capture, "raw", (0, 1, 3, 0, 0, 0)).unlink()
    code, out = validate(capsys, capture, "--deep")
    assert code == EXIT_BAD_INPUT and f"{capture}: 1 problem(s)" in out, out
    assert "array raw, chunk (0, 1, 3, 0, 0, 0): chunk file missing" in out


def test_a_store_without_checksums_still_validates_and_says_so(tmp_path, capsys, monkeypatch, chunk_files):
    """A store written before checksums were added: opened, validated, --deep checks what it can."""
    monkeypatch.setattr(integrity, "checksummed", lambda compressors=None: [])
    old = write_capture(tmp_path / "old.zarr")
    monkeypatch.undo()
    assert not has_checksums(zarr.open_group(str(old))["raw"])
    open_capture_store(old)
    for args in ([old], [old, "--deep"]):
        code, out = validate(capsys, *args)
        assert code == 0 and f"{old}: valid" in out and f"note: {CHECKSUM_NOTE}" in out, out
    chunk_files.flip_byte(chunk_files.path(old, "raw", (0, 0, 1, 0, 0, 0)))
    assert verify_store(old) == []                                 # undetectable without a checksum
    path = chunk_files.path(old, "raw", (0, 0, 2, 0, 0, 0))
    path.write_bytes(path.read_bytes()[:-10])
    code, out = validate(capsys, old, "--deep")
    assert code == EXIT_BAD_INPUT and "array raw, chunk (0, 0, 2, 0, 0, 0): truncated" in out, out


def test_validate_opens_other_store_kinds(tmp_path, capsys):
    from tasks.stores.measurement import write_measurement

    dirs = np.tile([0.0, 0.0, 1.0], (4, 1))
    write_measurement(tmp_path / "m.zarr", np.ones((4, 2, 2, 3)), np.eye(4, dtype=np.float32), dirs, dirs, (1, 1, 4))
    code, out = validate(capsys, tmp_path / "m.zarr")
    assert code == 0 and out == f"{tmp_path / 'm.zarr'}: valid\n", out     # schema-checked (validate_deep)
    code, out = validate(capsys, tmp_path / "nothing.zarr", "--deep")
    assert code == EXIT_BAD_INPUT and "nothing at" in out, out


def _created(group: zarr.Group, name: str, checksums: bool, **kwargs) -> zarr.Array:
    """``create_array``, or as a store written before checksums (issue 13) when not ``checksums``."""
    with pytest.MonkeyPatch.context() as patch:
        if not checksums:
            patch.setattr(integrity, "checksummed", lambda compressors=None: [])
        array = create_array(group, name, **kwargs)
    assert has_checksums(array) == checksums
    return array


def _banded(path: Path, checksums: bool = True) -> zarr.Array:
    """A btf-like array: 3 x 4 light/view chunks of 4 texture rows (the last of 2, padded), whole rows."""
    data = np.random.default_rng(8).uniform(0, 1, (12, 10, 5, 3)).astype(np.float32)
    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    array = _created(group, "btf", checksums, shape=data.shape, chunks=(4, 4, 5, 3), dtype="float32", fill_value=0.0)
    array[...] = data
    return array


def _reads(monkeypatch) -> list:
    """Counts the reads that go through Zarr (the fallback) rather than straight from the chunk files."""
    calls: list = []
    original = zarr.Array.get_basic_selection
    monkeypatch.setattr(zarr.Array, "get_basic_selection",
                        lambda self, *a, **k: calls.append(a) or original(self, *a, **k))
    return calls


@pytest.mark.parametrize("checksums", [True, False])
def test_rows_within_one_chunk_row_are_read_without_zarr_and_across_chunk_rows_through_it(tmp_path, monkeypatch,
                                                                                          checksums):
    """Whole chunks straight into the band, sub-bands and the padded edge chunk through a scratch buffer;
    rows that cross a chunk row through Zarr. The same for a store without checksums."""
    array = _banded(tmp_path / "b.zarr", checksums)
    calls = _reads(monkeypatch)
    for start, stop, straight in ((0, 4, True), (4, 8, True), (8, 10, True), (0, 2, True), (5, 6, True),
                                  (9, 10, True), (1, 5, False), (3, 9, False)):
        out = np.full((12, stop - start, 5, 3), np.nan, np.float32)
        before = len(calls)
        integrity.read_chunk_rows(array, start, stop, out)
        np.testing.assert_array_equal(out, array[:, start:stop])
        assert (len(calls) == before) == straight, (start, stop)          # no read through Zarr: straight


def _chunk_bytes(path: Path) -> dict[str, bytes]:
    return {str(f.relative_to(path)): f.read_bytes() for f in sorted(path.rglob("*")) if f.is_file()
            and "zarr.json" not in f.name}


def _direct_io_works(folder: Path) -> bool:
    """Whether this file system takes an O_DIRECT write of one aligned block."""
    import mmap
    import os

    if not hasattr(os, "O_DIRECT"):
        return False
    block = mmap.mmap(-1, 4096)
    try:
        fd = os.open(folder / "probe", os.O_WRONLY | os.O_CREAT | os.O_DIRECT, 0o644)
    except OSError:
        return False
    try:
        return os.write(fd, memoryview(block)[:integrity.DIRECT_BLOCK]) == integrity.DIRECT_BLOCK
    except OSError:
        return False
    finally:
        os.close(fd)
        os.remove(folder / "probe")


@pytest.mark.parametrize("checksums", [True, False])
def test_whole_chunks_are_written_as_zarr_writes_them(tmp_path, monkeypatch, checksums):
    """Blocks of whole chunks give the chunk files Zarr writes, byte for byte (with or without checksums): bands of
    one chunk row from a page-aligned buffer, the padded edge band, a view's rows across every chunk row (copied per
    chunk), light/view parts of a band; a chunk of fill values only is not stored and its old file is removed, as
    Zarr does. The aligned 512-byte blocks go past the page cache where the file system takes O_DIRECT. A block that
    is not whole chunks is refused, naming it."""
    import fcntl
    import os

    from tasks.buffers import prefaulted

    by_zarr, ours = _banded(tmp_path / "zarr.zarr", checksums), _banded(tmp_path / "ours.zarr", checksums)
    data = np.random.default_rng(9).uniform(1, 2, (12, 10, 5, 3)).astype(np.float32)
    data[4:8, 0:4] = 0.0                                            # chunk (1, 0): fill values only
    direct: list[bool] = []
    original = fcntl.fcntl

    def spied(fd, cmd, *args):
        direct.append(bool(cmd == fcntl.F_SETFL and args and args[0] & os.O_DIRECT))
        return original(fd, cmd, *args)

    monkeypatch.setattr(fcntl, "fcntl", spied)

    def both(lv: slice, rows: slice, values: np.ndarray) -> None:
        block = prefaulted(values.size, np.float32).reshape(values.shape)
        block[...] = values
        by_zarr[lv, rows] = block
        write_chunk_aligned(ours, (lv, rows), block)
        assert _chunk_bytes(tmp_path / "ours.zarr") == _chunk_bytes(tmp_path / "zarr.zarr"), (lv, rows)

    for start, stop in ((0, 4), (4, 8), (8, 10)):                   # bands; the last is the padded edge
        both(slice(None), slice(start, stop), data[:, start:stop])
    assert not (tmp_path / "ours.zarr" / "btf" / "c" / "1" / "0" / "0" / "0").exists()
    np.testing.assert_array_equal(ours[...], data)
    both(slice(4, 8), slice(None), -data[4:8])                     # a view: every chunk row, the old fill chunk
    for lv in (slice(8, 12), slice(0, 8)):                          # a band in light/view parts
        both(lv, slice(4, 8), data[lv, 4:8] + 1)
    assert any(direct) == _direct_io_works(tmp_path), direct
    assert not list((tmp_path / "ours.zarr").rglob("*.partial"))
    for lv, rows in ((slice(None), slice(1, 5)), (slice(2, 8), slice(4, 8))):
        with pytest.raises(ValueError, match=r"btf\[.*\] is not chunk-aligned on axis [01]"):
            write_chunk_aligned(ours, (lv, rows), np.ones((12, 4, 5, 3), np.float32))


def test_a_failed_chunk_write_leaves_the_old_file_and_no_partial_one(tmp_path, monkeypatch):
    """A write that fails (a full disk) raises, removes its temporary file and leaves the chunk's old file."""
    import errno
    import os

    from tasks.buffers import prefaulted

    array = _banded(tmp_path / "b.zarr")
    before = _chunk_bytes(tmp_path / "b.zarr")
    band = prefaulted(12 * 4 * 5 * 3, np.float32).reshape(12, 4, 5, 3)
    band[...] = 7.0

    def full(*args):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "pwrite", full)
    with pytest.raises(OSError, match="No space left"):
        write_chunk_aligned(array, (slice(None), slice(0, 4)), band)
    assert _chunk_bytes(tmp_path / "b.zarr") == before


def test_a_damaged_or_missing_chunk_in_a_whole_band_is_left_to_zarr(tmp_path, chunk_files):
    """A flipped byte or a cut file is named as any read names it; a missing chunk reads as fill values."""
    path = tmp_path / "b.zarr"
    array = _banded(path)
    out = np.empty((12, 4, 5, 3), np.float32)
    chunk_files.flip_byte(chunk_files.path(path, "btf", (1, 1, 0, 0)), offset=10)
    with pytest.raises(CorruptChunkError, match=r"array btf, chunk \(1, 1, 0, 0\): checksum mismatch"):
        integrity.read_chunk_rows(array, 4, 8, out)
    cut = chunk_files.path(path, "btf", (2, 0, 0, 0))
    cut.write_bytes(cut.read_bytes()[:50])
    with pytest.raises(CorruptChunkError, match=r"array btf, chunk \(2, 0, 0, 0\): truncated"):
        integrity.read_chunk_rows(array, 0, 4, out)
    cut.unlink()
    integrity.read_chunk_rows(array, 0, 4, out)
    assert not out[8:].any() and out[:8].all()
    sub = np.empty((12, 2, 5, 3), np.float32)                       # the same within a chunk row
    with pytest.raises(CorruptChunkError, match=r"array btf, chunk \(1, 1, 0, 0\): checksum mismatch"):
        integrity.read_chunk_rows(array, 5, 7, sub)
    integrity.read_chunk_rows(array, 1, 3, sub)
    assert not sub[8:].any() and sub[:8].all()


def _raw_like(path: Path, checksums: bool = True) -> zarr.Array:
    """A capture-raw-like array: one uint16 chunk of (exposures, rows, cols) per (view, illumination)."""
    data = np.random.default_rng(9).integers(0, 4096, (1, 2, 5, 3, 8, 9)).astype(np.uint16)
    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    array = _created(group, "raw", checksums, shape=data.shape, chunks=(1, 1, 1, 3, 8, 9), dtype="uint16",
                     fill_value=0)
    array[...] = data
    return array


def test_chunk_windows_are_read_without_zarr_and_damage_is_left_to_it(tmp_path, monkeypatch, chunk_files):
    """Every illumination's window of one view straight from the chunk files, equal to Zarr's read; a flipped
    byte is named as any read names it, a missing chunk reads as fill values (both through Zarr)."""
    array = _raw_like(tmp_path / "c.zarr")
    calls = _reads(monkeypatch)
    window = (slice(None), slice(2, 7), slice(1, 9))
    for view in (0, 1):
        out = np.zeros((5, 3, 5, 8), np.uint16)
        integrity.read_chunk_windows(array, (0, view), window, out)
        np.testing.assert_array_equal(out, array[(0, view, slice(None), *window)])
    assert not calls                                                    # no read through Zarr
    chunk_files.flip_byte(chunk_files.path(tmp_path / "c.zarr", "raw", (0, 1, 3, 0, 0, 0)), offset=7)
    with pytest.raises(CorruptChunkError, match=r"array raw, chunk \(0, 1, 3, 0, 0, 0\): checksum mismatch"):
        integrity.read_chunk_windows(array, (0, 1), window, out)
    chunk_files.path(tmp_path / "c.zarr", "raw", (0, 1, 3, 0, 0, 0)).unlink()
    integrity.read_chunk_windows(array, (0, 1), window, out)
    assert calls and not out[3].any()
    np.testing.assert_array_equal(out[[0, 1, 2, 4]], array[(0, 1, [0, 1, 2, 4], *window)])


def test_chunk_windows_of_a_store_without_checksums_are_read_without_zarr(tmp_path, monkeypatch):
    """A store written before checksums (issue 13) is read straight from its chunk files too; a cut file is
    left to Zarr, which names it."""
    array = _raw_like(tmp_path / "c.zarr", checksums=False)
    calls = _reads(monkeypatch)
    window = (slice(None), slice(1, 8), slice(0, 9))
    out = np.zeros((5, 3, 7, 9), np.uint16)
    integrity.read_chunk_windows(array, (0, 1), window, out)
    np.testing.assert_array_equal(out, array[(0, 1, slice(None), *window)])
    assert not calls
    cut = tmp_path / "c.zarr" / "raw" / "c" / "0" / "1" / "2" / "0" / "0" / "0"
    cut.write_bytes(cut.read_bytes()[:-2])
    with pytest.raises(CorruptChunkError, match=r"array raw, chunk \(0, 1, 2, 0, 0, 0\)"):
        integrity.read_chunk_windows(array, (0, 1), window, out)
    assert calls
