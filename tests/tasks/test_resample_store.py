"""BTF store -> resampled BTF store on a real LocalCluster: chunked equals in-memory, identity,
smooth functions, resumption and refusals, staged overwrite, bad sampling files."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import zarr

from btfcore.capture.resample import (
    lv_outside_hull,
    lv_product,
    parabolic_map,
    resample,
    resample_weights,
    ubo2014_directions,
)
from btfcore.dome import get_device
import tasks.resample
from tasks.resample import load_sampling, resample_store
from tasks.staging import staging_path, trash_path


def _synthetic_store(path, light, view, data, rows_per_view, complete=True):
    """A btf-texture store with given directions and data (what `btf ingest` writes, minus the capture)."""
    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    group.create_array("btf", data=data.astype(np.float32), chunks=(rows_per_view,) + data.shape[1:])
    group.create_array("light_dir", data=light)
    group.create_array("view_dir", data=view)
    group.attrs.put({"schema": "btf-texture", "schema_version": "1.0", "units": "test",
                     "ingest_hash": f"synthetic-{path.name}", "complete": complete})
    return path


def _bilinear(light, view):
    """a + b.p(l) + c.p(v) + p(l)^T D p(v): exact under barycentric weights inside the hulls."""
    pl, pv = parabolic_map(light), parabolic_map(view)
    return 1.0 + pl @ [0.3, -0.2] + pv @ [-0.1, 0.25] + np.einsum("ni,ij,nj->n", pl, [[0.2, 0.1], [-0.3, 0.15]], pv)


def _brdf(light, view):
    """cos-weighted Lambert + a broad Phong lobe (tests/btfcore/test_resample.py)."""
    r = light * np.array([-1.0, -1.0, 1.0])
    return light[:, 2] * (0.5 / np.pi + 0.3 * np.clip(np.einsum("ij,ij->i", r, view), 0.0, None) ** 4)


@pytest.fixture(scope="module")
def turntable(tmp_path_factory):
    """The tiny dome's 3 turntable positions (per-view light sets, the zenith camera at 3 angles):
    a bilinear and a BRDF-like function of (light, view) times a per-texel albedo."""
    L, V, _ = get_device("tiny").lv_directions()
    albedo = np.random.default_rng(3).uniform(0.2, 1.0, (4, 4, 3))
    root = tmp_path_factory.mktemp("resample-synthetic")
    stores = {}
    for name, f in (("bilinear", _bilinear), ("brdf", _brdf)):
        data = f(L, V)[:, None, None, None] * albedo
        stores[name] = _synthetic_store(root / f"{name}.zarr", L, V, data, rows_per_view=16)
    return L, V, albedo, stores


def _sampling_file(path, light, view):
    plain = [d.tolist() if isinstance(d, np.ndarray) else d for d in (light, view)]
    path.write_text(json.dumps({"light_dirs": plain[0], "view_dirs": plain[1]}))
    return path


def _read(path):
    return zarr.open_group(str(path), mode="r", zarr_format=3)


# --------------------------------------------------------------------------- results


@pytest.mark.parametrize("source", ["ingested", "turntable"])
def test_chunked_equals_in_memory_on_ubo2014(source, request, tmp_path, dask_client):
    src = request.getfixturevalue("tiny_btf") if source == "ingested" else \
        request.getfixturevalue("turntable")[3]["brdf"]
    before = _read(src)["btf"][...]
    out = tmp_path / "ubo.zarr"
    result = resample_store(src, out, dask_client)
    U = ubo2014_directions()
    dl, dv = lv_product(U, U)
    g, s = _read(out), _read(src)
    L, V = s["light_dir"][...], s["view_dir"][...]
    W = resample_weights(L, V, dl, dv)
    expected = resample(before, W)
    got = g["btf"][...]
    assert got.shape == (151 * 151,) + before.shape[1:] and got.dtype == np.float32
    assert g["btf"].chunks == (151,) + before.shape[1:]
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6 * float(np.abs(expected).max()))
    # rows, directions, index, flags, markers and attributes
    np.testing.assert_array_equal(g["light_dir"][...], dl)
    np.testing.assert_array_equal(g["view_dir"][...], dv)
    np.testing.assert_array_equal(g["target_light_dirs"][...], U)
    np.testing.assert_array_equal(g["lv_index"][1000], [1000 // 151, 1000 % 151])
    vo, lo = lv_outside_hull(L, V, dl, dv)
    np.testing.assert_array_equal(g["outside_hull"][...], vo | lo)
    assert g["written"][...].all()
    attrs = dict(g.attrs)
    assert attrs["complete"] and attrs["schema"] == "btf-texture" and attrs["sampling"] == "ubo2014"
    assert attrs["lv_order"] == ["view", "light"]
    assert attrs["resampled_from"] == {"path": str(src.resolve()), "ingest_hash": s.attrs["ingest_hash"]}
    assert result["rows"] == 22801 and result["outside_hull_rows"] == int((vo | lo).sum()) > 0
    assert result["views_processed"] == 151 and result["tasks"] > 1
    np.testing.assert_array_equal(_read(src)["btf"][...], before)          # the input is never modified
    assert _read(src).attrs["complete"]


@pytest.mark.parametrize("capture", ["tiny_btf", "tiny_btf_nonideal"])     # the ideal and a non-ideal dome
def test_identity_on_the_source_sampling(capture, request, tmp_path, dask_client):
    tiny_btf = request.getfixturevalue(capture)
    s = _read(tiny_btf)
    B, L, V = s["btf"][...], s["light_dir"][...], s["view_dir"][...]
    # one turntable position: the rows are every LED with every camera, view-major as the target
    sampling = _sampling_file(tmp_path / "own.json", L[:16], V[::16])
    result = resample_store(tiny_btf, tmp_path / "own.zarr", dask_client, sampling=sampling)
    g = _read(tmp_path / "own.zarr")
    assert result["outside_hull_rows"] == 0 and g.attrs["sampling"] == "own.json"
    np.testing.assert_allclose(g["btf"][...], B, rtol=1e-6, atol=0)
    np.testing.assert_allclose(g["light_dir"][...], L, atol=1e-12)


def test_smooth_functions_are_reproduced_inside_the_hull(turntable, tmp_path, dask_client):
    L, V, albedo, stores = turntable
    U = ubo2014_directions()
    dl, dv = lv_product(U, U)
    resample_store(stores["bilinear"], tmp_path / "bilinear.zarr", dask_client)
    g = _read(tmp_path / "bilinear.zarr")
    inside = ~g["outside_hull"][...]
    assert 0.1 < inside.mean() < 0.9                    # tiny covers the hemisphere coarsely
    truth = _bilinear(dl, dv)[:, None, None, None] * albedo
    got = g["btf"][...]
    # exact but for float32 storage wherever no weight extrapolates
    np.testing.assert_allclose(got[inside], truth[inside], rtol=2e-6)
    assert np.abs(got[~inside] - truth[~inside]).max() > 1e-3             # the flags mean something
    # a BRDF-like function: the accuracy of the tiny dome in tests/btfcore/test_resample.py (0.28)
    resample_store(stores["brdf"], tmp_path / "brdf.zarr", dask_client)
    got = _read(tmp_path / "brdf.zarr")["btf"][...]
    truth = _brdf(dl, dv)[:, None, None, None] * albedo
    assert np.linalg.norm(got - truth) / np.linalg.norm(truth) < 0.35


# --------------------------------------------------------------------------- resumption and refusals


def test_resumes_bit_identically_and_refuses_other_runs(tiny_btf, tmp_path, dask_client):
    U = ubo2014_directions()
    coarse = _sampling_file(tmp_path / "coarse.json", U[:19], U[:19])     # rings 0, 11, 23.5 deg
    out = tmp_path / "r.zarr"
    first = resample_store(tiny_btf, out, dask_client, sampling=coarse)
    assert first["views_processed"] == 19
    done = _read(out)["btf"][...]
    # a killed run: two views' data lost and their markers down
    rw = zarr.open_group(str(out), mode="r+", zarr_format=3)
    for v in (3, 11):
        rw["btf"][v * 19:(v + 1) * 19] = 0.0
        rw["written"][v] = 0
    rw.attrs["complete"] = False
    again = resample_store(tiny_btf, out, dask_client, sampling=coarse)
    assert again["views_processed"] == 2 and again["views_skipped"] == 17
    np.testing.assert_array_equal(_read(out)["btf"][...], done)
    assert resample_store(tiny_btf, out, dask_client, sampling=coarse)["views_processed"] == 0
    # another sampling at the same --out: refused, then replaced with overwrite
    with pytest.raises(FileExistsError, match=r"r\.zarr holds a complete resampled BTF store of another "
                                              r"source or sampling.*choose another --out or pass --overwrite"):
        resample_store(tiny_btf, out, dask_client)
    other = _sampling_file(tmp_path / "other.json", U[:7], U[:1])
    assert resample_store(tiny_btf, out, dask_client, sampling=other, overwrite=True)["rows"] == 7
    assert _read(out)["btf"].shape[0] == 7
    # never the input itself
    with pytest.raises(ValueError, match="is the source store"):
        resample_store(tiny_btf, tiny_btf, dask_client, sampling=coarse, overwrite=True)


class Killed(BaseException):
    """What a SIGKILL would do to the run at that point: stop it, nothing caught."""


def _files(root):
    """Every file under ``root`` by relative path with its bytes: equal dicts are bit-identical stores."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture()
