"""``btf export`` (tasks.bonn.export_btf): small seeded btf-texture stores written as DFMF, FMF and BDI files,
read back with the project's readers (tasks.bonn.dfmf, tasks.bonn.bdi) and decoded: the values equal the
store's within the file's precision, the header holds the store's directions, and the refusals name what is
wrong before anything is written."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.bonn import decode_colour, decode_textures, encode_colour
from tasks.bonn.bdi import read_bdi
from tasks.bonn.dfmf import read_factorised
from tasks.bonn.export_btf import check_export, export_store
from tasks.stores.btf import LV_ORDER, RESAMPLED_LV_ORDER, create_btf_store

N_V, N_L, H, W = 3, 5, 6, 7          # non-square textures: a swapped x/y fails
HALF_EPS = 2.0**-11                  # unit roundoff of a half float


def _dir(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


def _values(light: np.ndarray, view: np.ndarray, seed: int) -> np.ndarray:
    """Positive radiance (n_lv, H, W, 3): a smooth function of the directions times a per-texel albedo, plus
    seeded texture noise, so that the matrix has full rank."""
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.2, 1.0, (H, W, 3))
    lobe = light[:, 2] * (0.3 + 0.7 * np.clip(np.einsum("ij,ij->i", light * [-1, -1, 1], view), 0, None) ** 8)
    data = lobe[:, None, None, None] * albedo + 0.05 * rng.uniform(0, 1, (len(light), H, W, 3))
    return data.astype(np.float32)


def make_store(path, *, kind: str = "resampled", seed: int = 0, scale: float = 1.0, shuffle: bool = False,
               view_dir_change: bool = False, duplicate: bool = False):
    """A finished btf-texture store.

    ``kind="resampled"``: rows (view, light), one light set for every view; ``"ingested"``: rows (turntable,
    camera, light) with 2 turntable positions x 2 cameras, the lights rotating with the turntable.
    """
    rng = np.random.default_rng(seed + 100)
    if kind == "resampled":
        views = _dir(np.radians([0.0, 30.0, 60.0]), np.radians([0.0, 45.0, 200.0]))
        lights = _dir(rng.uniform(0, 1.2, N_L), rng.uniform(0, 2 * np.pi, N_L))
        light = np.tile(lights, (N_V, 1))
        view = np.repeat(views, N_L, axis=0)
        index = np.indices((N_V, N_L)).reshape(2, -1).T
        attrs = {"units": "test", "lv_order": RESAMPLED_LV_ORDER, "resample_hash": f"r{seed}",
                 "resampled_from": {"path": "x"}, "views_lights": [N_V, N_L]}
        written = (N_V,)
    else:
        n_t, n_c = 2, 2
        cams = _dir(np.radians([10.0, 50.0]), np.radians([0.0, 90.0]))
        leds = _dir(rng.uniform(0, 1.2, N_L), rng.uniform(0, 2 * np.pi, N_L))
        index = np.indices((n_t, n_c, N_L)).reshape(3, -1).T
        rot = [np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]) for a in (0.0, 0.7)]
        light = np.array([rot[t] @ leds[l] for t, c, l in index])
        view = np.array([rot[t] @ cams[c] for t, c, l in index])
        attrs = {"units": "test", "lv_order": LV_ORDER, "ingest_hash": f"i{seed}",
                 "turntable_cameras_leds": [n_t, n_c, N_L], "sample_size_m": 0.01}
        written = (n_t, n_c)
    data = _values(light, view, seed) * scale
    if view_dir_change:
        view = view.copy()
        view[1] = _dir(np.radians(31.0), np.radians(2.0))
    if shuffle:
        perm = rng.permutation(len(light))
        light, view, index, data = light[perm], view[perm], index[perm], data[perm]
    if duplicate:                                   # the last row claims the (view, light) of the one before
        index = index.copy()
        index[-1] = index[-2]
    store = create_btf_store(path, attrs, light_dir=light, view_dir=view, lv_index=index.astype(np.int32),
                             texture_shape=(H, W), rows_per_chunk=N_L, band=H, written_shape=written)
    store.btf[...] = data
    store.group["written"][...] = 1
    store.mark_complete()
    return store


def file_rows(store):
    """The store's (light, view, textures) in file row order l + n_l * v (what the file must hold)."""
    index = store.lv_index
    if store.attrs["lv_order"] == LV_ORDER:
        index = np.stack([index[:, 0] * 2 + index[:, 1], index[:, 2]], axis=1)
    order = np.lexsort((index[:, 1], index[:, 0]))
    return store.light_dir[order], store.view_dir[order], store.btf[...][order]


