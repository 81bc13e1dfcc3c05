"""The verdicts of claims (a)-(f) (tasks.evaluate_acquisition.claims): each rule flips when its input crosses
its threshold. Small constructed score tables, no cluster."""

from __future__ import annotations

import pytest

from tasks.evaluate_acquisition import claims, strategy_names
from tasks.html_report import columns_without_unit

#: Errors (rel. L2 log Y, fractions) where every claim holds.
BASE = {"abrdf-pmap7": 0.50, "abrdf-optimized": 0.20, "abtf-pmap7": 0.15, "abtf-optimized": 0.14,
        "abrdf-projection": 0.04, "abtf-projection": 0.10,
        "demultiplexed": 0.25, "projection": 0.11, "thresholded": 0.09,
        "sparse-tikhonov-n100": 0.24, "sparse-pinv-n100": 0.26, "sparse-tikhonov-n200": 0.18,
        "sparse-pinv-n200": 0.19, "sparse-tikhonov-n400": 0.16, "sparse-pinv-n400": 0.17,
        "multiplexed-direct": 0.17, "sparse-multiplexed-n400": 0.18,
        "patterns-quarter": 0.165, "smatrix-quarter": 0.2}
TIMES = {"evaluated_device_s": {"full-single": 1800.0, "sparse": 320.0, "multiplexed": 1400.0,
                                "sparse-multiplexed": 250.0, "patterns": 460.0, "smatrix-subsampled": 350.0},
         "thesis_device_s": {"full-single": 11000.0, "sparse": 1900.0, "multiplexed": 8400.0,
                             "sparse-multiplexed": 1500.0}}


def _result(classes=("carpet", "stone", "leather"), **changes: dict[str, float]) -> dict:
    """Two materials per class with the errors of BASE; ``changes[class]`` overrides that class' errors."""
    materials = {}
    for i, cls in enumerate(classes):
        errors = {**BASE, **changes.get(cls, {})}
        for j in range(2):
            materials[f"{2 * i + j:03d}-{cls}"] = {
                "class": cls, "scores": {name: {"rel_l2_log_y": errors[name], "mrmse": 0.1, "mpsnr": 20.0,
                                                "mre": 10.0} for name in strategy_names()},
                "strategies": {"patterns-quarter": {"m": 49}}, "sampling": {"patterns": {"n_leds": 198}}}
    return {"materials": materials}


def _everywhere(**errors: float) -> dict[str, dict[str, float]]:
    return {cls: errors for cls in ("carpet", "stone", "leather")}


def test_the_base_table_meets_every_claim():
    out = claims(_result(), TIMES)
    assert {k: c["verdict"] for k, c in out.items()} == dict.fromkeys("abcdef", "met")
    assert out["c"]["classes_in_order"] == "3/3"
    assert out["d"]["numbers"]["ratio_to_sparse"] == pytest.approx(0.18 / 0.16, abs=1e-3)


@pytest.mark.parametrize("name,value,verdict", [
    ("abtf-optimized", 0.199, "met"), ("abtf-optimized", 0.201, "not met"),
    ("abtf-pmap7", 0.499, "met"), ("abtf-pmap7", 0.501, "not met"),
])
def test_claim_a_needs_abtf_below_abrdf_in_every_structured_class(name, value, verdict):
    out = claims(_result(stone={name: value}), TIMES)          # one class crossing is enough
    assert out["a"]["verdict"] == verdict


def test_claim_a_is_not_tested_without_a_structured_class():
    out = claims(_result(classes=("metal", "wood")), TIMES)
    assert out["a"]["verdict"].startswith("not tested") and out["a"]["numbers"] == {}


@pytest.mark.parametrize("model", ["abrdf", "abtf"])
@pytest.mark.parametrize("optimized,verdict", [(0.149, "met"), (0.151, "not met")])
def test_claim_b_needs_the_mean_optimized_below_the_parabolic_map(model, optimized, verdict):
    pmap = {f"{model}-pmap7": 0.15}
    changes = _everywhere(**pmap, **{f"{model}-optimized": optimized},
                          **({"abtf-pmap7": 0.15, "abtf-optimized": 0.14} if model == "abrdf" else {}))
    out = claims(_result(**changes), TIMES)
    assert out["b"]["verdict"] == verdict
    assert out["b"]["numbers"][model]["materials_where_optimized_wins"] == ("6/6" if verdict == "met" else "0/6")


@pytest.mark.parametrize("changes,verdict", [
    ({"thresholded": 0.109}, "met"), ({"thresholded": 0.111}, "not met"),      # thresholded < projection
    ({"projection": 0.249}, "met"), ({"projection": 0.251}, "not met"),        # projection < demultiplexed
])
def test_claim_c_needs_thresholded_below_projection_below_demultiplexed(changes, verdict):
    if "projection" in changes:
        changes = {**changes, "thresholded": 0.10}
    out = claims(_result(**_everywhere(**changes)), TIMES)
    assert out["c"]["verdict"] == verdict


def test_claim_c_reports_each_half_and_the_classes_in_order():
    out = claims(_result(carpet={"thresholded": 0.12}), TIMES)   # carpet: thresholded above projection
    halves = out["c"]["numbers"]["halves"]
    assert halves["projection < demultiplexed"] == {"means": "met", "classes": "3/3"}
    assert halves["thresholded < projection"]["classes"] == "2/3" and out["c"]["classes_in_order"] == "2/3"


