"""A rerun of the acquisition evaluation reuses every finished result whose inputs did not change.

The counts are the summary's ``"reused"`` (``{what: [reused, total]}``), never timings.
"""

from __future__ import annotations

import zarr

CONFIG_KW = dict(device="tiny", n_turntable=None, texture_size=12, materials_per_class=2,
                 classes=("carpet", "stone"), sampling_steps=200, als_iterations=3, band_rows=4,
                 render_materials=1, render_size=16, keep_reconstructions=True)


def test_a_rerun_reuses_everything_and_a_changed_input_is_recomputed(tmp_path, dask_client):
    from tasks.evaluate_acquisition import EvaluationConfig, evaluate_acquisition, reuse_message, strategy_names

    config = EvaluationConfig(**CONFIG_KW)
    db, out = tmp_path / "db", tmp_path / "out"
    n_strategies = len(strategy_names())

    first = evaluate_acquisition(db, out, dask_client, config)
    assert first["reused"] == {"truth_stores": [0, 4], "bases": [0, 24], "material_scores": [0, 4],
                               "reconstructions": [0, n_strategies], "figures": [0, 1]}

    second = evaluate_acquisition(db, out, dask_client, config)
    assert second["reused"] == {"truth_stores": [4, 4], "bases": [24, 24], "material_scores": [4, 4],
                                "reconstructions": [n_strategies, n_strategies], "figures": [1, 1]}
    assert second["materials"] == first["materials"]
    assert second["claims"] == first["claims"] and second["figures"] == first["figures"]
    assert reuse_message(second["reused"]).startswith("evaluate acquisition: reused 4 of 4 truth stores, ")

    # a killed run: a record that is no finished JSON and a reconstruction store left incomplete are redone
    (mid_rendered,) = first["figures"]
    other = next(mid for mid in first["materials"] if mid != mid_rendered)
    record = out / "scores" / f"{other}.json"
    record.write_text(record.read_text()[:40])
    store = first["reconstructions"][mid_rendered][strategy_names()[0]]
    zarr.open_group(store, mode="r+", zarr_format=3).attrs.update({"complete": False})
    third = evaluate_acquisition(db, out, dask_client, config)
    assert third["reused"]["material_scores"] == [2, 4]
    assert third["reused"]["reconstructions"] == [0, n_strategies]
    assert third["reused"]["figures"] == [1, 1]
    assert third["materials"] == first["materials"]

    # another input (the exposure fill): every score is recomputed, the truth and the bases are not
    changed = EvaluationConfig(**{**CONFIG_KW, "fill": 0.7})
    fourth = evaluate_acquisition(db, out, dask_client, changed)
    assert fourth["reused"] == {"truth_stores": [4, 4], "bases": [24, 24], "material_scores": [0, 4],
                                "reconstructions": [0, n_strategies], "figures": [0, 1]}
    assert fourth["key"]["scores"] != first["key"]["scores"]
    assert fourth["materials"] != first["materials"]
