"""Plan layouts, measurement stores and chunked reconstruction (real Zarr, real LocalCluster)."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from btfcore.model.colour import from_log_yuv
from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.acquisition.measurement_operator import demultiplexing_matrix, measurement_solve_operator
from btfcore.acquisition.plan import ExposureModel, sparse_multiplexed_plan
from btfcore.acquisition.reconstruct import apply, measurement_matrix, solve_operator
from btfcore.dome import get_device
from tasks.measurement import plan_layout
from tasks.stores.measurement import write_measurement
from tasks.reconstruct import ReconstructSettings, check_inputs, open_model, reconstruct_chunk, reconstruct_store

N_TURN, N_CAM, N_LEDS, H, W = 2, 2, 8, 8, 8
N_LV = N_TURN * N_CAM * N_LEDS


def _directions(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(2, N_LV, 3))
    d[..., 2] = np.abs(d[..., 2]) + 0.5
    return tuple(d / np.linalg.norm(d, axis=-1, keepdims=True))


def _model(path, bases: dict[str, tuple[np.ndarray, np.ndarray]], cls: str = "leather", seed: int = 0) -> str:
    """A model store (btf-model layout of tasks.model) holding the given class bases."""
    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    light, view = _directions(seed)
    for name, data in (("light_dir", light), ("view_dir", view)):
        group.create_array(name, shape=data.shape, dtype="float64", chunks=data.shape)[...] = data
    group.attrs.put({"schema": "btf-model", "schema_version": "1.0", "rows_id": f"test-{seed}", "n_lv": N_LV})
    for name, (U, sigma) in bases.items():
        sub = group.require_group(f"classes/{cls}/{name}")
        for arr_name, data in (("U", U), ("sigma", sigma)):
            sub.create_array(arr_name, shape=data.shape, dtype="float64", chunks=data.shape)[...] = data
        sub.attrs.put({"method": "test", "key": f"{name}-key"})
    return str(path)


def _orthonormal(rng, n: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    U = np.linalg.qr(rng.normal(size=(n, k)))[0]
    return U, np.linspace(10.0, 1.0, k)


def _measurement(path, B: np.ndarray, G: np.ndarray) -> str:
    light, view = _directions()
    measured = (G @ B.reshape(N_LV, -1)).reshape(len(G), *B.shape[1:])
    write_measurement(path, measured, G, light, view, (N_TURN, N_CAM, N_LEDS))
    return str(path)


def _sparse_G(rows) -> np.ndarray:
    return measurement_matrix(N_LV, rows=np.asarray(rows))


def test_plan_layout_matches_the_plan():
    device = get_device("tiny")
    sel = np.array([[0, 0], [0, 3], [1, 5], [2, 18]])
    plan = sparse_multiplexed_plan(device, sel, ExposureModel(single_ms=(1.0, 10.0, 100.0)))
    illum, shot, times = plan_layout(plan)
    pat = multiplexing_patterns(device.n_leds)
    assert illum.shape == (4, device.n_leds)
    for k, s in enumerate(plan.shots):
        i = next(j for j in range(len(illum)) if tuple(np.flatnonzero(illum[j])) == s.leds)
        assert (shot[s.turntable, list(s.cameras), i] == k).all()
        np.testing.assert_allclose(times[s.turntable, 0, i, :s.n_exposures], np.asarray(s.shutter_ms) / 1000)
        assert tuple(np.flatnonzero(pat[sel[k, 1]])) == s.leds
    assert (shot >= 0).sum() == len(plan.shots) * device.n_cam


def test_general_G_operator_equals_solve_operator():
    rng = np.random.default_rng(1)
    U, sigma = _orthonormal(rng, N_LV, 6)
    pat = multiplexing_patterns(N_LEDS)
    rows = np.sort(rng.choice(N_TURN * N_CAM * pat.shape[0], 20, replace=False))
    G = measurement_matrix(N_LV, rows=rows, patterns=pat)
    y = rng.normal(size=(len(rows), 50))
    for lam in (0.0, 0.5):
        a = measurement_solve_operator(U, G, sigma, method="direct", lam=lam, dtype=np.float64)
        b = solve_operator(U, sigma, method="direct", rows=rows, patterns=pat, lam=lam, dtype=np.float64)
        np.testing.assert_allclose(apply(a, y), apply(b, y), rtol=1e-10, atol=1e-10)
    G_full = measurement_matrix(N_LV, patterns=pat)
    P = demultiplexing_matrix(G_full).toarray()
    np.testing.assert_allclose(P @ G_full, np.eye(N_LV), atol=1e-10)
    np.testing.assert_allclose(P, np.linalg.pinv(G_full), atol=1e-10)           # block by block = whole
    with pytest.raises(ValueError, match="method='direct'"):
        measurement_solve_operator(U, G, method="pinv")
    with pytest.raises(ValueError, match="cannot be demultiplexed"):
        measurement_solve_operator(U, G, method="projection")


@pytest.mark.parametrize("basis", ["als", "log_y"])
def test_exact_in_span_reconstruction_chunked_equals_in_memory(tmp_path, dask_client, basis):
    rng = np.random.default_rng(2)
    k = 5
    if basis == "als":
        U, sigma = _orthonormal(rng, N_LV, k)
        bases = {"als": (U, sigma)}
        B = (U @ rng.normal(size=(k, H * W * 3))).reshape(N_LV, H, W, 3)
    else:
        bases = {name: _orthonormal(rng, N_LV, k) for name in ("log_y", "u_y", "v_y")}
        x = np.stack([(bases[n][0] @ rng.normal(scale=s, size=(k, H * W))).reshape(N_LV, H, W)
                      for n, s in (("log_y", 1.0), ("u_y", 0.1), ("v_y", 0.1))], axis=-1)
        B = from_log_yuv(x)                                   # log Y, U/Y, V/Y exactly in the bases' span
    model = _model(tmp_path / "model.zarr", bases)
    rows = np.sort(rng.choice(N_LV, 12, replace=False))      # sparse single-light, 12 rows >= k
    meas = _measurement(tmp_path / "m.zarr", B, _sparse_G(rows))
    settings = ReconstructSettings(cls="leather", basis=basis, method="pinv")
    summary = reconstruct_store(meas, tmp_path, tmp_path / "out.zarr", settings, dask_client, band_rows=3)
    assert summary["bands_processed"] == 3
    out = zarr.open_group(str(tmp_path / "out.zarr"), mode="r")
    assert out.attrs["schema"] == "btf-texture" and out.attrs["complete"]
    assert not (tmp_path / "out.partial.zarr").exists()
    got = out["btf"][...]
    np.testing.assert_allclose(got, B, rtol=2e-3, atol=2e-4 * np.abs(B).max())
    # chunked (3 bands on the cluster) equals the in-memory reconstruction of the whole texture
    from tasks.reconstruct import build_operators
    ops = build_operators(settings, open_model(model), _sparse_G(rows), N_LV)
    whole = reconstruct_chunk(ops, zarr.open_group(meas, mode="r")["measured"][...])
    np.testing.assert_allclose(got, whole, rtol=1e-5, atol=1e-6 * np.abs(whole).max())
    # a finished output is reused, not recomputed
    again = reconstruct_store(meas, tmp_path, tmp_path / "out.zarr", settings, dask_client, band_rows=3)
    assert again["reused"]


def test_abtf_bands_equal_whole_texture_and_multiplexed_direct(tmp_path, dask_client):
    rng = np.random.default_rng(3)
    k = 6
    bases = {"abtf_log_y": _orthonormal(rng, 9 * N_LV, k), "u_y": _orthonormal(rng, N_LV, 4),
             "v_y": _orthonormal(rng, N_LV, 4), "als": _orthonormal(rng, N_LV, k)}
    _model(tmp_path / "model.zarr", bases)
    B = np.exp(rng.normal(scale=0.3, size=(N_LV, H, W, 3))).astype(np.float32)
    rows = np.sort(rng.choice(N_LV, 10, replace=False))
    meas = _measurement(tmp_path / "sparse.zarr", B, _sparse_G(rows))
    settings = ReconstructSettings(cls="leather", basis="abtf_log_y", method="pinv")
    reconstruct_store(meas, tmp_path / "model.zarr", tmp_path / "abtf.zarr", settings, dask_client, band_rows=2)
    from tasks.reconstruct import build_operators
    ops = build_operators(settings, open_model(tmp_path / "model.zarr"), _sparse_G(rows), N_LV)
    whole = reconstruct_chunk(ops, zarr.open_group(meas, mode="r")["measured"][...])
    got = zarr.open_group(str(tmp_path / "abtf.zarr"), mode="r")["btf"][...]
    np.testing.assert_allclose(got, whole, rtol=1e-4, atol=1e-6 * np.abs(whole).max())
    # multiplexed rows: exact in the ALS span with 'direct'
    U = bases["als"][0]
    B_lin = (U @ rng.normal(size=(k, H * W * 3))).reshape(N_LV, H, W, 3)
    pat = multiplexing_patterns(N_LEDS)
    G = measurement_matrix(N_LV, rows=np.arange(0, N_TURN * N_CAM * pat.shape[0], 3), patterns=pat)
    mux = _measurement(tmp_path / "mux.zarr", B_lin, G)
    reconstruct_store(mux, tmp_path / "model.zarr", tmp_path / "direct.zarr",
                      ReconstructSettings(cls="leather", basis="als", method="direct"), dask_client)
    got = zarr.open_group(str(tmp_path / "direct.zarr"), mode="r")["btf"][...]
    np.testing.assert_allclose(got, B_lin, atol=2e-4 * np.abs(B_lin).max())
    with pytest.raises(ValueError, match="multiplexed rows"):
        check_inputs(mux, tmp_path / "model.zarr", ReconstructSettings(cls="leather", basis="log_y"))


def test_bad_input_is_named_before_anything_is_written(tmp_path):
    rng = np.random.default_rng(4)
    U, sigma = _orthonormal(rng, N_LV, 10)
    _model(tmp_path / "model.zarr", {"als": (U, sigma)})
    _model(tmp_path / "other.zarr", {"als": (U, sigma)}, seed=9)        # another light/view sampling
    B = rng.normal(size=(N_LV, H, W, 3))
    meas = _measurement(tmp_path / "m.zarr", B, _sparse_G(np.arange(6)))
    with pytest.raises(ValueError, match="light/view pair 0 differs"):
        check_inputs(meas, tmp_path / "other.zarr", ReconstructSettings(cls="leather"))
    with pytest.raises(ValueError, match=r"6 measured rows for k=10.*tikhonov"):
        check_inputs(meas, tmp_path / "model.zarr", ReconstructSettings(cls="leather", method="pinv"))
    check_inputs(meas, tmp_path / "model.zarr", ReconstructSettings(cls="leather", method="tikhonov", lam=0.01))
    with pytest.raises(ValueError, match="--class 'wood' is not a class of this model; choose one of: leather"):
        check_inputs(meas, tmp_path / "model.zarr", ReconstructSettings(cls="wood"))
    with pytest.raises(ValueError, match="log space"):
        ReconstructSettings(cls="leather", basis="log_y", method="direct")
    assert not (tmp_path / "out.zarr").exists()


def test_tikhonov_defaults_to_the_thesis_lambda_of_the_basis():
    assert ReconstructSettings(cls="leather", basis="als", method="tikhonov").lam == 0.01      # paper 4, ALS
    assert ReconstructSettings(cls="leather", basis="log_y", method="tikhonov").lam == 40.0   # paper 4, log bases
    assert ReconstructSettings(cls="leather", basis="als", method="tikhonov", lam=2.0).lam == 2.0
    assert ReconstructSettings(cls="leather", basis="als", method="pinv").lam is None


@pytest.mark.parametrize("case", ["sparse log_y pinv", "multiplexed als direct", "full multiplexed als thresholded"])
def test_radiometric_correction_of_an_uncorrected_measurement(tmp_path, dask_client, case):
    """A corrected BTF in the basis' span, measured uncorrected (``G D_c B_c``, then the inverse colour
    matrix): ``--white``/``--colour-matrix`` at reconstruction give the corrected BTF back."""
    from btfcore.capture.radiometric import apply_colour_matrix
    from tasks.radiometric import Calibration
    from tasks.reconstruct import RowCorrection, build_operators

    rng = np.random.default_rng(5)
    k = 5
    gain = rng.uniform(0.5, 2.0, (N_LEDS, 3))                              # per-LED RGB gains
    matrix = np.array([[1.2, -0.1, 0.0], [0.05, 0.9, 0.05], [0.0, -0.2, 1.1]])
    calibration = Calibration(led_gain=gain, colour_matrix=matrix, info={"white_standard": "test"})
    if case.startswith("sparse"):
        bases = {name: _orthonormal(rng, N_LV, k) for name in ("log_y", "u_y", "v_y")}
        x = np.stack([(bases[n][0] @ rng.normal(scale=s, size=(k, H * W))).reshape(N_LV, H, W)
                      for n, s in (("log_y", 1.0), ("u_y", 0.1), ("v_y", 0.1))], axis=-1)
        B = from_log_yuv(x)                                                 # corrected, exactly in the span
        settings = ReconstructSettings(cls="leather", basis="log_y", method="pinv")
        G = _sparse_G(np.sort(rng.choice(N_LV, 12, replace=False)))
    else:
        bases = {"als": _orthonormal(rng, N_LV, k)}
        B = (bases["als"][0] @ rng.normal(size=(k, H * W * 3))).reshape(N_LV, H, W, 3)
        pat = multiplexing_patterns(N_LEDS)
        n_rows = N_TURN * N_CAM * pat.shape[0]
        thresholded = case.endswith("thresholded")
        G = measurement_matrix(N_LV, rows=None if thresholded else np.arange(0, n_rows, 2), patterns=pat)
        settings = ReconstructSettings(cls="leather", basis="als", method="thresholded" if thresholded else "direct")
    model = _model(tmp_path / "model.zarr", bases)
    camera = apply_colour_matrix(B, np.linalg.inv(matrix))                 # what the camera saw, LEDs corrected
    raw = camera * np.tile(gain, (N_LV // N_LEDS, 1))[:, None, None, :]    # and before the LED gains
    meas = _measurement(tmp_path / "m.zarr", raw, G)
    check_inputs(meas, model, settings, calibration)
    ops = build_operators(settings, open_model(model), G, N_LV, np.ones(N_LV) if settings.method == "thresholded"
                          else None)
    assert set(ops) == ({"y", "u", "v"} if case.startswith("sparse") else {"rgb"})
    correction = RowCorrection.of(gain, matrix, G, N_LV)                   # multiplexed: one operator per channel
    assert set(build_operators(settings, open_model(model), G, N_LV, np.ones(N_LV), correction=correction)) == \
        ({"y", "u", "v"} if case.startswith("sparse") else {"r", "g", "b"})
    summary = reconstruct_store(meas, model, tmp_path / "out.zarr", settings, dask_client, band_rows=3,
                                calibration=calibration)
    out = zarr.open_group(str(tmp_path / "out.zarr"), mode="r")
    assert out.attrs["radiometric"] == {"white_standard": "test"} and "calibrated" in out.attrs["units"]
    np.testing.assert_allclose(out["btf"][...], B, rtol=2e-3, atol=2e-4 * np.abs(B).max())
    # without the correction the same measurement reconstructs to something else, and the key differs
    plain = reconstruct_store(meas, model, tmp_path / "plain.zarr", settings, dask_client, band_rows=3)
    assert not np.allclose(zarr.open_group(str(tmp_path / "plain.zarr"), mode="r")["btf"][...], B, rtol=0.05)
    assert summary["out"] != plain["out"]
    # a corrected BTF store is not corrected twice
    with pytest.raises(ValueError, match="already radiometrically corrected"):
        check_inputs(tmp_path / "out.zarr", model, ReconstructSettings(cls="leather", basis=settings.basis,
                                                                         method="projection"), calibration)
    wrong = Calibration(led_gain=gain[:3], colour_matrix=None, info={"white_standard": "small"})
    with pytest.raises(ValueError, match="small: the white standard has 3 LEDs.*8"):
        check_inputs(meas, model, settings, wrong)


def test_sparse_G_gives_the_dense_results():
    """Every function of btfcore.acquisition.measurement_operator takes G dense or sparse alike (tasks read G sparse)."""
    from scipy import sparse

    from btfcore.acquisition.measurement_operator import is_single_light, single_light_rows

    rng = np.random.default_rng(6)
    U, sigma = _orthonormal(rng, N_LV, 6)
    pat = multiplexing_patterns(N_LEDS)
    full = measurement_matrix(N_LV, patterns=pat)
    mux = full[np.sort(rng.choice(len(full), 20, replace=False))]
    single = _sparse_G(np.sort(rng.choice(N_LV, 12, replace=False)))
    for G, method, lam in ((mux, "direct", 0.1), (single, "tikhonov", 0.1), (full, "thresholded", None)):
        kw = {"method": method, "lam": lam, "variance": np.linspace(1.0, 2.0, N_LV), "dtype": np.float64}
        a = measurement_solve_operator(U, G, sigma, **kw)
        b = measurement_solve_operator(U, sparse.csr_matrix(G), sigma, **kw)
        z = rng.normal(size=(G.shape[0], 9))
        np.testing.assert_allclose(apply(a, z), apply(b, z), rtol=1e-12, atol=1e-12)
        assert is_single_light(G) == is_single_light(sparse.csr_matrix(G)) == (G is single)
    np.testing.assert_array_equal(single_light_rows(single), single_light_rows(sparse.csr_matrix(single)))
    np.testing.assert_array_equal(demultiplexing_matrix(full).toarray(),
                                  demultiplexing_matrix(sparse.csr_matrix(full)).toarray())
    bad = sparse.lil_matrix(single)
    bad[3, 0] = np.nan
    with pytest.raises(ValueError, match=r"G\[3, 0\] = nan: G must be finite"):
        measurement_solve_operator(U, bad.tocsr(), sigma, method="tikhonov", lam=0.1)
    two = single.copy()
    two[2] += single[3]                                       # row 2 now measures two pairs
    with pytest.raises(ValueError, match="G row 2 measures 2 light/view pairs"):
        single_light_rows(sparse.csr_matrix(two))


@pytest.mark.parametrize("affine", [False, True])
def test_colour_matrix_alone_on_a_multiplexed_measurement(tmp_path, affine):
    """Without LED gains a linear colour matrix is applied before the solve (it commutes with G); an affine
    one after it, per channel (its offset does not commute with G). Both give the corrected BTF back."""
    from btfcore.capture.radiometric import apply_colour_matrix
    from tasks.reconstruct import RowCorrection, build_operators

    rng = np.random.default_rng(7)
    U, sigma = _orthonormal(rng, N_LV, 5)
    model = open_model(_model(tmp_path / "model.zarr", {"als": (U, sigma)}))
    camera = (U @ rng.normal(size=(5, H * W * 3))).reshape(N_LV, H, W, 3)   # what the camera saw, in the span
    M = np.array([[1.2, -0.1, 0.0], [0.05, 0.9, 0.05], [0.0, -0.2, 1.1]])
    matrix = np.hstack([M, [[0.01], [0.02], [-0.01]]]) if affine else M
    B = apply_colour_matrix(camera, matrix)                                    # the corrected BTF
    pat = multiplexing_patterns(N_LEDS)
    G = measurement_matrix(N_LV, rows=np.arange(0, N_TURN * N_CAM * pat.shape[0], 2), patterns=pat)
    measured = (G @ camera.reshape(N_LV, -1)).reshape(len(G), H, W, 3)
    correction = RowCorrection.of(None, matrix, G, N_LV)
    assert (correction.measured_gain is None) == affine
    ops = build_operators(ReconstructSettings(cls="leather", method="direct"), model, G, N_LV, correction=correction)
    assert set(ops) == ({"r", "g", "b"} if affine else {"rgb"})
    got = reconstruct_chunk(ops, measured, correction=correction)
    np.testing.assert_allclose(got, B, atol=2e-4 * np.abs(B).max())


def test_all_finite_needs_no_mask_of_the_band_and_misses_nothing():
    """The band checks test the float sum first: a NaN or Inf anywhere is found, and finite values whose
    sum overflows are not taken for one."""
    from tasks.reconstruct import _all_finite

    a = np.ones((4, 5, 3), np.float32)
    assert _all_finite(a)
    for bad in (np.nan, np.inf, -np.inf):
        b = a.copy()
        b[3, 4, 2] = bad
        assert not _all_finite(b)
    assert _all_finite(np.full((64,), 3e38, np.float32))           # sums to inf, every value finite
