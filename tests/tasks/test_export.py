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


def test_nonfinite_textures_are_refused_before_anything_is_written(tmp_path, capsys):
    """Issue 13: `btf export-exr` wrote NaN textures without a word. Every selected row is checked
    first; the message names the store, the rows and their counts; `--keep-nonfinite` writes them."""
    from flows.cli import EXIT_BAD_INPUT, main

    data = _btf_store(tmp_path / "b.zarr")
    group = zarr.open_group(str(tmp_path / "b.zarr"), mode="r+")
    bad = data.copy()
    bad[3, 0, :3, 1] = np.nan                                      # 3 texels
    bad[4, 5, 6, :] = np.inf                                       # 1 texel, all channels
    group["btf"][...] = bad
    out = tmp_path / "exr"
    with pytest.raises(ValueError) as err:
        export_exr(tmp_path / "b.zarr", out)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(str(tmp_path / "b.zarr"))
    assert "in 2 of the 5 selected rows" in msg and "row 3: 3 of 42 texels" in msg and "row 4: 1 of 42 texels" in msg
    assert "--keep-nonfinite" in msg
    assert not out.exists()                                        # nothing partial: not even the folder
    # the rows before the bad ones are not written either; a selection without them is fine
    assert [f.name for f in export_exr(tmp_path / "b.zarr", out, [0, 1, 2])] == \
        ["lv00000_t0_c0_l0.exr", "lv00001_t0_c0_l1.exr", "lv00002_t0_c0_l2.exr"]

    code = main(["export-exr", str(tmp_path / "b.zarr"), "--out", str(tmp_path / "cli")])
    stderr = capsys.readouterr().err
    assert code == EXIT_BAD_INPUT and "row 3: 3 of 42 texels" in stderr and not (tmp_path / "cli").exists()
    assert stderr.count(str(tmp_path / "b.zarr")) == 1, stderr      # the store is named once
    code = main(["export-exr", str(tmp_path / "b.zarr"), "--out", str(tmp_path / "cli"), "--keep-nonfinite"])
    assert code == 0, capsys.readouterr().err
    with OpenEXR.File(str(tmp_path / "cli" / "lv00003_t0_c0_l3.exr")) as exr:
        np.testing.assert_array_equal(exr.channels()["RGB"].pixels, bad[3])   # NaN kept as it was
    assert len(list((tmp_path / "cli").glob("*.exr"))) == 5


def test_export_reads_each_chunk_once_and_keeps_the_order(tmp_path):
    """Rows in any order give the same files as one at a time (rows are read a chunk of rows at a time)."""
    data = _btf_store(tmp_path / "b.zarr", n_lv=7)
    group = zarr.open_group(str(tmp_path / "b.zarr"), mode="r+")
    del group["btf"]
    group.create_array("btf", data=data, chunks=(3, 6, 7, 3))
    files = export_exr(tmp_path / "b.zarr", tmp_path / "exr", [6, 0, 4, 3, 1])
    assert [f.name[:7] for f in files] == ["lv00006", "lv00000", "lv00004", "lv00003", "lv00001"]
    for f, row in zip(files, (6, 0, 4, 3, 1)):
        with OpenEXR.File(str(f)) as exr:
            np.testing.assert_array_equal(exr.channels()["RGB"].pixels, data[row])
