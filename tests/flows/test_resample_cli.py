"""`btf resample` end to end through `flows.cli.main`: a tiny ingested capture onto UBO2014,
under real Prefect and a real LocalCluster; bad input exits 1 with the reason."""

from __future__ import annotations

import json
import shutil

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
    share = report["outside_hull_rows"] / report["rows"]
    assert (share > 0.1) == bool(report["warnings"]), (share, report["warnings"])
    assert all(f"{share:.0%} of the resampled rows" in w for w in report["warnings"])
    # its textures export like an ingested store's, named by (view, light)
    assert main(["export-exr", str(out), "--out", str(tmp_path / "exr"), "--lv", "0,22800"]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in (tmp_path / "exr").iterdir()) == ["lv00000_v0_l0.exr", "lv22800_v150_l150.exr"]
    # the same run again: nothing to do
    assert main(["--no-progress", "resample", str(tiny_btf), "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["stages"]["resample"]["views_processed"] == 0

    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"light_dirs": [[0, 0, 1]], "view_dirs": [[0, 0, 1], [0.5, 0, -0.1]]}))
    assert main(["resample", str(tiny_btf), "--out", str(tmp_path / "x.zarr"), "--sampling", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.json: 1 problem(s)" in err and "view_dirs[1] = [0.5, 0, -0.1] points at or below the horizon" in err
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"light_dirs": [[0, 0, 1]], "view_dirs": [[0, 0, 1]]}))
    assert main(["resample", str(tiny_btf), "--out", str(out), "--sampling", str(good)]) == 2
    assert "choose another --out or pass --overwrite" in capsys.readouterr().err
    assert zarr.open_group(str(out), mode="r", zarr_format=3)["btf"].shape[0] == 22801      # left alone


def _files(store, report):
    """The bytes of the report and of every file of the store, by path: equal dicts are bit-identical."""
    return {path: path.read_bytes() for path in [report, *sorted(store.rglob("*"))] if path.is_file()}


@pytest.mark.parametrize("rerun", [["--overwrite"], []], ids=["rerun with --overwrite", "rerun without"])
def test_a_failed_staged_overwrite_keeps_store_and_report_and_the_rerun_swaps_them(rerun, tiny_btf, tmp_path,
                                                                                    run_btf):
    """`btf resample --overwrite` from a source with a NaN in one view fails part-way (exit 1): the finished
    store and its report stay bit for bit; once the source is fixed, the rerun, with or without --overwrite,
    resumes ``r.partial.zarr``, swaps it in and only then writes the report."""
    src = tmp_path / "src.zarr"
    shutil.copytree(tiny_btf, src)
    group = zarr.open_group(str(src), mode="r+", zarr_format=3)
    own = tmp_path / "own.json"          # the source's own directions: target view v reads source view v only
    own.write_text(json.dumps({"light_dirs": group["light_dir"][:16].tolist(),
                               "view_dirs": group["view_dir"][::16].tolist()}))
    coarse = tmp_path / "coarse.json"
    coarse.write_text(json.dumps({"light_dirs": group["light_dir"][:5].tolist(),
                                  "view_dirs": group["view_dir"][::32].tolist()}))
    out, report = tmp_path / "out" / "r.zarr", tmp_path / "out" / "r.report.json"
    out.parent.mkdir()
    assert run_btf("resample", src, "--out", out, "--sampling", coarse)[0] == 0
    before = _files(out, report)

    good = group["btf"][48:64]
    bad = good.copy()
    bad[:, 0] = np.nan                                              # view 3, texel row 0
    group["btf"][48:64] = bad
    code, _, err = run_btf("resample", src, "--out", out, "--sampling", own, "--overwrite")
    assert code == 2 and f"{src}: btf[48, 0, 0, 0] = nan" in err, err
    assert _files(out, report) == before
    staged = zarr.open_group(str(tmp_path / "out" / "r.partial.zarr"), mode="r", zarr_format=3)
    assert not staged.attrs["complete"] and staged["written"][3] == 0
    done = int(staged["written"][...].sum())

    group["btf"][48:64] = good                                      # the source is written again
    code, printed, err = run_btf("resample", src, "--out", out, "--sampling", own, *rerun)
    assert code == 0, err
    stage = json.loads(printed)["stages"]["resample"]
    assert stage["staged"] and (stage["views_skipped"], stage["views_processed"]) == (done, 4 - done), stage
    assert sorted(p.name for p in out.parent.iterdir()) == ["r.report.json", "r.zarr"]
    assert json.loads(report.read_text())["rows"] == 64 and json.loads(report.read_text())["sampling"] == "own.json"
    np.testing.assert_allclose(zarr.open_group(str(out), mode="r")["btf"][...], group["btf"][...], rtol=1e-6)


def test_outside_hull_warning_on_both_sides_of_its_threshold():
    from flows.resample import outside_hull_warnings

    assert outside_hull_warnings({"outside_hull_rows": 10, "rows": 100}) == []
    (warning,) = outside_hull_warnings({"outside_hull_rows": 68, "rows": 100})
    assert warning.startswith("68% of the resampled rows (68 of 100) lie outside the hull")
