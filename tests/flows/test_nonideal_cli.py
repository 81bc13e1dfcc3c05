"""``--non-ideal`` of ``btf simulate`` and ``btf evaluate acquisition``: a bad spec is refused before anything starts,
naming the option and the choices; a good one reaches the config."""

from __future__ import annotations

import pytest


@pytest.mark.parametrize("spec,msg", [("fancy", "--non-ideal fancy: 'fancy' is no preset; give one of ideal, realistic"),
                                      ("realistic,led_drift=2", "led_drift must be a number in [0, 0.5], got 2.0"),
                                      ("gain=3", "unknown dome non-ideality 'gain'; choose from led_drift")])
@pytest.mark.parametrize("command", ["simulate", "evaluate"])
def test_bad_specs_are_refused(command, spec, msg, tmp_path, capsys):
    from flows.cli import EXIT_BAD_INPUT, main

    argv = (["simulate", "--out", str(tmp_path / "db")] if command == "simulate" else
            ["evaluate", "acquisition", "--db", str(tmp_path / "db"), "--out", str(tmp_path / "o"),
             "--report", str(tmp_path / "report.json")])
    assert main([*argv, "--non-ideal", spec]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert f"btf {command}: " in err and msg in err and "Traceback" not in err
    assert not (tmp_path / "db").exists() and not (tmp_path / "o").exists()


def test_a_spec_reaches_the_configs():
    import argparse

    from btfcore.simulate.nonideal import PRESETS
    from flows.cli import _evaluation_config, _simulation_config

    args = argparse.Namespace(db="d", out="o", eval_device="tiny", eval_turntable=1, eval_texture=12,
                              eval_materials_per_class=2, eval_seed=0, eval_render=0,
                              no_adaptive=True, adaptive_select="committee", adaptive_rows="fused",
                              adaptive_predictor="posterior",
                              non_ideal="realistic,hot_pixel_fraction=0")
    config = _evaluation_config(args)
    assert config.non_ideal.hot_pixel_fraction == 0 and config.non_ideal.single_gain_db == 10.0
    assert not config.adaptive
    args = argparse.Namespace(device="tiny", materials=1, seed=0, illumination="both", bayer=None, texture_size=None,
                              turntable=1, psf_sigma=0.0, camera_scale=1, classes=None, plan=None,
                              non_ideal="realistic")
    assert _simulation_config(args).non_ideal == PRESETS["realistic"]