def killed_overwrite(tiny_btf, tmp_path, dask_client, monkeypatch):
    """``r.zarr``, a finished resampling onto 19 x 19 UBO directions, its files, and an ``overwrite`` onto
    another sampling (5 views x 7 lights) killed after its views were written, before the swap."""
    U = ubo2014_directions()
    coarse = _sampling_file(tmp_path / "coarse.json", U[:19], U[:19])
    other = _sampling_file(tmp_path / "other.json", U[:7], U[:5])
    out = tmp_path / "out" / "r.zarr"
    out.parent.mkdir()
    resample_store(tiny_btf, out, dask_client, sampling=coarse)
    before = _files(out)

    def kill(*args):
        raise Killed()

    with monkeypatch.context() as patch:
        patch.setattr(tasks.resample, "commit_staged", kill)
        with pytest.raises(Killed):
            resample_store(tiny_btf, out, dask_client, sampling=other, overwrite=True)
    assert _files(out) == before and _read(staging_path(out)).attrs["complete"]
    return out, before, coarse, other


@pytest.mark.parametrize("rerun", [{"overwrite": True}, {}], ids=["rerun with overwrite", "rerun without"])
def test_a_killed_staged_overwrite_keeps_the_output_and_the_rerun_resumes_and_swaps(
        rerun, killed_overwrite, tiny_btf, tmp_path, dask_client):
    """overwrite builds ``r.partial.zarr`` beside ``r.zarr``; killed part-way (two views' data and markers
    lost, as a kill leaves them) ``r.zarr`` is bit for bit as it was; the rerun resumes the staged store, with
    or without overwrite, and only then renames it over ``r.zarr``, leaving no staging or replaced store."""
    out, before, _, other = killed_overwrite
    staged = zarr.open_group(str(staging_path(out)), mode="r+", zarr_format=3)
    for v in (1, 3):
        staged["btf"][v * 7:(v + 1) * 7] = 0.0
        staged["written"][v] = 0
    staged.attrs["complete"] = False
    assert _files(out) == before

    again = resample_store(tiny_btf, out, dask_client, sampling=other, **rerun)
    assert again["staged"] and (again["views_processed"], again["views_skipped"]) == (2, 3), again
    assert sorted(p.name for p in out.parent.iterdir()) == ["r.zarr"]
    clean = resample_store(tiny_btf, tmp_path / "clean.zarr", dask_client, sampling=other)
    assert not clean["staged"]
    np.testing.assert_array_equal(_read(out)["btf"][...], _read(tmp_path / "clean.zarr")["btf"][...])
    assert _read(out).attrs["complete"] and _read(out).attrs["sampling"] == "other.json"


