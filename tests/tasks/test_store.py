"""Tests of the capture store (tasks/stores/capture*.py) on real Zarr v3 stores on disk."""

from __future__ import annotations

import json
import os
import pickle
import shutil

import numpy as np
import pytest
import zarr

from tasks.stores import (
    BAYER_PATTERNS,
    CaptureMetadata,
    CaptureStore,
    CaptureStoreError,
    Problem,
    create_capture_store,
    open_capture_store,
    to_json_attr,
    validate_capture_store,
    write_chunk_aligned,
)
from tasks.stores.capture import SCHEMA_NAME, SCHEMA_VERSION

N_TURN, N_CAM, N_ILLUM, N_EXP, ROWS, COLS = 2, 2, 3, 2, 8, 8
N_LEDS, N_DARK = 4, 2
TEX = (4, 4)
S = 0.02  # sample side, m


# --------------------------------------------------------------------------
# A tiny synthetic dome
# --------------------------------------------------------------------------


def look_at(centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World->camera (R, t) of a camera at ``centre`` looking at the origin (OpenCV axes)."""
    z = -centre / np.linalg.norm(centre)
    up = np.array([0.0, 1.0, 0.0])
    y = -(up - (up @ z) * z)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    R = np.stack([x, y, z])
    return R, -R @ centre


def rot_z(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def tiny_meta(config_hash: str = "abc123", **over) -> CaptureMetadata:
    f = 200.0  # px: the 2 cm sample spans ~4 px at 1 m
    K = np.array([[f, 0, (COLS - 1) / 2], [0, f, (ROWS - 1) / 2], [0, 0, 1]])
    centres = [np.array([0.0, 0.0, 1.0]), np.array([0.0, -np.sin(0.5), np.cos(0.5)])]
    Rs, ts = zip(*(look_at(cc) for cc in centres))
    angles = np.array([0.0, 30.0])
    H = np.empty((N_TURN, N_CAM, 3, 3))
    for ti, ang in enumerate(angles):
        Rt = rot_z(ang)  # sample frame -> world
        for ci in range(N_CAM):
            H[ti, ci] = K @ np.column_stack([Rs[ci] @ Rt[:, 0], Rs[ci] @ Rt[:, 1], ts[ci]])
    illum = np.array([[1, 0, 0, 0], [0, 1, 1, 0], [1, 1, 0, 1]], dtype=np.uint8)
    leds = np.array([[0.5, 0, 0.8], [0, 0.5, 0.8], [-0.5, 0, 0.8], [0, -0.5, 0.8]])
    kw = dict(
        device="tiny-dome", bayer_pattern="RGGB", black_level=64, white_level=4095, bit_depth=12,
        sensor={"gain_e_per_dn": 2.5, "read_noise_e": 3.0, "full_well_e": None,
                "dark_current_e_per_s": 0.1},
        sample_size_m=S, texture_shape=TEX, illumination=illum, led_position=leds,
        camera_K=np.stack([K, K]), camera_R=np.stack(Rs), camera_t=np.stack(ts),
        turntable_angle=angles, homography=H, dark_exposure_time=np.array([0.01, 0.1]),
        n_exp=N_EXP, roi_shape=(ROWS, COLS),
        provenance={"code_version": "0.1.0", "config_hash": config_hash, "seed": 7,
                    "created": "2026-11-02T10:00:00+00:00", "source": "simulator",
                    "input_stores": []},
    )
    kw.update(over)
    return CaptureMetadata(**kw)


def view_data(t: int, c: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(100 * t + c)
    frames = rng.integers(1, 4096, size=(N_ILLUM, N_EXP, ROWS, COLS), dtype=np.uint16)
    et = np.array([[0.001, 0.004]] * N_ILLUM) * (1 + t + 2 * c)
    return frames, et


def truth_view(t: int, c: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1000 + 10 * t + c)
    h, w = TEX
    return (rng.random((N_LEDS, h, w, 3), dtype=np.float32),
            rng.random((N_LEDS, 2 * h, 2 * w, 3), dtype=np.float32))


def truth_dirs():
    n = N_TURN * N_CAM * N_LEDS
    rng = np.random.default_rng(5)
    ld = rng.normal(size=(n, 3)); ld[:, 2] = np.abs(ld[:, 2]) + 0.1
    vd = rng.normal(size=(n, 3)); vd[:, 2] = np.abs(vd[:, 2]) + 0.1
    ld /= np.linalg.norm(ld, axis=1, keepdims=True)
    vd /= np.linalg.norm(vd, axis=1, keepdims=True)
    li = np.indices((N_TURN, N_CAM, N_LEDS)).reshape(3, -1).T
    return ld, vd, li


def fill(store: CaptureStore, views=None) -> None:
    views = views if views is not None else [(t, c) for t in range(N_TURN) for c in range(N_CAM)]
    for t, c in views:
        store.write_bracket(t, c, *view_data(t, c))
        if store.has_truth:
            store.write_truth_view(t, c, *truth_view(t, c))


def finish(store: CaptureStore) -> None:
    fill(store)
    store.write_dark_frames(np.full((N_CAM, N_DARK, ROWS, COLS), 70, np.uint16))
    if store.has_truth:
        store.write_truth_directions(*truth_dirs())
    store.mark_complete()


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> str:
    """A complete, valid store with ground truth (copied per test)."""
    path = str(tmp_path_factory.mktemp("tpl") / "capture.zarr")
    store = create_capture_store(path, tiny_meta(), with_truth=True)
    finish(store)
    return path


@pytest.fixture
def good(template, tmp_path) -> str:
    path = str(tmp_path / "capture.zarr")
    shutil.copytree(template, path)
    return path


def rw(path: str) -> zarr.Group:
    return zarr.open_group(path, mode="r+", zarr_format=3)


def problems_of(path, **kw) -> tuple[list[Problem], str]:
    with pytest.raises(CaptureStoreError) as ei:
        open_capture_store(path, **kw)
    assert ei.value.problems == validate_capture_store(path, **kw)
    return ei.value.problems, str(ei.value)


# --------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------


def test_metadata_round_trip(tmp_path):
    meta = tiny_meta()
    path = tmp_path / "c.zarr"
    create_capture_store(path, meta)
    store = open_capture_store(path, require_complete=False)
    got = store.meta
    for f in ("device", "bayer_pattern", "black_level", "white_level", "bit_depth",
              "sample_size_m", "n_exp"):
        assert getattr(got, f) == getattr(meta, f), f
    assert got.sensor == meta.sensor
    assert got.texture_shape == TEX and got.roi_shape == (ROWS, COLS)
    assert got.provenance == meta.provenance
    for f in ("illumination", "led_position", "camera_K", "camera_R", "camera_t",
              "turntable_angle", "homography", "dark_exposure_time"):
        np.testing.assert_array_equal(getattr(got, f), getattr(meta, f), err_msg=f)
    assert got.illumination.dtype == np.uint8 and got.homography.dtype == np.float64
    assert (store.n_turn, store.n_cam, store.n_illum, store.n_exp) == (N_TURN, N_CAM, N_ILLUM, N_EXP)
    assert (store.n_leds, store.n_dark, store.roi_shape) == (N_LEDS, N_DARK, (ROWS, COLS))
    assert store.n_lv == N_TURN * N_CAM * N_LEDS
    assert store.raw.shape == (N_TURN, N_CAM, N_ILLUM, N_EXP, ROWS, COLS)
    assert store.raw.chunks == (1, 1, 1, N_EXP, ROWS, COLS)
    assert store.group["exposure_time"].chunks == (1, 1, N_ILLUM, N_EXP)
    assert store.group["written"].chunks == (1, 1, N_ILLUM)
    assert store.raw.metadata.dimension_names == (
        "turntable", "camera", "illumination", "exposure", "row", "col")
    a = store.attrs
    assert (a["schema"], a["schema_version"]) == (SCHEMA_NAME, SCHEMA_VERSION)
    assert a["lv_order"] == ["turntable", "camera", "light"]
    assert a["units"] == {"exposure_time": "s", "positions": "m", "turntable_angle": "deg"}
    assert a["complete"] is False and not store.complete
    assert not store.has_truth


def test_brackets_round_trip_and_complete(tmp_path):
    path = tmp_path / "c.zarr"
    store = create_capture_store(path, tiny_meta(), with_truth=True)
    finish(store)
    store = open_capture_store(path)  # require_complete=True
    assert store.complete
    for t in range(N_TURN):
        for c in range(N_CAM):
            frames, et = view_data(t, c)
            for i in range(N_ILLUM):
                got_f, got_e = store.read_bracket(t, c, i)
                assert got_f.dtype == np.uint16 and got_e.dtype == np.float64
                np.testing.assert_array_equal(got_f, frames[i])
                np.testing.assert_array_equal(got_e, et[i])
            btf, btf2 = truth_view(t, c)
            lv0 = (t * N_CAM + c) * N_LEDS
            np.testing.assert_array_equal(store.truth["btf"][lv0:lv0 + N_LEDS], btf)
            np.testing.assert_array_equal(store.truth["btf_2x"][lv0:lv0 + N_LEDS], btf2)
    np.testing.assert_array_equal(store.truth["lv_index"][...], truth_dirs()[2])
    np.testing.assert_array_equal(store.dark_frames[...], 70)
    assert store.pending_views() == []


@pytest.mark.parametrize("dtype", [np.uint16, np.int32, np.uint8])
def test_write_bracket_accepts_integer_dtypes(tmp_path, dtype):
    store = create_capture_store(tmp_path / "c.zarr", tiny_meta())
    frames, et = view_data(1, 0)
    frames = (frames % 256).astype(dtype)
    store.write_bracket(1, 0, frames, et)
    got, _ = store.read_bracket(1, 0, 2)
    assert got.dtype == np.uint16
    np.testing.assert_array_equal(got, frames[2])


# --------------------------------------------------------------------------
# Chunk ownership
# --------------------------------------------------------------------------


def chunk_files(path, array: str) -> set[tuple[int, ...]]:
    root = os.path.join(path, array, "c")
    out = set()
    for d, _, files in os.walk(root):
        for f in files:
            rel = os.path.relpath(os.path.join(d, f), root)
            out.add(tuple(int(x) for x in rel.split(os.sep)))
    return out


def test_write_bracket_owns_exactly_its_chunks(tmp_path):
    path = str(tmp_path / "c.zarr")
    store = create_capture_store(path, tiny_meta(), with_truth=True)
    assert chunk_files(path, "raw") == set()
    store.write_bracket(0, 1, *view_data(0, 1))
    assert chunk_files(path, "raw") == {(0, 1, i, 0, 0, 0) for i in range(N_ILLUM)}
    assert chunk_files(path, "exposure_time") == {(0, 1, 0, 0)}
    assert chunk_files(path, "written") == {(0, 1, 0)}
    store.write_bracket(1, 0, *view_data(1, 0))
    assert chunk_files(path, "raw") == {(t, c, i, 0, 0, 0) for t, c in [(0, 1), (1, 0)]
                                        for i in range(N_ILLUM)}
    # the other views still read as the fill value
    assert not store.raw[0, 0].any() and not store.raw[1, 1].any()
    np.testing.assert_array_equal(store.written[:, :, 0], [[0, 1], [1, 0]])
    store.write_truth_view(1, 0, *truth_view(1, 0))
    assert chunk_files(path, "truth/btf") == {(2, 0, 0, 0)}  # lv block (1*2+0)
    assert chunk_files(path, "truth/written") == {(1, 0)}


def test_write_bracket_is_idempotent(tmp_path):
    store = create_capture_store(tmp_path / "c.zarr", tiny_meta())
    frames, et = view_data(1, 1)
    store.write_bracket(1, 1, np.zeros_like(frames), et)
    store.write_bracket(1, 1, frames, et)
    np.testing.assert_array_equal(store.raw[1, 1], frames)


@pytest.mark.parametrize("selection", [
    (0, 0, 0, 0),                         # one exposure of a bracket
    (0, 0, 0, slice(None), slice(0, 4)),  # half the rows
    (0, 0, slice(1, 3), slice(0, 1)),     # part of the exposure axis
])
def test_partial_chunk_write_refused(tmp_path, selection):
    store = create_capture_store(tmp_path / "c.zarr", tiny_meta())
    before = store.raw[...]
    with pytest.raises(ValueError, match="not chunk-aligned"):
        write_chunk_aligned(store.raw, selection, 1)
    np.testing.assert_array_equal(store.raw[...], before)


def test_chunk_aligned_blocks_accepted(tmp_path):
    store = create_capture_store(tmp_path / "c.zarr", tiny_meta())
    write_chunk_aligned(store.raw, (1, slice(0, 2)), 9)
    write_chunk_aligned(store.group["exposure_time"], (slice(0, 1), 1), 3.0)
    assert (store.raw[1] == 9).all() and not store.raw[0].any()
    assert (store.exposure_time[0, 1] == 3).all() and not store.exposure_time[1].any()
    with pytest.raises(ValueError, match="not chunk-aligned on axis 2"):
        write_chunk_aligned(store.group["exposure_time"], (0, 0, 1), 3.0)


@pytest.mark.parametrize("bad, match", [
    (lambda f, e: (f[:, :1], e), "expected shape"),
    (lambda f, e: (f.astype(np.float32), e), "integer raw DN"),
    (lambda f, e: (f | np.uint16(4096), e), "12-bit range"),
    (lambda f, e: (f, e[:, ::-1]), r"\(t, c, i\)=\(1, 1, 0\)"),
    (lambda f, e: (f, np.where(np.arange(3)[:, None] == 2, -e, e)), r"\(1, 1, 2\)"),
])
def test_write_bracket_refuses_bad_input(tmp_path, bad, match):
    store = create_capture_store(tmp_path / "c.zarr", tiny_meta())
    with pytest.raises(ValueError, match=match):
        store.write_bracket(1, 1, *bad(*view_data(1, 1)))
    assert not store.written.any() and not store.raw[1, 1].any()


def test_read_only_store_refuses_writes(good):
    store = open_capture_store(good)
    with pytest.raises(PermissionError, match="read-only"):
        store.write_bracket(0, 0, *view_data(0, 0))


# --------------------------------------------------------------------------
# Resume and (re)creation
# --------------------------------------------------------------------------


def test_resume_after_partial_writes(tmp_path):
    path = tmp_path / "c.zarr"
    store = create_capture_store(path, tiny_meta(), with_truth=True)
    assert store.pending_views() == [(0, 0), (0, 1), (1, 0), (1, 1)]
    store.write_bracket(0, 1, *view_data(0, 1))
    store.write_truth_view(0, 1, *truth_view(0, 1))
    store.write_bracket(1, 1, *view_data(1, 1))  # killed before its truth was written
    # a torn bracket: data landed, marker did not
    write_chunk_aligned(store.raw, (1, 0), view_data(1, 0)[0])
    assert store.pending_views() == [(0, 0), (1, 0), (1, 1)]
    with pytest.raises(CaptureStoreError):
        open_capture_store(path)

    again = create_capture_store(path, tiny_meta(), with_truth=True)  # resume
    assert again.pending_views() == [(0, 0), (1, 0), (1, 1)]
    np.testing.assert_array_equal(again.raw[0, 1], view_data(0, 1)[0])
    for t, c in again.pending_views():
        again.write_bracket(t, c, *view_data(t, c))
        again.write_truth_view(t, c, *truth_view(t, c))
    assert again.pending_views() == []
    again.write_dark_frames(np.full((N_CAM, N_DARK, ROWS, COLS), 70, np.uint16))
    again.write_truth_directions(*truth_dirs())
    again.mark_complete()
    assert open_capture_store(path).complete


def test_create_refuses_complete_store(good):
    with pytest.raises(FileExistsError, match="overwrite=True") as ei:
        create_capture_store(good, tiny_meta(), with_truth=True)
    assert good in str(ei.value)
    assert open_capture_store(good).complete  # untouched
    fresh = create_capture_store(good, tiny_meta(), overwrite=True)
    assert not fresh.complete and not fresh.has_truth
    assert len(fresh.pending_views()) == N_TURN * N_CAM and not fresh.raw[...].any()


def test_create_refuses_other_config(tmp_path):
    path = tmp_path / "c.zarr"
    create_capture_store(path, tiny_meta("hash-A")).write_bracket(0, 0, *view_data(0, 0))
    with pytest.raises(FileExistsError, match="'hash-A'.*'hash-B'"):
        create_capture_store(path, tiny_meta("hash-B"))
    with pytest.raises(FileExistsError, match="device"):  # same hash, other metadata
        create_capture_store(path, tiny_meta("hash-A", device="other"))
    with pytest.raises(FileExistsError, match="with_truth"):
        create_capture_store(path, tiny_meta("hash-A"), with_truth=True)
    assert create_capture_store(path, tiny_meta("hash-A")).written[0, 0].all()


def test_create_refuses_foreign_directory(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "notes.txt").write_text("hi")
    with pytest.raises(FileExistsError, match="not a capture store"):
        create_capture_store(tmp_path / "x", tiny_meta())
    create_capture_store(tmp_path / "empty", tiny_meta())  # missing dir is fine


def test_mark_complete_names_missing_brackets(tmp_path):
    store = create_capture_store(tmp_path / "c.zarr", tiny_meta())
    fill(store, [(0, 0), (0, 1), (1, 0)])
    store.write_dark_frames(np.zeros((N_CAM, N_DARK, ROWS, COLS), np.uint16))
    with pytest.raises(CaptureStoreError) as ei:
        store.mark_complete()
    msg = str(ei.value)
    assert "(1, 1, 0), (1, 1, 1), (1, 1, 2)" in msg and "3 of 12 bracket(s)" in msg
    assert "btf simulate" in msg
    assert not store.complete


def test_mark_complete_requires_dark_frames(tmp_path):
    store = create_capture_store(tmp_path / "c.zarr", tiny_meta())
    fill(store)
    store.write_dark_frames(np.zeros((N_DARK, ROWS, COLS), np.uint16), camera=1)
    with pytest.raises(CaptureStoreError, match=r"dark_written\[camera 0\]"):
        store.mark_complete()
    store.write_dark_frames(np.zeros((N_DARK, ROWS, COLS), np.uint16), camera=0)
    store.mark_complete()


# --------------------------------------------------------------------------
# Metadata validation at creation
# --------------------------------------------------------------------------


def test_create_validates_metadata_before_writing(tmp_path):
    path = tmp_path / "c.zarr"
    R = tiny_meta().camera_R.copy()
    R[1] *= 2
    with pytest.raises(CaptureStoreError) as ei:
        create_capture_store(path, tiny_meta(bayer_pattern="RGBG", camera_R=R,
                                             turntable_angle=np.zeros(3)))
    arrays = {p.array for p in ei.value.problems}
    assert {"attrs", "camera_R", "homography"} <= arrays, ei.value.problems
    assert "turntable_angle" in str(ei.value)
    assert not path.exists()


def test_attrs_are_plain_json(tmp_path):
    meta = tiny_meta(black_level=np.int64(64), white_level=np.uint16(4095),
                     sample_size_m=np.float32(0.02), texture_shape=np.array(TEX),
                     n_exp=np.int64(N_EXP))
    meta.provenance["extra"] = {"gains": np.array([1.5, 2.0]), "n": np.int32(3)}
    store = create_capture_store(tmp_path / "c.zarr", meta)

    def no_constants(x):
        raise AssertionError(f"non-standard JSON constant {x}")

    with open(tmp_path / "c.zarr" / "zarr.json") as f:
        doc = json.load(f, parse_constant=no_constants)
    a = doc["attributes"]
    assert a["black_level"] == 64 and type(a["black_level"]) is int
    assert a["texture_shape"] == [4, 4]
    assert a["provenance"]["extra"] == {"gains": [1.5, 2.0], "n": 3}
    assert a["sensor"]["full_well_e"] is None
    json.dumps(store.attrs, allow_nan=False)


def test_nan_attrs_refused(tmp_path):
    meta = tiny_meta()
    meta.sensor["full_well_e"] = float("nan")
    with pytest.raises(CaptureStoreError, match="full_well_e"):
        create_capture_store(tmp_path / "c.zarr", meta)
    with pytest.raises(ValueError, match="finite"):
        to_json_attr({"a": [1.0, np.float64("inf")]})
    assert not (tmp_path / "c.zarr").exists()


# --------------------------------------------------------------------------
# Validation of stored captures: one corruption each
# --------------------------------------------------------------------------


def set_attr(key, value):
    def f(path):
        rw(path).attrs[key] = value
    return f


def set_nested(key, sub, value):
    def f(path):
        g = rw(path)
        d = dict(g.attrs[key])
        d[sub] = value
        g.attrs[key] = d
    return f


def set_values(array, index, value):
    def f(path):
        rw(path)[array][index] = value
    return f


def recreate(array, data, **kw):
    def f(path):
        g = rw(path)
        parent, _, name = array.rpartition("/")
        grp = g[parent] if parent else g
        del grp[name]
        grp.create_array(name, data=np.asarray(data), **kw)
    return f


def delete(array):
    def f(path):
        del rw(path)[array]
    return f


def bad_rotation(path):
    g = rw(path)
    R = g["camera_R"][...]
    R[1] = R[1] @ np.diag([1.0, 1.0, -1.0])  # a reflection: det -1
    g["camera_R"][...] = R


def shifted_homography(path):
    g = rw(path)
    H = g["homography"][...]
    H[0, 1] = np.array([[1, 0, 20], [0, 1, 0], [0, 0, 1.0]]) @ H[0, 1]  # 20 px to the right
    g["homography"][...] = H


def non_increasing(path):
    g = rw(path)
    g["exposure_time"][1, 0, 2] = [0.004, 0.004]


CORRUPTIONS = {
    "schema name": (set_attr("schema", "btf-other"), "attrs", "schema", ["'btf-other'"]),
    "schema version": (set_attr("schema_version", "0.9"), "attrs", "schema_version", ["'0.9'"]),
    "missing attr": (lambda p: rw(p).attrs.__delitem__("bit_depth"), "attrs", "bit_depth", ["nothing"]),
    "bayer": (set_attr("bayer_pattern", "RGBG"), "attrs", "bayer_pattern", ["RGGB", "'RGBG'"]),
    "black >= white": (set_attr("black_level", 5000), "attrs", "black_level", ["white_level"]),
    "white > 2^bd": (set_attr("white_level", 5000), "attrs", "white_level", ["4095"]),
    "sensor": (set_nested("sensor", "gain_e_per_dn", -1.0), "attrs", "sensor.gain_e_per_dn", ["> 0"]),
    "provenance": (set_nested("provenance", "source", "camera"), "attrs", "provenance.source", ["ingest"]),
    "exposure not increasing": (non_increasing, "exposure_time", "(1, 0, 2)", ["strictly increasing"]),
    "exposure <= 0": (set_values("exposure_time", (0, 1, 1, 0), 0.0), "exposure_time", "(0, 1, 1)", ["> 0"]),
    "exposure NaN": (set_values("exposure_time", (1, 1, 0, 1), np.nan), "exposure_time", "(1, 1, 0)", ["NaN"]),
    "led NaN": (set_values("led_position", (2, 1), np.nan), "led_position", "(2, 1)", ["NaN/Inf"]),
    "led below": (set_values("led_position", (3, 2), -0.1), "led_position", "led 3", ["z > 0"]),
    "homography Inf": (set_values("homography", (1, 0, 0, 2), np.inf), "homography", "(1, 0, 0, 2)", ["NaN/Inf"]),
    "illum not binary": (set_values("illumination", (1, 2), 2), "illumination", "(1, 2)", ["binary"]),
    "illum dark row": (set_values("illumination", 2, 0), "illumination", "row 2", ["at least one LED"]),
    "rotation": (bad_rotation, "camera_R", "camera 1", ["det"]),
    "K": (set_values("camera_K", (0, 0, 0), -200.0), "camera_K", "camera 0", ["fx, fy > 0"]),
    "homography singular": (set_values("homography", (1, 0), 0.0), "homography", "(1, 0)", ["invertible"]),
    "homography outside": (shifted_homography, "homography", "(0, 1)", ["inside", "8x8"]),
    "dark times": (set_values("dark_exposure_time", 1, 0.001), "dark_exposure_time", "dark 1",
                   ["strictly increasing"]),
    "missing array": (delete("exposure_time"), "exposure_time", None, ["array 'exposure_time'"]),
    "wrong dtype": (recreate("turntable_angle", np.array([0.0, 30.0], np.float32),
                             dimension_names=["turntable"]),
                    "turntable_angle", None, ["float64", "float32"]),
    "shape mismatch": (recreate("turntable_angle", np.zeros(3), dimension_names=["turntable"]),
                       "turntable_angle", "axis 0 (turntable)", ["length 2", "raw axis 0", "length 3"]),
    "wrong ndim": (recreate("camera_t", np.zeros((2, 3, 1)), dimension_names=["camera", "xyz", "x"]),
                   "camera_t", None, ["2 dimensions"]),
    "wrong chunks": (recreate("written", np.ones((2, 2, 3), np.uint8), chunks=(2, 2, 3),
                              dimension_names=["turntable", "camera", "illumination"]),
                     "written", "chunks", ["(1, 1, 3)"]),
    "truth vs n_lv": (recreate("truth/light_dir", np.tile([0, 0, 1.0], (15, 1)),
                               dimension_names=["lv", "xyz"]),
                      "truth/light_dir", "axis 0 (lv)", ["length 16", "length 15"]),
    "truth not unit": (set_values("truth/view_dir", 5, [0, 0, 2.0]), "truth/view_dir", "lv 5", ["unit"]),
    "truth btf shape": (recreate("truth/btf", np.zeros((16, 4, 5, 3), np.float32),
                                 chunks=(4, 4, 5, 3), dimension_names=["lv", "tex_row", "tex_col", "channel"]),
                        "truth/btf", "axis 2 (tex_col)", ["texture_shape"]),
    "incomplete": (set_values("written", (1, 0, 1), 0), "written", "(1, 0, 1)",
                   ["1 of 12 bracket(s) not written", "although attrs['complete'] is true", "btf simulate"]),
}


@pytest.mark.parametrize("case", list(CORRUPTIONS))
def test_validation_names_array_and_index(good, case):
    corrupt, array, index, needles = CORRUPTIONS[case]
    assert validate_capture_store(good) == []
    corrupt(good)
    problems, msg = problems_of(good)
    hits = [p for p in problems if p.array == array and (index is None or index in (p.index or ""))]
    assert hits, f"no problem for {array}[{index}] in:\n{msg}"
    text = str(hits[0])
    for needle in needles:
        assert needle in text, f"{needle!r} not in {text!r}"
    assert hits[0].hint and good in msg
    assert f"{good}: {array}" in msg


def test_incomplete_store_lists_missing_and_count(tmp_path):
    path = str(tmp_path / "c.zarr")
    store = create_capture_store(path, tiny_meta())
    store.write_bracket(0, 0, *view_data(0, 0))
    assert validate_capture_store(path, require_complete=False) == []
    open_capture_store(path, require_complete=False)
    problems, msg = problems_of(path)
    (p,) = [p for p in problems if p.array == "written"]
    assert "(0, 1, 0), (0, 1, 1), (0, 1, 2), (1, 0, 0)" in p.index
    assert "(1, 1, 2)" in p.index and "more" not in p.index and "9 of 12" in p.found
    assert "dark_written" in msg and "btf simulate" in msg and "require_complete=False" in msg
    create_capture_store(tmp_path / "none.zarr", tiny_meta())
    (p,) = [p for p in validate_capture_store(tmp_path / "none.zarr") if p.array == "written"]
    assert p.index.endswith("(1, 0, 2), (1, 1, 0) (+2 more, 12 in all)"), p.index


def test_not_marked_complete(tmp_path):
    path = str(tmp_path / "c.zarr")
    store = create_capture_store(path, tiny_meta())
    fill(store)
    store.write_dark_frames(np.zeros((N_CAM, N_DARK, ROWS, COLS), np.uint16))
    problems, msg = problems_of(path)
    assert [(p.array, p.index) for p in problems] == [("attrs", "complete")]
    assert "mark_complete" in msg


def test_many_problems_reported_at_once(good):
    set_attr("bayer_pattern", "XXXX")(good)
    set_values("exposure_time", (0, 0, 0, 0), -1.0)(good)
    bad_rotation(good)
    set_values("illumination", 0, 0)(good)
    delete("turntable_angle")(good)
    set_values("written", (1, 1, 2), 0)(good)
    problems, msg = problems_of(good)
    arrays = {p.array for p in problems}
    assert {"attrs", "exposure_time", "camera_R", "illumination", "turntable_angle",
            "written"} <= arrays
    assert len(problems) >= 6
    assert msg.count(f"  - {good}: ") == len(problems)
    assert "problems:" in msg.splitlines()[0]


def test_missing_or_foreign_path(tmp_path):
    (p,) = validate_capture_store(tmp_path / "nope.zarr")
    assert p.array == "<store>" and "nope.zarr" in p.found
    with pytest.raises(CaptureStoreError, match="nope.zarr"):
        open_capture_store(tmp_path / "nope.zarr")
    (tmp_path / "plain").mkdir()
    (p,) = validate_capture_store(tmp_path / "plain")
    assert "Zarr v3 group" in p.expected


def test_error_pickles(good):
    set_attr("bayer_pattern", "XXXX")(good)
    with pytest.raises(CaptureStoreError) as ei:
        open_capture_store(good)
    err = pickle.loads(pickle.dumps(ei.value))
    assert err.problems == ei.value.problems and str(err) == str(ei.value)
    assert isinstance(err, ValueError)


def test_truth_writers_check_input(tmp_path):
    store = create_capture_store(tmp_path / "c.zarr", tiny_meta(), with_truth=True)
    btf, btf2 = truth_view(0, 0)
    with pytest.raises(ValueError, match="expected shape"):
        store.write_truth_view(0, 0, btf[:, :2], btf2)
    btf[0, 0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        store.write_truth_view(0, 0, btf, btf2)
    ld, vd, li = truth_dirs()
    with pytest.raises(ValueError, match="row-major"):
        store.write_truth_directions(ld, vd, li[::-1])
    with pytest.raises(ValueError, match="unit"):
        store.write_truth_directions(2 * ld, vd, li)
    store.write_truth_map("albedo", np.full((4, 4, 3), 0.5, np.float32))
    store.set_truth_material({"class": "leather", "roughness": np.float32(0.25)})
    assert store.truth["maps_albedo"].shape == (4, 4, 3)
    assert store.truth.attrs["material"] == {"class": "leather", "roughness": 0.25}
    plain = create_capture_store(tmp_path / "p.zarr", tiny_meta())
    with pytest.raises(KeyError, match="with_truth"):
        plain.write_truth_view(0, 0, *truth_view(0, 0))


def test_bayer_patterns_constant():
    assert BAYER_PATTERNS == ("RGGB", "BGGR", "GRBG", "GBRG")