def decoded(path):
    """Linear RGB (n_lv, H, W, 3) of a written DFMF/FMF file, and the file."""
    fact = read_factorised(path)
    channels = decode_textures(fact.U, fact.SxV, slice(None))
    rgb = decode_colour(channels, fact.colour_model, fact.colour_mean, fact.colour_matrix)
    return rgb.reshape(-1, fact.header.height, fact.header.width, 3), fact


def within_precision(got: np.ndarray, want: np.ndarray, eps: float, factor: float = 8.0) -> None:
    """|got - want| <= factor * eps * (the ABRDF's norm over rows, per texel and channel): the error bound of a
    product of rounded orthonormal U and S V^T factors."""
    norm = np.sqrt((want.astype(np.float64) ** 2).sum(axis=0, keepdims=True))
    err = np.abs(got.astype(np.float64) - want)
    assert (err <= factor * eps * norm.max(axis=-1, keepdims=True)).all(), float((err / norm.max()).max())


@pytest.fixture()
def resampled(tmp_path):
    return make_store(tmp_path / "resampled.zarr")


# --------------------------------------------------------------------------- values read back


@pytest.mark.parametrize("precision, eps", [("half", HALF_EPS), ("single", 2.0**-24)])
def test_dfmf_reads_back_equal_to_the_store(resampled, tmp_path, precision, eps):
    out = tmp_path / "m.btf"
    summary = export_store(resampled.path, out, format="dfmf", precision=precision)
    rgb, fact = decoded(out)
    light, view, want = file_rows(resampled)
    assert fact.format == "dfmf" and fact.header.signature == "!DFMF08FCR" and fact.colour_model == 0
    assert fact.scalar_size == {"half": 2, "single": 4}[precision]
    assert [u.shape for u in fact.U] == [(N_V * N_L, N_V * N_L)] * 3          # all components: min(15, 42)
    assert [s.shape for s in fact.SxV] == [(H * W, N_V * N_L)] * 3
    within_precision(rgb, want, eps)
    assert summary["bytes"] == out.stat().st_size and summary["components"] == [N_V * N_L] * 3
    assert summary["max_abs_error"] == pytest.approx(float(np.abs(rgb - want).max()), rel=1e-3, abs=1e-7)
    if precision == "half":                     # rounding to half is visible, and bounded
        assert 1e-5 < summary["max_abs_error"] < 2e-3
    assert not list(tmp_path.glob(".*.tmp.*"))


def test_the_header_holds_the_store_directions_and_the_cosine_flag(resampled, tmp_path):
    export_store(resampled.path, tmp_path / "m.btf", format="dfmf")
    header = read_factorised(tmp_path / "m.btf").header
    light, view, _ = file_rows(resampled)
    assert (header.n_v, header.n_l, header.width, header.height) == (N_V, N_L, W, H)
    np.testing.assert_allclose(header.light_dir(), light, atol=2e-6)
    np.testing.assert_allclose(header.view_dir(), view, atol=2e-6)
    assert header.cosine_flag is True and header.channel_names == ("R", "G", "B") and header.version == 4
    assert header.rotations is not None and header.rotations.shape == (0, 3, 3)
    assert "btf_pipeline_export" in header.xml and "resampled" in header.xml


@pytest.mark.parametrize("model", [1, 11, 12])
def test_dfmf_honours_the_colour_model(resampled, tmp_path, model):
    out = tmp_path / f"m{model}.btf"
    export_store(resampled.path, out, format="dfmf", colour_model=model)
    rgb, fact = decoded(out)
    _, _, want = file_rows(resampled)
    assert fact.colour_model == model
    stored = decode_textures(fact.U, fact.SxV, slice(None)).reshape(want.shape)
    encoded, _, _ = encode_colour(want, model)
    within_precision(stored, encoded, HALF_EPS)                 # the file holds the model's channels, not RGB
    assert np.abs(stored - want).max() > 0.05
    # a log model's half-float error is relative: compare in the log domain, then the linear values loosely
    within_precision(rgb, want, HALF_EPS, factor=64.0)


def test_fmf_is_one_factorisation_of_all_channels(resampled, tmp_path):
    out = tmp_path / "m.fmf"
    summary = export_store(resampled.path, out, format="fmf")
    rgb, fact = decoded(out)
    _, _, want = file_rows(resampled)
    assert fact.format == "fmf" and fact.header.signature == "!FMF12FCER" and summary["components"] == [42]          # min(3 x 15, 6 x 7)
    assert len(fact.S) == 3 and fact.U[0].shape == (N_V * N_L, 42)
    within_precision(rgb, want, HALF_EPS)


