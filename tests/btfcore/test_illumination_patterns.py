"""Basis-aware illumination patterns (btfcore.acquisition.illumination_patterns, issue 20): the predicted error
is the solve's error, the design beats random and S-matrix codes on it, binary and seeded."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.acquisition.illumination_patterns import (
    PatternModel,
    design_patterns,
    expected_error,
    pattern_operator,
    random_patterns,
    select_rows,
)
from btfcore.acquisition.noise import SensorNoise
from btfcore.acquisition.reconstruct import apply


def _model(n_views: int = 6, n_leds: int = 16, k: int = 5, seed: int = 0, **kw) -> PatternModel:
    """An orthonormal basis whose first vector is a smooth positive ABRDF-like mean, the rest random."""
    rng = np.random.default_rng(seed)
    n = n_views * n_leds
    mean = 1.0 + 0.5 * np.sin(np.linspace(0, 3, n)) + 0.2 * rng.random(n)
    U = np.linalg.qr(np.column_stack([mean, rng.normal(size=(n, k - 1))]))[0]
    return PatternModel(U, np.geomspace(30.0, 1.0, k), n_leds, SensorNoise(), **kw)


def _monte_carlo(model: PatternModel, patterns: np.ndarray, draws: int, seed: int) -> float:
    """Mean ||U (c_hat - c)||^2 of the solve over coefficients drawn from the prior, a model error outside the
    basis (relative model_error of each pair's typical radiance) and Gaussian image noise at the model's
    predicted variances."""
    rng = np.random.default_rng(seed)
    op = pattern_operator(model, patterns, dtype=np.float64)
    c = rng.normal(size=(model.k, draws)) * np.sqrt(model.prior)[:, None]
    B = model.U @ c                                                             # (n_lv, draws)
    e = rng.normal(size=B.shape) * (model.model_error * model.radiance.reshape(-1))[:, None]
    y = np.einsum("pl,vld->vpd", patterns.astype(float), (B + e).reshape(model.n_views, model.n_leds, draws))
    x = model.radiance @ patterns.T.astype(float)                               # (V, m) typical radiance
    y = y + rng.normal(size=y.shape) * np.sqrt(model.variance(x))[..., None]
    B_hat = apply(op, y.reshape(-1, draws))
    return float(np.mean(np.sum((B_hat - B) ** 2, axis=0)))


@pytest.mark.parametrize("kind", ["designed", "s-matrix", "random"])
def test_the_objective_is_the_monte_carlo_error_of_the_solve(kind):
    model = _model()
    if kind == "designed":
        patterns = design_patterns(model, 4, seed=1).patterns
    elif kind == "s-matrix":
        patterns = multiplexing_patterns(model.n_leds)
    else:
        patterns = random_patterns(model.n_leds, 4, seed=2)
    J = expected_error(model, patterns).objective
    mc = _monte_carlo(model, patterns, 20000, seed=3)
    assert mc == pytest.approx(J, rel=0.04)


def test_the_relative_error_does_not_depend_on_the_prior_scale():
    a = _model()
    b = _model(prior_scale=1e4)
    p = random_patterns(a.n_leds, 5, seed=0)
    assert expected_error(b, p).relative_error == pytest.approx(expected_error(a, p).relative_error, rel=1e-9)
    assert expected_error(b, p).objective == pytest.approx(1e4 * expected_error(a, p).objective, rel=1e-9)


@pytest.mark.parametrize("shutter_fill", [None, 0.01])
def test_designed_patterns_beat_random_and_subsampled_s_matrix_codes(shutter_fill):
    model = _model(n_leds=24, shutter_fill=shutter_fill)
    m = model.n_leds // 4
    design = design_patterns(model, m, seed=0)
    S = multiplexing_patterns(model.n_leds)
    _, sub = select_rows(model, S, m)
    rand = min(expected_error(model, random_patterns(model.n_leds, m, seed=s)).objective for s in range(5))
    assert design.objective < sub.objective and design.objective < rand
    assert set(np.unique(design.patterns)) <= {0, 1} and design.patterns.dtype == np.uint8
    assert design.patterns.shape == (m, model.n_leds) and (design.patterns.sum(axis=1) >= 1).all()
    assert np.all(np.diff(design.history) <= 1e-9 * design.history[0])          # never worse for a step
    assert design.objective == pytest.approx(expected_error(model, design.patterns).objective, rel=1e-9)


def test_a_short_shutter_turns_more_leds_on():
    """Under auto exposure every image holds the same charge, so a pattern gains no SNR from more LEDs; at a
    short chosen shutter a single LED is read-noise limited and patterns light more LEDs until they saturate."""
    auto = design_patterns(_model(n_leds=24, model_error=0.0), 6, seed=0)
    dark = design_patterns(_model(n_leds=24, model_error=0.0, shutter_fill=0.002), 6, seed=0)
    assert dark.leds_on.mean() > 2 * auto.leds_on.mean()


def test_model_error_makes_patterns_spread_light_and_refining_a_start_helps():
    """A model error outside the basis is averaged by patterns of many LEDs and leaks through repeated ones:
    with it the design lights more LEDs; refining the chosen S-matrix rows never raises the objective."""
    clean = design_patterns(_model(n_leds=24, model_error=0.0), 6, seed=0)
    rough = _model(n_leds=24, model_error=0.3)
    assert design_patterns(rough, 6, seed=0).leds_on.mean() > clean.leds_on.mean()
    _, sub = select_rows(rough, multiplexing_patterns(24), 6)
    refined = design_patterns(rough, 6, seed=0, start=sub.patterns)
    assert refined.objective < sub.objective and refined.history[0] == pytest.approx(sub.objective)


def test_the_design_is_seeded():
    model = _model(n_leds=20)
    a = design_patterns(model, 5, seed=4)
    b = design_patterns(model, 5, seed=4)
    np.testing.assert_array_equal(a.patterns, b.patterns)
    assert a.objective == b.objective
    np.testing.assert_array_equal(random_patterns(20, 5, seed=1), random_patterns(20, 5, seed=1))


def test_select_rows_picks_distinct_candidates_that_lower_the_objective():
    model = _model(n_leds=16)
    S = multiplexing_patterns(model.n_leds)
    rows, design = select_rows(model, S, 6)
    assert len(set(rows.tolist())) == 6
    np.testing.assert_array_equal(design.patterns, S[rows])
    assert np.all(np.diff(design.history) < 0)
    with pytest.raises(ValueError, match="m must lie in 1..19"):
        select_rows(model, S, 20)


def test_the_operator_recovers_data_in_the_basis_span():
    model = _model()
    patterns = design_patterns(model, 4, seed=0).patterns
    op = pattern_operator(model, patterns, dtype=np.float64)
    assert op.method == "direct" and op.n_meas == model.n_views * 4 and op.n_out == model.U.shape[0]
    c = np.random.default_rng(0).normal(size=(model.k, 3)) * np.sqrt(model.prior)[:, None]
    B = model.U @ c
    y = np.einsum("pl,vld->vpd", patterns.astype(float), B.reshape(model.n_views, model.n_leds, 3))
    B_hat = apply(op, y.reshape(-1, 3))
    assert np.linalg.norm(B_hat - B) < 0.05 * np.linalg.norm(B)              # only the prior's shrinkage


def test_bad_patterns_are_refused():
    model = _model()
    with pytest.raises(ValueError, match="switches no LED on"):
        expected_error(model, np.zeros((2, model.n_leds)))
    with pytest.raises(ValueError, match="binary"):
        expected_error(model, np.full((2, model.n_leds), 0.5))
    with pytest.raises(ValueError, match="not a multiple of n_leds"):
        PatternModel(model.U[:-1], model.sigma, model.n_leds)


def test_one_exposure_per_view_keeps_the_patterns_below_saturation():
    """With one exposure per view metered on the median pattern, patterns brighter than 1 / fill of the median
    saturate. Designed for it, no pattern does, and its predicted error under that exposure beats the
    per-image design's, which lights patterns that clip."""
    single = _model(n_leds=24, single_exposure=True)
    per_image = _model(n_leds=24)
    m = 6
    own = design_patterns(single, m, seed=0, start=select_rows(single, multiplexing_patterns(24), m)[1].patterns)
    other = design_patterns(per_image, m, seed=0, start=select_rows(per_image, multiplexing_patterns(24), m)[1].patterns)

    def saturating(patterns):
        x = single.radiance @ patterns.T.astype(float)                              # (V, m)
        return int(np.sum(x > single.meter(x, axis=1) / single.noise.fill * (1 + 1e-9)))

    assert saturating(own.patterns) == 0
    assert saturating(other.patterns) > 0
    assert own.objective < expected_error(single, other.patterns).objective
    assert own.objective == pytest.approx(expected_error(single, own.patterns).objective, rel=1e-9)
    assert np.all(np.diff(own.history[1:]) <= 1e-9 * own.history[0])               # refinement never worse


@pytest.mark.parametrize("single_exposure", [False, True])
@pytest.mark.parametrize("n_others", [0, 3])
def test_a_flip_scan_scores_every_flipped_pattern_as_woodbury_does(single_exposure, n_others):
    """The terms a scan shares (`_FlipTerms`) give the gains `_candidate_gains` gives each
    flipped pattern formed explicitly; a flip that would empty the pattern is -inf."""
    from btfcore.acquisition.illumination_patterns import _candidate_gains, _flip_scan, _others

    model = _model(k=6, seed=4, single_exposure=single_exposure)
    rng = np.random.default_rng(5)
    others = (rng.random((n_others, model.n_leds)) < 0.4).astype(np.uint8)
    others[:, 0] = 1                                                            # none empty
    o, G = _others(model, others), model.gram
    for pattern in ((rng.random(model.n_leds) < 0.5).astype(np.uint8), np.eye(model.n_leds, dtype=np.uint8)[3]):
        flipped = np.repeat(pattern[None], model.n_leds, axis=0) ^ np.eye(model.n_leds, dtype=np.uint8)
        full = flipped.sum(axis=1) > 0
        expected = np.full(model.n_leds, -np.inf)
        expected[full] = _candidate_gains(model, o, G, flipped[full])
        np.testing.assert_allclose(_flip_scan(model, o, G, pattern), expected, rtol=1e-9)