@pytest.mark.parametrize("changes,times,verdict", [
    ({"sparse-multiplexed-n400": 0.319}, None, "met"),                    # <= 2x sparse-only (0.16)
    ({"sparse-multiplexed-n400": 0.321}, None, "not met"),
    ({"multiplexed-direct": 0.1605, "sparse-multiplexed-n400": 0.32}, None, "met"),   # <= 2x multiplexed-only
    ({"multiplexed-direct": 0.1595, "sparse-multiplexed-n400": 0.32}, None, "not met"),
    ({}, {"sparse-multiplexed": 319.0}, "met"),                            # faster than sparse-only (320 s)
    ({}, {"sparse-multiplexed": 321.0}, "not met"),
    ({}, {"multiplexed": 251.0, "sparse": 1000.0}, "met"),                 # faster than multiplexed-only
    ({}, {"multiplexed": 249.0, "sparse": 1000.0}, "not met"),
])
def test_claim_d_needs_an_error_within_2x_and_a_shorter_time(changes, times, verdict):
    if changes.get("sparse-multiplexed-n400") == 0.32:
        changes = {**changes, "sparse-tikhonov-n400": 0.2}                # keep the sparse-only ratio below 2
    t = {**TIMES, "evaluated_device_s": {**TIMES["evaluated_device_s"], **(times or {})}}
    out = claims(_result(**_everywhere(**changes)), t)
    assert out["d"]["verdict"] == verdict


@pytest.mark.parametrize("tikhonov,verdict", [(0.259, "met"), (0.261, "not met")])
def test_claim_e_needs_tikhonov_below_pinv_at_the_smallest_count(tikhonov, verdict):
    out = claims(_result(**_everywhere(**{"sparse-tikhonov-n100": tikhonov})), TIMES)
    assert out["e"]["verdict"] == verdict
    assert out["e"]["numbers"]["n_s=100"] == {"tikhonov": round(100 * tikhonov, 3), "pinv": 26.0}


def test_divergence_and_conditioning_name_their_reason():
    from btfcore.acquisition.band_evaluation import conditioning, divergence

    good = {"rel_l2_log_y": 0.2, "mrmse": 0.1, "mpsnr": 20.0, "mre": 900.0}
    info = {"k": 166, "n_meas": 222, "kappa_log_y": 9.2e4}
    assert divergence(good, info) is None and conditioning(info) is None
    reason = divergence({**good, "mre": 2.3e11, "mpsnr": 2.08}, info)
    assert reason.startswith("diverged: mRE 2.3e+11 % > 10,000 %") and "condition number" in reason
    assert "166 basis vectors from 222 samples" in reason
    assert "log Y relative L2 170 % > 100 %" in divergence({**good, "rel_l2_log_y": 1.7})
    assert "mpsnr is not finite" in divergence({**good, "mpsnr": float("nan")})
    assert "condition number 2e+07 > 1e+06" in conditioning({"condition": 2e7})
    assert "12 samples below the basis rank 32" in conditioning({"k": 32, "n_meas": 12})


def test_means_leave_diverged_results_out_and_say_how_many():
    from tasks.evaluate_acquisition import class_means, overall_means, thesis_tables
    from tasks.evaluate_acquisition.claims import result_flags

    result = _result()
    bad = result["materials"]["000-carpet"]["scores"]["abrdf-pmap7"]
    bad.update(rel_l2_log_y=0.9, mre=2.3e11)                        # diverged (mRE), its log Y error plausible
    assert set(result_flags(result)["diverged"]) == {"000-carpet"}
    assert class_means(result)["carpet"]["abrdf-pmap7"] == pytest.approx(0.50)     # the other carpet only
    assert overall_means(result)["abrdf-pmap7"] == pytest.approx(0.50)
    assert overall_means(result, "mre")["abrdf-pmap7"] == pytest.approx(10.0)
    out = claims(result, TIMES)
    assert out["a"]["excluded"] == {"carpet": {"abrdf-pmap7": "1 of 2"}} and out["b"]["excluded"]
    assert out["b"]["numbers"]["abrdf"]["materials_where_optimized_wins"] == "6/6"
    # every result of a group diverged: the mean is over them, and flagged so
    result["materials"]["001-carpet"]["scores"]["abrdf-pmap7"].update(mre=1e12)
    assert class_means(result)["carpet"]["abrdf-pmap7"] == pytest.approx(0.70)
    tables = thesis_tables(result, flagged=True)
    carpet = next(r for r in tables["paper1_table2"] if r[0] == "carpet")
    assert carpet[2]["flag"].startswith("all 2 results diverged")
    assert [r[:2] for r in tables["flagged_results"][1:]] == [["000-carpet", "abrdf-pmap7"],
                                                              ["001-carpet", "abrdf-pmap7"]]
    plain = thesis_tables(result)                                  # report.json: numbers, no flags
    assert not any(isinstance(c, dict) for row in plain["paper1_table2"] for c in row)
    # every numeric column names its unit or is a count
    for rows in [t["rows"] for claim in out.values() for t in claim["tables"]] + list(tables.values()):
        assert columns_without_unit(rows) == [], rows[0]


@pytest.mark.parametrize("error,time,verdict", [
    (0.17, 700.0, "met"), (0.171, 700.0, "not met"), (0.165, 701.0, "not met"),
])
def test_claim_f_needs_patterns_no_worse_than_the_full_s_matrix_at_half_its_time(error, time, verdict):
    """Issue 20's bar: the designed patterns' mean error <= the full S-matrix's (0.17) and time <= 0.5 x 1400 s."""
    t = {**TIMES, "evaluated_device_s": {**TIMES["evaluated_device_s"], "patterns": time}}
    out = claims(_result(**_everywhere(**{"patterns-quarter": error})), t)
    assert out["f"]["verdict"] == verdict
    assert out["f"]["numbers"]["time_ratio_to_full_s_matrix"] == pytest.approx(time / 1400.0, abs=1e-3)