def test_a_resample_commit_killed_between_its_renames_is_finished_or_undone(killed_overwrite, tiny_btf,
                                                                             dask_client):
    """A kill after ``r.zarr`` was renamed to ``r.replaced.zarr``: the next run into ``r.zarr`` puts the
    complete staged store in place, or the old store back when the staged one is unfinished."""
    out, before, coarse, other = killed_overwrite
    staged = zarr.open_group(str(staging_path(out)), mode="r+", zarr_format=3)
    staged.attrs["complete"] = False
    out.rename(trash_path(out))
    kept = resample_store(tiny_btf, out, dask_client, sampling=coarse)      # the old one is back, untouched
    assert not kept["staged"] and kept["views_processed"] == 0 and _files(out) == before
    assert sorted(p.name for p in out.parent.iterdir()) == ["r.partial.zarr", "r.zarr"]

    staged.attrs["complete"] = True
    out.rename(trash_path(out))
    swapped = resample_store(tiny_btf, out, dask_client, sampling=other)
    assert not swapped["staged"] and swapped["views_processed"] == 0
    assert sorted(p.name for p in out.parent.iterdir()) == ["r.zarr"] and _read(out)["btf"].shape[0] == 35
    # a source where a replacement of --out would be staged is never written
    source = out.rename(out.with_name("s.partial.zarr"))
    with pytest.raises(ValueError, match=r"--out .*s\.zarr would stage its replacement in the source s\.partial"):
        resample_store(source, out.with_name("s.zarr"), dask_client, sampling=coarse, overwrite=True)


