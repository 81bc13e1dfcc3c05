"""`btf resample` end to end through `flows.cli.main`: a tiny ingested capture onto UBO2014,
under real Prefect and a real LocalCluster; bad input exits 1 with the reason."""

from __future__ import annotations

import json

import numpy as np
import pytest
import zarr

from flows.cli import main


def test_help_says_what_is_written(capsys):
    with pytest.raises(SystemExit) as info:
        main(["resample", "--help"])
    assert info.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for words in ("UBO2014 151 x 151", "outside_hull", "report.json", "never modified", "resumes",
                  "--overwrite", "--sampling"):
        assert words in text, words


def test_cli_resamples_onto_ubo2014_and_names_bad_input(tiny_btf, tmp_path, runtime_session, monkeypatch, capsys):
    monkeypatch.setenv("PREFECT_API_URL", runtime_session[1])      # the session's server, not a new one
    out = tmp_path / "leather-ubo.zarr"
    assert main(["--no-progress", "resample", str(tiny_btf), "--out", str(out)]) == 0, capsys.readouterr().err
    summary = json.loads(capsys.readouterr().out)
    report = json.loads((tmp_path / "leather-ubo.report.json").read_text())
    assert report["rows"] == summary["rows"] == 151 * 151 and report["sampling"] == "ubo2014"
    group = zarr.open_group(str(out), mode="r", zarr_format=3)
    assert group.attrs["complete"] and group["written"][...].all()
    btf = group["btf"][...]
    assert btf.shape == (22801, 8, 8, 3) and np.isfinite(btf).all() and btf.min() >= 0 and btf.max() > 0
    assert report["outside_hull_rows"] == int(group["outside_hull"][...].sum()) > 0
    # its textures export like an ingested store's, named by (view, light)
    assert main(["export-exr", str(out), "--out", str(tmp_path / "exr"), "--lv", "0,22800"]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in (tmp_path / "exr").iterdir()) == ["lv00000_v0_l0.exr", "lv22800_v150_l150.exr"]
    # the same run again: nothing to do
    assert main(["--no-progress", "resample", str(tiny_btf), "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["stages"]["resample"]["views_processed"] == 0

    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"light_dirs": [[0, 0, 1]], "view_dirs": [[0, 0, 1], [0.5, 0, -0.1]]}))
    assert main(["resample", str(tiny_btf), "--out", str(tmp_path / "x.zarr"), "--sampling", str(bad)]) == 1
    err = capsys.readouterr().err
    assert "bad.json: 1 problem(s)" in err and "view_dirs[1] = [0.5, 0, -0.1] points at or below the horizon" in err
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"light_dirs": [[0, 0, 1]], "view_dirs": [[0, 0, 1]]}))
    assert main(["resample", str(tiny_btf), "--out", str(out), "--sampling", str(good)]) == 1
    assert "choose another --out or pass --overwrite" in capsys.readouterr().err
    assert zarr.open_group(str(out), mode="r", zarr_format=3)["btf"].shape[0] == 22801      # left alone
