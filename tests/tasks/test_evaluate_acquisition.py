"""Acquisition evaluation (tasks.evaluate_acquisition): truth stores, chunked = in-memory, bad input.

The numerics on arrays (noise model, multiplexing, strategies, band scores) are tested in
tests/btfcore/test_band_evaluation.py."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from btfcore.metrics import mpsnr, mre, mrmse, relative_error

CONFIG_KW = dict(device="tiny", n_turntable=None, texture_size=12, materials_per_class=2,
                 classes=("carpet", "stone"), sampling_steps=200, als_iterations=3, band_rows=4)


# --------------------------------------------------------------------------- a tiny evaluated database




@pytest.fixture(scope="module")
def tiny_eval(tmp_path_factory, dask_client):
    from tasks.evaluate_acquisition import EvaluationConfig, ensure_truth_database, fit_bases
    from tasks.model import discover

    out = tmp_path_factory.mktemp("eval-acq")
    config = EvaluationConfig(**CONFIG_KW)
    ensure_truth_database(config, out / "db", dask_client)
    materials = discover(out / "db")
    fit_bases(str(out / "model.zarr"), materials, config.model_settings(), dask_client)
    return config, out, materials


def _setup(config, out, materials, material_id):
    from btfcore.acquisition.hadamard import multiplexing_patterns
    from btfcore.acquisition.noise import SensorNoise
    from btfcore.acquisition.band_evaluation import moments_variance
    from tasks.evaluate_acquisition import band_maxima, band_variance, bands
    from tasks.evaluate_acquisition.graph import (_gains, material_geometry, _operators, _reduce_max, _with_pattern_gains,
                                                  band_pattern_maxima)

    m = next(x for x in materials if x.material_id == material_id)
    geometry = material_geometry(m)
    patterns = multiplexing_patterns(geometry.n_leds)
    noise = SensorNoise(fill=config.fill)
    seed = (0, 5)
    parts = bands(geometry.height, 5)
    gains = _gains(_reduce_max([band_maxima(m.path, a, b, patterns, geometry) for a, b in parts]), noise, m.path)
    variance = moments_variance([band_variance(m.path, a, b, gains, patterns, geometry, noise, seed)
                                 for a, b in parts])
    ops = _operators(str(out / "model.zarr"), materials, material_id, config.model_settings(), geometry,
                     config, variance, patterns)
    strategies, _ = _with_pattern_gains(ops, [band_pattern_maxima(m.path, a, b, ops) for a, b in parts], noise,
                                        m.path)
    return m, geometry, patterns, noise, seed, gains, variance, strategies


def test_truth_stores_are_a_database(tiny_eval):
    config, out, materials = tiny_eval
    assert len(materials) == 4 and {m.cls for m in materials} == {"carpet", "stone"}
    g = zarr.open_group(materials[0].path, mode="r", zarr_format=3)
    assert g["btf"].shape == (3 * 4 * 16, 12, 12, 3) and float(g["btf"][...].min()) >= 0
    assert g.attrs["complete"] and g.attrs["kind"] == "evaluation-truth"


def test_variance_over_bands_equals_the_whole_texture(tiny_eval):
    from btfcore.acquisition.reconstruct import texture_variance
    from btfcore.acquisition.band_evaluation import moments_variance
    from tasks.evaluate_acquisition import band_variance, demultiplex_views, noisy_rows
    from tasks.evaluate_acquisition.graph import _read_rows
    config, out, materials = tiny_eval
    m, geometry, patterns, noise, seed, gains, variance, _ = _setup(config, out, materials, materials[0].material_id)
    truth = _read_rows(m.path, 0, geometry.height)
    _, mux = noisy_rows(truth, 0, gains, patterns, geometry, noise, seed)
    # VMV §4.1: per-texture variance of the linear ("unnormalised") demultiplexed BTF, texels and channels
    x = demultiplex_views(mux, patterns, geometry)
    assert variance.shape == (geometry.n_lv,)
    np.testing.assert_allclose(variance, texture_variance(x.reshape(geometry.n_lv, -1)), rtol=1e-6)
    other = moments_variance([band_variance(m.path, a, b, gains, patterns, geometry, noise, seed)
                              for a, b in ((0, 12),)])
    np.testing.assert_allclose(other, variance, rtol=1e-5)


@pytest.mark.parametrize("band_rows", [1, 4, 5])
def test_chunked_reconstruction_equals_in_memory(tiny_eval, tmp_path, band_rows):
    from tasks.evaluate_acquisition import (
        BandScores, bands, create_reconstruction_store, demultiplex_views, evaluate_band, finish_scores, noisy_rows,
        reconstruct_band)
    from btfcore.acquisition.band_evaluation import floor_name, noise_free_band, noisy_patterns
    from btfcore.acquisition.strategies import FLOOR_COMPUTED
    from tasks.evaluate_acquisition.graph import _read_rows

    config, out, materials = tiny_eval
    mid = materials[1].material_id
    m, geometry, patterns, noise, seed, gains, _, strategies = _setup(config, out, materials, mid)
    h = geometry.height
    # in memory: the whole texture at once
    truth = _read_rows(m.path, 0, h)
    single, mux = noisy_rows(truth, 0, gains, patterns, geometry, noise, seed)
    demux = demultiplex_views(mux, patterns, geometry)
    def own(s, noisy=True):                     # a strategy's own patterns measured over the whole texture
        return noisy_patterns(truth, 0, s.gains, s.patterns, *((noise, seed) if noisy else (None, None))) \
            if s.source == "patterns" else None
    whole = {s.name: reconstruct_band(s, 0, h, h, truth, single, mux, 0, geometry, demux, None, own(s))
             for s in strategies}
    # chunked: bands with halos, written to stores and reduced scores
    write = {s.name: create_reconstruction_store(tmp_path / f"{s.name}.zarr", m.path, band_rows, s.name)
             for s in strategies}
    total: dict[str, BandScores] = {}
    for a, b in bands(h, band_rows):
        for name, sc in evaluate_band(m.path, a, b, strategies, gains, patterns, geometry, noise, seed, write).items():
            total[name] = total.get(name, BandScores()).add(sc)
    row_max = truth.reshape(geometry.n_lv, -1).max(1)
    for s in strategies:
        chunked = zarr.open_group(write[s.name], mode="r", zarr_format=3)["btf"][...]
        # float32 GEMMs of other widths round differently; U/Y and V/Y of near-black demultiplexed texels
        # (Y at the floor) amplify that rounding, hence a tolerance of 1e-3 of the peak
        np.testing.assert_allclose(chunked, whole[s.name], rtol=1e-3, atol=1e-3 * float(truth.max()),
                                   err_msg=s.name)
        got = finish_scores(total[s.name], row_max)
        ref = whole[s.name].astype(np.float32)
        assert got["rel_l2_log_y"] == pytest.approx(relative_error(truth, ref, space="log_y"), rel=1e-3), s.name
        assert got["mrmse"] == pytest.approx(mrmse(truth, ref), rel=1e-3), s.name
        assert got["mpsnr"] == pytest.approx(mpsnr(truth, ref), rel=1e-3, abs=1e-3), s.name
        assert got["mre"] == pytest.approx(mre(truth, ref), rel=1e-3), s.name
        # the noise-free floor of every strategy that reads a noisy measurement, reduced over bands alike
        floor = floor_name(s.name)
        assert (floor in total) == (s.floor == FLOOR_COMPUTED), s.name
        if floor in total:
            noise_free = noise_free_band(truth, 0, 0, h, patterns, geometry)
            whole_floor = reconstruct_band(s, 0, h, h, truth, *noise_free[1:3], 0, geometry, noise_free[3], None,
                                           own(s, noisy=False))
            assert finish_scores(total[floor], row_max)["rel_l2_log_y"] == pytest.approx(
                relative_error(truth, whole_floor.astype(np.float32), space="log_y"), rel=1e-3), s.name


def test_denoising_reduces_the_demultiplexed_error(tiny_eval):
    """Sanity of the multiplexed path: a model projection removes noise a plain demultiplexing keeps."""
    from tasks.evaluate_acquisition import demultiplex_views, noisy_rows
    from tasks.evaluate_acquisition.graph import _read_rows

    config, out, materials = tiny_eval
    m, geometry, patterns, noise, seed, gains, _, _ = _setup(config, out, materials, materials[0].material_id)
    truth = _read_rows(m.path, 0, geometry.height)
    single, mux = noisy_rows(truth, 0, gains, patterns, geometry, noise, seed)
    demux = demultiplex_views(mux, patterns, geometry)
    # noise-free multiplexing demultiplexes exactly
    from btfcore.acquisition.reconstruct import measure
    np.testing.assert_allclose(demultiplex_views(measure(truth, patterns=patterns), patterns, geometry), truth,
                               atol=1e-4 * float(truth.max()))
    assert relative_error(truth, demux) > relative_error(truth, single) > 0


def test_vmv_denoising_is_linear_on_the_class_truncated_svd(tiny_eval):
    """VMV §4.1: projection U Uᵀ B and thresholded U Ũ⁺ B̃ on the class' truncated SVD of linear RGB, rows
    above the 9th decile of the linear demultiplexed variance left out; both reproduce a BTF in the basis."""
    from btfcore.acquisition.reconstruct import apply, threshold_rows
    from tasks.evaluate_acquisition import leave_one_out_bases
    from tasks.model import LINEAR_SVD

    config, out, materials = tiny_eval
    mid = materials[0].material_id
    _, geometry, _, _, _, _, variance, strategies = _setup(config, out, materials, mid)
    bases = leave_one_out_bases(str(out / "model.zarr"), materials, mid, config.model_settings())
    # merging only the held-out class gives that class' bases of the merge of every class
    import zarr

    from tasks.evaluate_acquisition import EVAL_BASES
    from tasks.model import merge_bases
    every = merge_bases(zarr.open_group(str(out / "model.zarr"), mode="r"), materials, config.model_settings(),
                        exclude=mid, store=False, bases=EVAL_BASES)
    for name in EVAL_BASES:
        np.testing.assert_array_equal(bases[name].U, every[name][materials[0].cls].U)
    U = bases[LINEAR_SVD].U
    assert bases[LINEAR_SVD].method != "als" and not np.allclose(U[:, :2], bases["als"].U[:, :2])
    by = {s.name: s for s in strategies}
    kept, dropped = threshold_rows(variance, 9)
    assert 0 < len(dropped) <= 0.11 * geometry.n_lv + 1
    B = U.astype(np.float64) @ np.random.default_rng(0).standard_normal((U.shape[1], 7))
    for name in ("projection", "thresholded"):
        s = by[name]
        assert s.space == "linear" and s.source == "demux" and s.rows is None, name
        np.testing.assert_allclose(apply(s.operators["rgb"], B.astype(np.float32)), B, atol=1e-3, err_msg=name)
    noisy = B.copy()
    noisy[dropped] += 100.0                            # the thresholded operator ignores the dropped textures
    np.testing.assert_allclose(apply(by["thresholded"].operators["rgb"], noisy.astype(np.float32)), B, atol=1e-3)


# --------------------------------------------------------------------------- bad input


def test_one_material_per_class_is_refused(tmp_path, dask_client):
    from tasks.evaluate_acquisition import EvaluationConfig, evaluate_acquisition

    config = EvaluationConfig(**{**CONFIG_KW, "materials_per_class": 1})
    with pytest.raises(ValueError, match=r"class 'carpet' has 1 material .*at least 2.*add materials"):
        evaluate_acquisition(tmp_path / "db", tmp_path / "out", dask_client, config)


def test_missing_basis_is_named(tiny_eval, tmp_path):
    import shutil

    from tasks.evaluate_acquisition import leave_one_out_bases

    config, out, materials = tiny_eval
    model = tmp_path / "model.zarr"
    shutil.copytree(out / "model.zarr", model)
    victim = materials[2].material_id
    shutil.rmtree(model / "materials" / victim / "als")
    with pytest.raises(ValueError, match=rf"basis materials/{victim}/als is missing.*run the fit again"):
        leave_one_out_bases(str(model), materials, materials[0].material_id, config.model_settings())


def test_a_foreign_store_in_the_db_is_not_overwritten(tmp_path, dask_client):
    from tasks.evaluate_acquisition import EvaluationConfig, ensure_truth_database, truth_specs

    config = EvaluationConfig(**CONFIG_KW)
    db = tmp_path / "db"
    db.mkdir()
    foreign = db / f"{truth_specs(config)[0].material_id}.zarr"
    zarr.open_group(str(foreign), mode="w", zarr_format=3).attrs.put({"schema": "btf-texture", "complete": True})
    with pytest.raises(ValueError, match="something other than a truth store.*choose another --db"):
        ensure_truth_database(config, db, dask_client)
    assert dict(zarr.open_group(str(foreign), mode="r", zarr_format=3).attrs)["complete"] is True


def test_bad_config_is_refused():
    from tasks.evaluate_acquisition import EvaluationConfig

    with pytest.raises(ValueError, match="classes \\['velvet'\\] are unknown"):
        EvaluationConfig(classes=("velvet",))
