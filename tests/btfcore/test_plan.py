"""Capture-plan strategies, exposure model and validation (btfcore.acquisition.plan)."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.capture.demultiplex import demultiplex_operator
from btfcore.acquisition.hadamard import multiplexing_patterns, s_matrix
from btfcore.acquisition.plan import (
    CapturePlan,
    ExposureModel,
    Shot,
    bootstrap_quadrants,
    bootstrapping_plan,
    full_single_light_plan,
    multiplexed_plan,
    sparse_multiplexed_plan,
    sparse_plan,
    validate_plan,
)
from btfcore.dome import get_device


@pytest.fixture(scope="module")
def tiny():
    return get_device("tiny")


@pytest.fixture(scope="module")
def dome2():
    return get_device("bonn-dome2")


EXPOSURE = ExposureModel(single_ms=(10.0, 144.2, 2080.1, 30000.0))


# --------------------------------------------------------------------------- strategies


@pytest.mark.parametrize("name", ["tiny", "bonn-dome2"])
def test_full_single_light_covers_every_pair_once(name):
    device = get_device(name)
    plan = full_single_light_plan(device, EXPOSURE)
    assert plan.n_shots == device.n_turn * device.n_leds
    np.testing.assert_array_equal(plan.coverage(), 1)
    assert all(s.n_leds_on == 1 and s.cameras == tuple(range(device.n_cam)) for s in plan.shots)
    assert all(s.shutter_ms == EXPOSURE.single_ms for s in plan.shots)
    assert validate_plan(plan, device) is plan


def test_sparse_plan_covers_only_the_chosen_pairs(tiny):
    pairs = np.array([[2, 5], [0, 3], [1, 0], [0, 12]])
    plan = sparse_plan(tiny, pairs, EXPOSURE)
    expected = np.zeros((tiny.n_turn, tiny.n_leds), dtype=int)
    expected[pairs[:, 0], pairs[:, 1]] = 1
    np.testing.assert_array_equal(plan.coverage(), expected)
    assert [s.turntable for s in plan.shots] == [0, 0, 1, 2]       # turntable-major order
    assert all(s.cameras == tuple(range(tiny.n_cam)) for s in plan.shots)  # all cameras always fire
    np.testing.assert_array_equal(sparse_plan(tiny, expected.astype(bool), EXPOSURE).coverage(), expected)


def test_multiplexed_patterns_are_s_matrix_rows_and_invertible(tiny, dome2):
    for device in (tiny, dome2):
        plan = multiplexed_plan(device, EXPOSURE)
        n = multiplexing_patterns(device.n_leds).shape[0]
        assert plan.n_shots == n * device.n_turn
        for t in (0, device.n_turn - 1):
            M = plan.illumination(t)
            np.testing.assert_array_equal(M, s_matrix(n)[:, : device.n_leds])
            assert np.linalg.matrix_rank(M.astype(float)) == device.n_leds
            P = demultiplex_operator(M)
            np.testing.assert_allclose(P @ M, np.eye(device.n_leds), atol=1e-9)
    assert plan.parameters["s_matrix_order"] == 199 and plan.groups() == ("S199",)


def test_multiplexed_exposure_follows_the_model(tiny):
    plan = multiplexed_plan(tiny, EXPOSURE)
    for s in plan.shots:
        assert s.shutter_ms == EXPOSURE.bracket_ms(s.n_leds_on)
        np.testing.assert_allclose(s.shutter_ms, np.maximum(np.array(EXPOSURE.single_ms) / s.n_leds_on, 0.1))


def test_sparse_multiplexed_patterns_select_rows(dome2):
    sel = np.array([[0, 0], [0, 198], [5, 17], [11, 3]])
    plan = sparse_multiplexed_plan(dome2, sel, EXPOSURE)
    M = multiplexing_patterns(dome2.n_leds)
    assert plan.n_shots == 4
    for s, (t, r) in zip(plan.shots, sel):
        assert s.turntable == t and s.leds == tuple(np.flatnonzero(M[r]).tolist())


def test_sparse_multiplexed_leds_gets_own_s_matrix_per_turntable(tiny):
    sel = np.array([[0, 1], [0, 4], [0, 7], [0, 9], [0, 11], [1, 2], [2, 3], [2, 8]])
    plan = sparse_multiplexed_plan(tiny, sel, EXPOSURE, select="leds")
    cov = plan.coverage()
    chosen = np.zeros_like(cov, dtype=bool)
    chosen[sel[:, 0], sel[:, 1]] = True
    assert np.all(cov[chosen] >= 1) and np.all(cov[~chosen] == 0)   # only the chosen pairs are ever lit
    M0 = plan.illumination(0)[:, [1, 4, 7, 9, 11]]
    np.testing.assert_array_equal(M0, s_matrix(7)[:, :5])           # 5 LEDs -> order 7
    assert np.linalg.matrix_rank(M0.astype(float)) == 5
    assert plan.illumination(1).tolist() == [[0, 0, 1] + [0] * 13]   # one LED alone: a single-light shot
    assert plan.parameters["s_matrix_order_per_turntable"] == {"0": 7, "1": 1, "2": 3}


def test_bootstrapping_specular_quadrant_is_single_light(dome2):
    sector = bootstrap_quadrants(dome2)
    assert sorted(np.bincount(sector).tolist()) == sorted([59, 45, 48, 46])
    # the preset's first 10 LEDs sit opposite the lower cameras (azimuth 180 deg, cameras at 0 deg)
    phi = np.degrees(np.arctan2(dome2.led_position[:, 1], dome2.led_position[:, 0])) % 360
    np.testing.assert_allclose(phi[:10], 180.0)
    assert np.all(sector[np.isclose(phi, 180.0)] == 0)
    plan = bootstrapping_plan(dome2, EXPOSURE)
    assert np.all(plan.coverage() >= 1)
    for s in plan.shots:
        in_sector = set(sector[list(s.leds)].tolist())
        assert len(in_sector) == 1                                    # a pattern never mixes quadrants
        if in_sector == {0}:
            assert s.n_leds_on == 1 and s.group == "q0-single" and s.shutter_ms == EXPOSURE.single_ms
        else:
            assert s.n_leds_on > 1
    np.testing.assert_array_equal(plan.coverage()[:, sector == 0], 1)
    for k in (1, 2, 3):                                                # each quadrant its own S-matrix
        leds = np.flatnonzero(sector == k)
        group = [g for g in plan.groups() if g.startswith(f"q{k}-")][0]
        M = plan.illumination(3, group)[:, leds]
        np.testing.assert_array_equal(M, multiplexing_patterns(len(leds)))
    # half-width 50 deg reproduces the thesis' order-47 S-matrices (VMV §5.1)
    plan50 = bootstrapping_plan(dome2, EXPOSURE, specular_half_width_deg=50.0)
    assert plan50.parameters["s_matrix_orders"] == {"1": 47, "2": 47, "3": 47}


def test_bootstrapping_refuses_a_surrounding_dome():
    with pytest.raises(ValueError, match="surround the sample"):
        bootstrap_quadrants(get_device("ubo-dome1"))


# --------------------------------------------------------------------------- exposure model


def test_exposure_model():
    e = ExposureModel(single_ms=(1.0, 10.0, 100.0), exponent=1.0, min_shutter_ms=0.5, measured_ms={100: (30.0,)})
    assert e.bracket_ms(1) == (1.0, 10.0, 100.0)
    assert e.bracket_ms(4) == (0.5, 2.5, 25.0)
    assert e.bracket_ms(20) == (0.5, 5.0)                 # steps below the shortest shutter merge
    assert e.bracket_ms(100) == (30.0,)                   # measured bracket wins
    assert ExposureModel(single_ms=(1.0, 10.0), exponent=0.0).bracket_ms(50) == (1.0, 10.0)
    assert ExposureModel.from_dict(e.to_dict()) == e
    with pytest.raises(ValueError, match="strictly increasing"):
        ExposureModel(single_ms=(10.0, 1.0))
    with pytest.raises(ValueError, match="at least one LED"):
        e.bracket_ms(0)


# --------------------------------------------------------------------------- validation


def _plan(shots, n_turn=3, n_cam=4, n_leds=16):
    return CapturePlan(device="tiny", n_turn=n_turn, n_cam=n_cam, n_leds=n_leds,
                       turntable_angle_deg=(0.0, 120.0, 240.0)[:n_turn], strategy="custom", shots=shots)


@pytest.mark.parametrize("bad, match", [
    (Shot(0, (16,), (0,), (1.0,)), r"shot 1 switches on LED\(s\) \[16\]"),
    (Shot(0, (3,), (0, 4), (1.0,)), r"shot 1 uses camera\(s\) \[4\]"),
    (Shot(3, (3,), (0,), (1.0,)), r"shot 1 uses turntable position 3"),
    (Shot(-1, (3,), (0,), (1.0,)), r"shot 1 uses turntable position -1"),
])
def test_validation_names_shot_and_id(tiny, bad, match):
    good = Shot(0, (0,), (0, 1, 2, 3), (1.0,))
    with pytest.raises(ValueError, match=match):
        _plan([good, bad])
    if bad.turntable >= 0:  # a plan made for a bigger device fails validation against the tiny one
        big = CapturePlan(device="big", n_turn=12, n_cam=11, n_leds=198, turntable_angle_deg=tuple(range(12)),
                          strategy="custom", shots=(good, bad))
        with pytest.raises(ValueError, match=r"plan for device 'tiny': " + match):
            validate_plan(big, tiny)


def test_validation_turntable_angles(tiny):
    plan = CapturePlan(device="tiny", n_turn=3, n_cam=4, n_leds=16, turntable_angle_deg=(0.0, 90.0, 180.0),
                       strategy="custom", shots=(Shot(0, (0,), (0,), (1.0,)),))
    with pytest.raises(ValueError, match="turntable angles"):
        validate_plan(plan, tiny)


@pytest.mark.parametrize("kwargs, match", [
    (dict(leds=()), "Shot.leds is empty"),
    (dict(leds=(1, 1)), "lists an id twice"),
    (dict(shutter_ms=(5.0, 1.0)), "strictly increasing"),
    (dict(shutter_ms=(0.0,)), "> 0 ms"),
    (dict(cameras=()), "Shot.cameras is empty"),
])
def test_shot_rejects_bad_fields(kwargs, match):
    base = dict(turntable=0, leds=(1,), cameras=(0,), shutter_ms=(1.0,))
    with pytest.raises(ValueError, match=match):
        Shot(**{**base, **kwargs})


@pytest.mark.parametrize("selection, match", [
    (np.array([[0, 16]]), r"selection pair 0: LED 16 is out of range 0..15"),
    (np.array([[0, 1], [3, 2]]), r"selection pair 1: turntable 3 is out of range 0..2"),
    (np.array([[0, 1], [1, 2], [0, 1]]), r"selection pair 0 .* more than once"),
    (np.zeros((2, 16), dtype=bool), r"mask must have shape \(3, 16\)"),
    (np.array([1, 2]), r"\(n, 2\) array"),
])
def test_sparse_selection_errors(tiny, selection, match):
    with pytest.raises(ValueError, match=match):
        sparse_plan(tiny, selection, EXPOSURE)


def test_unknown_cameras_and_select(tiny):
    with pytest.raises(ValueError, match=r"cameras \[7\] are not cameras of device 'tiny'"):
        full_single_light_plan(tiny, cameras=[0, 7])
    with pytest.raises(ValueError, match="select must be"):
        sparse_multiplexed_plan(tiny, np.array([[0, 1]]), select="rows")


def test_dict_round_trip(dome2):
    plan = bootstrapping_plan(dome2, EXPOSURE)
    again = CapturePlan.from_dict(plan.to_dict())
    assert again.to_dict() == plan.to_dict()
    assert again.shots == plan.shots


# --------------------------------------------------------------------------- predicted multiplexing gain


def _simulated_gain(plan, fw: float, sr: float, fraction: float, seed: int = 7, n_px: int = 20000) -> float:
    """Measured r.m.s. noise ratio single-light / demultiplexed, turntable 0, one bracket step per pattern."""
    from btfcore.acquisition.noise import SensorNoise, expose
    from btfcore.acquisition.plan import _exposure_gain_of

    rng = np.random.default_rng(seed)
    noise = SensorNoise(full_well_e=fw, read_noise_e=sr, fill=1.0)
    x = fraction * fw
    t_ref = max(plan.parameters["exposure"]["single_ms"])
    shots = [s for s in plan.shots if s.turntable == 0]
    M = plan.illumination(0)
    g = np.array([x * _exposure_gain_of(s.n_leds_on, s.shutter_ms, x, t_ref, fw)[0] for s in shots])
    measured = expose(np.repeat((M @ np.ones(M.shape[1]))[:, None], n_px, axis=1), g, noise, rng, np.float64)
    demux = demultiplex_operator(M) @ measured
    single = expose(np.ones((M.shape[1], n_px)), np.full(M.shape[1], x), noise, rng, np.float64)
    return float(np.sqrt(np.mean((single - 1.0) ** 2) / np.mean((demux - 1.0) ** 2)))


@pytest.mark.parametrize("exponent, fraction, loses", [(1.0, 0.8, True), (0.0, 0.8, True), (0.0, 0.0005, False)])
def test_multiplexing_gain_matches_a_simulated_capture(tiny, exponent, fraction, loses):
    from btfcore.acquisition.plan import multiplexing_gain

    plan = multiplexed_plan(tiny, ExposureModel(single_ms=(10.0, 100.0, 1000.0), exponent=exponent))
    fw, sr = tiny.sensor.full_well_e, tiny.sensor.read_noise_e
    rep = multiplexing_gain(plan, full_well_e=fw, read_noise_e=sr, signal_fraction=fraction)
    assert rep["loses"] is loses and (rep["gain"] < 1) is loses
    assert rep["gain"] == pytest.approx(_simulated_gain(plan, fw, sr, fraction), rel=0.03)
    assert set(rep["groups"]) == {"S19"} and rep["saturated_patterns"] == 0


def test_multiplexing_gain_equals_noise_gain_at_equal_exposure(tiny):
    from btfcore.acquisition.plan import multiplexing_gain
    from btfcore.capture.demultiplex import noise_gain

    plan = multiplexed_plan(tiny, ExposureModel(single_ms=(1000.0,), exponent=0.0))
    x = 0.01 * tiny.sensor.full_well_e
    want = noise_gain(multiplexing_patterns(tiny.n_leds), np.full((tiny.n_leds, 1), x),
                      read_noise=tiny.sensor.read_noise_e)
    rep = multiplexing_gain(plan, full_well_e=tiny.sensor.full_well_e, read_noise_e=tiny.sensor.read_noise_e,
                            signal_fraction=0.01)
    assert rep["gain"] == pytest.approx(want, rel=1e-12)
    # a single-light plan has nothing to demultiplex; a bracket step that saturates is counted
    assert multiplexing_gain(full_single_light_plan(tiny), full_well_e=5500.0, read_noise_e=3.0) is None
    rep = multiplexing_gain(plan, full_well_e=tiny.sensor.full_well_e, read_noise_e=3.0, signal_fraction=0.8)
    assert rep["saturated_patterns"] == plan.n_shots


def test_multiplexing_gain_rejects_bad_inputs(tiny):
    from btfcore.acquisition.plan import multiplexing_gain

    plan = multiplexed_plan(tiny)
    with pytest.raises(ValueError, match="signal_fraction must lie in"):
        multiplexing_gain(plan, full_well_e=5500.0, read_noise_e=3.0, signal_fraction=1.5)
    with pytest.raises(ValueError, match="full_well_e must be finite"):
        multiplexing_gain(plan, full_well_e=0.0, read_noise_e=3.0)
    custom = CapturePlan.from_dict({**plan.to_dict(), "parameters": {}})
    with pytest.raises(ValueError, match="no parameters.exposure.single_ms"):
        multiplexing_gain(custom, full_well_e=5500.0, read_noise_e=3.0)
    assert multiplexing_gain(custom, full_well_e=5500.0, read_noise_e=3.0, single_ms=(1000.0,))["loses"]
