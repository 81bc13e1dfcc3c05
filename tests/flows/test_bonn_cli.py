"""`btf export` and `btf import-btf` on the real command line (issue 18): a store written by the project goes
out as a Bonn DFMF/FMF file and comes back in, and the imported stores go through `btf resample`, `btf render`,
`btf build-db` and `btf reconstruct` like ingested ones; a truncated file is refused with its byte offset
before any cluster starts.

`btf export` (no cluster) and the refused import run as subprocesses (``python -m flows.cli``); the commands
that run on a cluster go through ``flows.cli.main`` in this process (``run_btf``: the session's Prefect server
and a threaded cluster, a second each instead of a server start).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr

from btf_env import btf_environ
from tasks.bonn.dfmf import read_factorised

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slow


def btf(*args, state: Path) -> subprocess.CompletedProcess:
    """``btf ARGS`` as a subprocess (no progress), in the repository root."""
    return subprocess.run([sys.executable, "-m", "flows.cli", "--no-progress", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300, env=btf_environ(state))


def test_export_import_and_the_rest_of_the_pipeline(tiny_btf, run_btf, tmp_path):
    source = zarr.open_group(str(tiny_btf), mode="r")
    B = source["btf"][...]                                 # 1 turntable x 4 cameras x 16 LEDs, 8 x 8 texels
    db, files = tmp_path / "db", tmp_path / "files"
    files.mkdir()
    # out: DFMF (half, YUV) and FMF (single) from an ingested store, each camera a view with its own lights;
    # the store holds DN/s, beyond half floats: --scale auto
    scales = {}
    for name, extra in (("a.btf", ["--format", "dfmf", "--colour-model", "1", "--scale", "auto"]),
                        ("b.fmf", ["--format", "fmf", "--precision", "single"])):
        done = btf("export", tiny_btf, *extra, "--out", files / name, state=tmp_path)
        assert done.returncode == 0, done.stderr
        summary = json.loads(done.stdout)
        assert summary["views"] == 4 and summary["lights"] == 16 and summary["bytes"] == (files / name).stat().st_size
        assert summary["relative_rms_error"] < (2e-3 if name == "a.btf" else 1e-6), summary
        scales[name] = summary["scale"]
    assert scales["a.btf"] < 1 and scales["b.fmf"] == 1
    again = btf("export", tiny_btf, "--format", "dfmf", "--out", files / "a.btf", state=tmp_path)
    assert again.returncode == 2 and "a.btf exists" in again.stderr and "Traceback" not in again.stderr
    # in: two imported materials of one class
    for name, material in (("a.btf", "leather-a"), ("b.fmf", "leather-b")):
        code, out, err = run_btf("import-btf", files / name, "--out", db / f"{material}.zarr", "--class", "leather",
                                 "--material-id", material)
        assert code == 0, err
    imported = zarr.open_group(str(db / "leather-a.zarr"), mode="r")
    assert imported.attrs["complete"] and imported.attrs["material"] == {"material_id": "leather-a", "class": "leather"}
    np.testing.assert_allclose(imported["btf"][...] / scales["a.btf"], B, rtol=0, atol=4e-3 * float(np.abs(B).max()))
    np.testing.assert_allclose(zarr.open_group(str(db / "leather-b.zarr"), mode="r")["btf"][...], B, rtol=1e-5,
                               atol=1e-6 * float(np.abs(B).max()))
    np.testing.assert_allclose(imported["light_dir"][...], source["light_dir"][...], atol=1e-6)
    # an imported store exports again with the file's own angles, bit for bit
    done = btf("export", db / "leather-a.zarr", "--format", "dfmf", "--colour-model", "1", "--scale", "auto",
               "--out", files / "a2.btf", state=tmp_path)
    assert done.returncode == 0, done.stderr
    first, second = read_factorised(files / "a.btf").header, read_factorised(files / "a2.btf").header
    assert np.array_equal(first.view_angles, second.view_angles) and first.xml == second.xml
    assert all(np.array_equal(x, y) for x, y in zip(first.light_angles, second.light_angles))
    # resample to a small sampling, render
    sampling = tmp_path / "sampling.json"
    light, view = source["light_dir"][...], source["view_dir"][...]
    sampling.write_text(json.dumps({"light_dirs": light[:16:5].tolist(), "view_dirs": view[::16][:2].tolist()}))
    code, out, err = run_btf("resample", db / "leather-a.zarr", "--sampling", sampling, "--out",
                             tmp_path / "resampled.zarr")
    assert code == 0, err
    assert zarr.open_group(str(tmp_path / "resampled.zarr"), mode="r")["btf"].shape == (2 * 4, 8, 8, 3)
    code, out, err = run_btf("render", db / "leather-a.zarr", "--size", "32", "--out", tmp_path / "sphere.png")
    assert code == 0 and (tmp_path / "sphere.png").stat().st_size > 0, err
    # a model database of the imported materials, and a reconstruction of one with it
    code, out, err = run_btf("build-db", db, "--out", tmp_path / "model", "--k-log-y", "8", "--k-chroma", "4",
                             "--k-merged", "16")
    assert code == 0, err
    model = zarr.open_group(str(tmp_path / "model" / "model.zarr"), mode="r")
    assert sorted(model.attrs["materials"]) == ["leather-a", "leather-b"]
    done = btf("export", db / "leather-a.zarr", "--format", "dfmf", "--basis", tmp_path / "model", "--class",
               "leather", "--components", "8", "--out", files / "basis.btf", state=tmp_path)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["components"] == [8, 8, 8]
    code, out, err = run_btf("reconstruct", db / "leather-a.zarr", "--model", tmp_path / "model", "--class",
                             "leather", "--out", tmp_path / "rec.zarr")
    assert code == 0, err
    rec = zarr.open_group(str(tmp_path / "rec.zarr"), mode="r")
    assert rec.attrs["complete"] and rec["btf"].shape == B.shape
    A = imported["btf"][...]                               # the scaled values of the file
    assert float(np.linalg.norm(rec["btf"][...] - A) / np.linalg.norm(A)) < 0.1


def test_a_truncated_file_is_refused_before_any_cluster_starts(tiny_btf, tmp_path):
    whole = tmp_path / "whole.btf"
    done = btf("export", tiny_btf, "--format", "dfmf", "--precision", "single", "--out", whole, state=tmp_path)
    assert done.returncode == 0, done.stderr
    data = whole.read_bytes()
    cut = tmp_path / "cut.btf"
    cut.write_bytes(data[:len(data) // 2])
    refused = btf("import-btf", cut, "--out", tmp_path / "cut.zarr", state=tmp_path)
    assert refused.returncode == 2, refused.stderr
    assert f"{cut}: byte " in refused.stderr and "Traceback" not in refused.stderr, refused.stderr
    assert "Dask cluster" not in refused.stderr and "Prefect API" not in refused.stderr   # nothing started
    assert not (tmp_path / "cut.zarr").exists() and not (tmp_path / "cut.partial.zarr").exists()
    inside = btf("export", tiny_btf, "--format", "bdi", "--out", tiny_btf / "x.bdi", state=tmp_path)
    assert inside.returncode == 2 and "is inside the input STORE" in inside.stderr, inside.stderr
    assert not (tiny_btf / "x.bdi").exists()


def test_help_texts_explain_the_formats(tmp_path):
    for command, words in (("export", ["dfmf", "fmf", "bdi", "--precision", "--colour-model", "cosine"]),
                           ("import-btf", ["DFMF", "FMF", "BDI", "PVF", "--class", "byte offset"])):
        done = btf(command, "--help", state=tmp_path)
        assert done.returncode == 0 and all(w in done.stdout for w in words), (command, done.stdout)
