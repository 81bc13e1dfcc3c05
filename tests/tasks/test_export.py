"""OpenEXR export round trip through the real OpenEXR library."""

from __future__ import annotations

import numpy as np
import OpenEXR
import pytest
import zarr

from tasks.export import export_exr, parse_selection


def _btf_store(path, n_lv=5, h=6, w=7):
    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    rng = np.random.default_rng(0)
    data = rng.lognormal(0, 2, (n_lv, h, w, 3)).astype(np.float32)
    group.create_array("btf", data=data)
    dirs = rng.normal(size=(n_lv, 3))
    dirs[:, 2] = np.abs(dirs[:, 2])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    group.create_array("light_dir", data=dirs)
    group.create_array("view_dir", data=dirs[::-1].copy())
    group.create_array("lv_index", data=np.stack([np.zeros(n_lv), np.zeros(n_lv), np.arange(n_lv)], 1).astype(np.int32))
    group.attrs["schema"] = "btf-texture"
    return data


def test_exr_round_trip_is_exact(tmp_path):
    data = _btf_store(tmp_path / "b.zarr")
    files = export_exr(tmp_path / "b.zarr", tmp_path / "exr", parse_selection("1,3-4", 5))
    assert [f.name for f in files] == ["lv00001_t0_c0_l1.exr", "lv00003_t0_c0_l3.exr", "lv00004_t0_c0_l4.exr"]
    for f, row in zip(files, (1, 3, 4)):
        with OpenEXR.File(str(f)) as exr:
            np.testing.assert_array_equal(exr.channels()["RGB"].pixels, data[row])
            assert "btf_light_dir" in exr.header()


def test_bad_selection_and_store(tmp_path):
    with pytest.raises(ValueError, match="outside 0..4"):
        parse_selection("2,9", 5)
    with pytest.raises(ValueError, match="neither an index nor a range"):
        parse_selection("x", 5)
    zarr.open_group(str(tmp_path / "other.zarr"), mode="w", zarr_format=3)
    with pytest.raises(ValueError, match="not a BTF store"):
        export_exr(tmp_path / "other.zarr", tmp_path / "exr")