@pytest.mark.parametrize("compression", ["raw", "bzip2", "sparse"])
def test_bdi_reads_back_as_half_floats_of_the_store(resampled, tmp_path, compression):
    out = tmp_path / "m.bdi"
    summary = export_store(resampled.path, out, format="bdi", compression=compression, lines_per_chunk=4)
    bdi = read_bdi(out)
    _, _, want = file_rows(resampled)
    assert bdi.header.signature == "!BDIF06R2!" and bdi.compression == {"raw": 0, "bzip2": 1, "sparse": 2}[compression]
    got = bdi.read_texture_rows(0, H)
    np.testing.assert_array_equal(got, want.astype(np.float16).astype(np.float32))
    assert summary["compression"] == compression and summary["bytes"] == out.stat().st_size
    assert summary["max_abs_error"] == pytest.approx(float(np.abs(got - want).max()), rel=1e-6)


def test_an_ingested_store_exports_each_view_with_its_own_lights(tmp_path):
    store = make_store(tmp_path / "ingested.zarr", kind="ingested", seed=3)
    export_store(store.path, tmp_path / "i.btf", format="dfmf")
    rgb, fact = decoded(tmp_path / "i.btf")
    light, view, want = file_rows(store)
    header = fact.header
    assert header.n_v == 4 and header.n_l == N_L
    assert not np.allclose(header.light_angles[0], header.light_angles[2])     # turntable 1 rotates the lights
    np.testing.assert_allclose(header.light_dir(), light, atol=2e-6)
    np.testing.assert_allclose(header.view_dir(), view, atol=2e-6)
    assert header.ppmm == pytest.approx(W / 10.0)                            # 7 texels over 10 mm
    within_precision(rgb, want, HALF_EPS)


def test_rows_in_another_order_are_written_in_file_order(tmp_path):
    plain = make_store(tmp_path / "plain.zarr", seed=5)
    shuffled = make_store(tmp_path / "shuffled.zarr", seed=5, shuffle=True)
    for store, name in ((plain, "a.bdi"), (shuffled, "b.bdi")):
        export_store(store.path, tmp_path / name, format="bdi")
    np.testing.assert_array_equal(read_bdi(tmp_path / "a.bdi").read_texture_rows(0, H),
                                  read_bdi(tmp_path / "b.bdi").read_texture_rows(0, H))


def test_fewer_components_give_a_smaller_file_and_a_larger_error(resampled, tmp_path):
    full = export_store(resampled.path, tmp_path / "full.btf", format="dfmf")
    few = export_store(resampled.path, tmp_path / "few.btf", format="dfmf", components=2)
    assert few["components"] == [2, 2, 2] and few["bytes"] < full["bytes"]
    assert few["relative_rms_error"] > 10 * full["relative_rms_error"]
    rgb, _ = decoded(tmp_path / "few.btf")
    _, _, want = file_rows(resampled)
    assert float(np.abs(rgb - want).max()) == pytest.approx(few["max_abs_error"], rel=1e-3)


# --------------------------------------------------------------------------- refusals


def test_an_existing_out_is_refused_unless_overwrite(resampled, tmp_path):
    out = tmp_path / "m.btf"
    out.write_bytes(b"keep me")
    with pytest.raises(FileExistsError, match=r"m\.btf exists; give another --out or --overwrite"):
        export_store(resampled.path, out, format="dfmf")
    assert out.read_bytes() == b"keep me"
    export_store(resampled.path, out, format="dfmf", overwrite=True)
    assert out.read_bytes()[:10] == b"!DFMF08FCR" and not list(tmp_path.glob(".*.tmp.*"))


@pytest.mark.parametrize("change, match", [
    (dict(view_dir_change=True), r"row 1 \(view 0, light 1\) has another view direction"),
    (dict(duplicate=True), r"15 rows are not a full grid of 3 views x 5 lights \(view 2, light 4 is missing\)"),
])
def test_a_store_that_is_not_views_by_lights_is_refused(tmp_path, change, match):
    store = make_store(tmp_path / "bad.zarr", **change)
    with pytest.raises(ValueError, match=match):
        export_store(store.path, tmp_path / "bad.btf", format="dfmf")
    assert not list(tmp_path.glob("bad.btf*"))