def test_refuses_bad_sources(turntable, tmp_path, dask_client):
    L, V, albedo, _ = turntable
    unfinished = _synthetic_store(tmp_path / "unfinished.zarr", L, V, np.ones((len(L), 2, 2, 3)), 16,
                                  complete=False)
    with pytest.raises(ValueError, match=r"unfinished\.zarr is an unfinished BTF store.*finish `btf ingest`"):
        resample_store(unfinished, tmp_path / "o.zarr", dask_client)
    assert not (tmp_path / "o.zarr").exists()
    with pytest.raises(FileNotFoundError, match="ghost.zarr does not exist"):
        resample_store(tmp_path / "ghost.zarr", tmp_path / "o.zarr", dask_client)
    zarr.open_group(str(tmp_path / "other.zarr"), mode="w", zarr_format=3).attrs["schema"] = "btf-capture"
    with pytest.raises(ValueError, match="not a BTF store"):
        resample_store(tmp_path / "other.zarr", tmp_path / "o.zarr", dask_client)
    data = np.ones((len(L), 2, 2, 3))
    data[1, 1, 0, 2] = np.nan                   # (turntable 0, zenith camera, LED 1): used below
    nan = _synthetic_store(tmp_path / "nan.zarr", L, V, data, 16)
    one_view = _sampling_file(tmp_path / "s.json", L[:3], V[:1])
    with pytest.raises(ValueError, match=r"nan\.zarr: btf\[1, 1, 0, 2\] = nan"):
        resample_store(nan, tmp_path / "o.zarr", dask_client, sampling=one_view)
    # an ingested store at --out is not taken for a resampling
    ok = _synthetic_store(tmp_path / "ok.zarr", L, V, np.ones((len(L), 2, 2, 3)), 16)
    with pytest.raises(FileExistsError, match=r"nan\.zarr holds a Zarr store that is not a resampled BTF store"):
        resample_store(ok, nan, dask_client, sampling=one_view)


# --------------------------------------------------------------------------- sampling files


def test_sampling_files_are_normalised(tmp_path):
    ubo = load_sampling("ubo2014")
    assert (ubo.n_l, ubo.n_v, ubo.name) == (151, 151, "ubo2014")
    s = load_sampling(_sampling_file(tmp_path / "mine.json", [[0, 0, 2], [3, 0, 4]], [[0, 1e-3, 1e-3]]))
    assert s.name == "mine.json"
    np.testing.assert_allclose(s.light_dirs, [[0, 0, 1], [0.6, 0, 0.8]])
    np.testing.assert_allclose(s.view_dirs, [[0, np.sqrt(0.5), np.sqrt(0.5)]])
    light, view, index = s.rows()
    np.testing.assert_array_equal(index, [[0, 0], [0, 1]])
    np.testing.assert_allclose(light, s.light_dirs)


@pytest.mark.parametrize("light, view, problems", [
    ([[0, 0, 0], [0, 0, 1]], [[0, 0, 1]], [r"light_dirs\[0\] = \[0, 0, 0\] is the zero vector"]),
    ([[0, 0, 1]], [[0.1, 0, 1], [1, 0, -0.2], [1, 0, 0]],
     [r"view_dirs\[1\] = \[1, 0, -0.2\] points at or below the horizon", r"view_dirs\[2\] .* below the horizon"]),
    ([[0, 0, 1], [0, "a", 1], [0, 0]], [[0, 0, 1]],
     [r"light_dirs\[1\] = \[0, \"a\", 1\] is not a list of three numbers", r"light_dirs\[2\] = \[0, 0\]"]),
    ([[0, 0, 1], [0, 0, 2]], [[0, 0, 1]], [r"light_dirs\[1\] repeats light_dirs\[0\]"]),
    ([], [[0, 0, 1]], [r"light_dirs must be a non-empty list"]),
])
def test_bad_sampling_files_name_array_and_index(tmp_path, light, view, problems):
    path = _sampling_file(tmp_path / "bad.json", light, view)
    with pytest.raises(ValueError) as info:
        load_sampling(path)
    message = str(info.value)
    assert message.startswith(f"{path}: {len(problems)} problem(s)"), message
    for pattern in problems:
        assert re.search(pattern, message), (pattern, message)
    assert "ubo2014" in message                                            # says what would do


def test_nan_missing_keys_and_broken_json(tmp_path):
    path = tmp_path / "nan.json"
    path.write_text('{"light_dirs": [[0, 0, 1], [NaN, 0, 1], [0, Infinity, 1]]}')
    with pytest.raises(ValueError) as info:
        load_sampling(path)
    assert "light_dirs[1] = [nan, 0, 1] is not finite" in str(info.value)
    assert "light_dirs[2] = [0, inf, 1] is not finite" in str(info.value)
    assert "view_dirs is missing" in str(info.value)
    path.write_text('{"light_dirs": [[0, 0, 1]')
    with pytest.raises(ValueError, match="nan.json: not a readable JSON sampling file"):
        load_sampling(path)
    with pytest.raises(FileNotFoundError, match="ghost.json does not exist"):
        load_sampling(tmp_path / "ghost.json")