def test_views_with_different_light_counts_are_refused(tmp_path):
    store = make_store(tmp_path / "bad.zarr")
    index = store.lv_index
    index[N_L - 1] = [1, N_L]                        # view 0 loses a light, view 1 gains one
    store.group["lv_index"][...] = index
    with pytest.raises(ValueError, match=r"views have different numbers of lights \(view 1: 6, view 0: 4\)"):
        check_export(store.path, tmp_path / "bad.btf", format="dfmf")


def test_rows_without_a_views_by_lights_order_are_refused(tmp_path):
    store = make_store(tmp_path / "odd.zarr")
    store.group.attrs["lv_order"] = ["light"]
    with pytest.raises(ValueError, match=r"rows ordered \['light'\] .* are not views x lights"):
        check_export(store.path, tmp_path / "o.btf", format="bdi")


@pytest.mark.parametrize("kwargs, match", [
    (dict(format="pvf"), r"--format 'pvf': give one of dfmf, fmf, bdi"),
    (dict(format="dfmf", colour_model=7), r"colour model 7 is not supported \(--colour-model\)"),
    (dict(format="fmf", colour_model=1), r"FMF stores RGB \(colour model 0\) only"),
    (dict(format="bdi", precision="single"), r"BDI stores half floats only"),
    (dict(format="dfmf", components=16), r"--components 16: give 1 to 15"),
    (dict(format="dfmf", compression="bzip2"), r"only BDI files have chunk compression"),
    (dict(format="dfmf", max_bytes=1000), r"factorises in memory up to 0 MiB .* --format bdi"),
])
def test_bad_settings_are_refused_before_writing(resampled, tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        export_store(resampled.path, tmp_path / "x.btf", **kwargs)
    assert not list(tmp_path.glob("x.btf*"))


def test_values_beyond_half_floats_need_single_precision_or_a_scale(tmp_path):
    store = make_store(tmp_path / "bright.zarr", scale=1e5)             # DN/s of an uncalibrated ingest
    with pytest.raises(ValueError, match=r"beyond the largest half float .* --precision single, or --scale auto"):
        export_store(store.path, tmp_path / "b.btf", format="dfmf")
    with pytest.raises(ValueError, match=r"beyond the largest half float .* --scale auto .* --precision single"):
        export_store(store.path, tmp_path / "b.bdi", format="bdi")
    assert not list(tmp_path.glob("b.*"))
    summary = export_store(store.path, tmp_path / "b.btf", format="dfmf", precision="single")
    assert summary["relative_rms_error"] < 1e-6 and summary["scale"] == 1.0


@pytest.mark.parametrize("fmt, model", [("dfmf", 1), ("fmf", 0), ("bdi", 0)])
def test_scale_auto_fits_bright_values_into_half_floats_by_a_power_of_two(tmp_path, fmt, model):
    store = make_store(tmp_path / "bright.zarr", scale=1e5)
    _, _, want = file_rows(store)
    out = tmp_path / f"b.{fmt}"
    summary = export_store(store.path, out, format=fmt, colour_model=model, scale="auto")
    scale = summary["scale"]
    assert scale < 1 and np.log2(scale) == np.round(np.log2(scale))
    if fmt == "bdi":
        bdi = read_bdi(out)
        got, header = bdi.read_texture_rows(0, H), bdi.header
        assert np.abs(got).max() <= 2.0**14
        np.testing.assert_allclose(got / scale, want, rtol=HALF_EPS, atol=0)
    else:
        got, fact = decoded(out)
        header = fact.header
        assert max(float(np.abs(np.asarray(a, np.float64)).max()) for a in fact.S + fact.SxV) <= 2.0**14
        within_precision(got / scale, want, HALF_EPS)
    assert f'scale="{scale!r}"' in header.xml
    assert summary["relative_rms_error"] < 1e-3


def test_scale_auto_leaves_values_that_fit_alone_and_a_given_scale_is_applied(resampled, tmp_path):
    assert export_store(resampled.path, tmp_path / "a.bdi", format="bdi", scale="auto")["scale"] == 1.0
    summary = export_store(resampled.path, tmp_path / "b.bdi", format="bdi", scale=0.5)
    _, _, want = file_rows(resampled)
    np.testing.assert_array_equal(read_bdi(tmp_path / "b.bdi").read_texture_rows(0, H),
                                  (want * 0.5).astype(np.float16).astype(np.float32))
    assert summary["scale"] == 0.5 and 'scale="0.5"' in read_bdi(tmp_path / "b.bdi").header.xml
    with pytest.raises(ValueError, match=r"--scale 'x': give a positive number or auto"):
        export_store(resampled.path, tmp_path / "c.bdi", format="bdi", scale="x")


def test_a_log_colour_model_refuses_negative_radiance(tmp_path):
    store = make_store(tmp_path / "dark.zarr")
    data = store.btf[...]
    data[2, 1, 1] = -0.01                          # noise of a dark measured texel
    store.btf[...] = data
    with pytest.raises(ValueError, match=r"colour model 12 .* cannot encode"):
        export_store(store.path, tmp_path / "d.btf", format="dfmf", colour_model=12)
    assert not list(tmp_path.glob("d.btf*"))


@pytest.mark.parametrize("fmt, model", [("dfmf", 1), ("dfmf", 0), ("fmf", 0)])
def test_row_blocks_do_not_change_the_file(resampled, tmp_path, monkeypatch, fmt, model):
    """The colour encoding and the error summary run block of rows by block: one row per block writes the same
    bytes and reports the same errors as one block for all."""
    import tasks.bonn.export_btf as export_btf

    whole = export_store(resampled.path, tmp_path / "whole", format=fmt, colour_model=model, scale=0.5)
    monkeypatch.setattr(export_btf, "BLOCK_BYTES", 1)
    rows = export_store(resampled.path, tmp_path / "rows", format=fmt, colour_model=model, scale=0.5)
    assert (tmp_path / "whole").read_bytes() == (tmp_path / "rows").read_bytes()
    # the decoded check values differ only by float32 rounding of the GEMMs' blocking
    assert rows["max_abs_error"] == pytest.approx(whole["max_abs_error"], rel=1e-3) and whole["max_abs_error"] > 0
    assert rows["relative_rms_error"] == pytest.approx(whole["relative_rms_error"], rel=1e-3)


def _model(tmp_path, store, k: int):
    """A `btf build-db`-like model folder whose class ``leather`` has the store's own ALS-like basis: the
    leading ``k`` left singular vectors of its linear RGB matrix (rows in store order)."""
    from btfcore.model._lowrank import TruncatedSVD
    from tasks.model import Material, open_model_store, write_basis

    B = store.btf[...].reshape(store.n_lv, -1).astype(np.float64)
    U, s, _ = np.linalg.svd(B, full_matrices=False)
    material = Material("m", "leather", store.path, "k", store.n_lv, store.texture_shape, "rows")
    group = open_model_store(tmp_path / "model" / "model.zarr", [material])
    write_basis(group, "classes/leather/als", TruncatedSVD(U[:, :k], s[:k], "merge"), "test")
    return tmp_path / "model", U[:, :k]


@pytest.mark.parametrize("k", [15, 4])
def test_export_on_a_model_basis_projects_the_store(resampled, tmp_path, k):
    model, U = _model(tmp_path, resampled, k)
    summary = export_store(resampled.path, tmp_path / "b.btf", format="dfmf", basis=model, basis_class="leather")
    rgb, fact = decoded(tmp_path / "b.btf")
    _, _, want = file_rows(resampled)
    assert summary["components"] == [k] * 3 and all(np.array_equal(u, fact.U[0]) for u in fact.U)
    np.testing.assert_allclose(np.asarray(fact.U[0], np.float64), U, atol=HALF_EPS)     # the basis itself
    projected = (U @ (U.T @ want.reshape(len(want), -1))).reshape(want.shape)           # B projected on the basis
    within_precision(rgb, projected, HALF_EPS)
    if k == 15:                                         # the full basis spans the rows: lossless to half floats
        within_precision(rgb, want, HALF_EPS)
    else:
        assert summary["relative_rms_error"] > 1e-3
    assert "classes/leather/als" in fact.header.xml


def test_a_model_basis_of_other_rows_or_class_is_refused(resampled, tmp_path):
    model, _ = _model(tmp_path, resampled, 4)
    with pytest.raises(ValueError, match=r"no ALS basis of class 'stone' \(classes: leather\)"):
        check_export(resampled.path, tmp_path / "x.btf", format="dfmf", basis=model, basis_class="stone")
    with pytest.raises(ValueError, match=r"DFMF in colour model 0"):
        check_export(resampled.path, tmp_path / "x.btf", format="dfmf", colour_model=1, basis=model,
                     basis_class="leather")
    with pytest.raises(ValueError, match=r"--components 5: give 1 to 4"):
        check_export(resampled.path, tmp_path / "x.btf", format="dfmf", components=5, basis=model,
                     basis_class="leather")
    other = make_store(tmp_path / "other.zarr", seed=9)                   # other light directions
    with pytest.raises(ValueError, match=r"other\.zarr: its 15 light/view pairs are not the rows of the model"):
        check_export(other.path, tmp_path / "x.btf", format="dfmf", basis=model, basis_class="leather")
