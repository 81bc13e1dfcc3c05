"""`btf build-db` end to end on a simulated, ingested tiny database (issue 4)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from tasks.model import ModelSettings, build_database, discover, with_k

#: Small bases so that the tests stay fast; the thesis' defaults are capped by the tiny data anyway.
SMALL = with_k(ModelSettings(k_class=48, k_global=48, als_iterations=8), log_y=24, abtf_log_y=16, als=6)


@pytest.fixture(scope="module")
def database(tmp_path_factory, dask_client) -> Path:
    """Six classes x four materials on the tiny dome, ingested: the leave-one-out database of issue 4."""
    from tasks.ingest import ingest_capture
    from tasks.simulate import SimulationConfig, simulate_database

    root = tmp_path_factory.mktemp("model-db")
    captures = simulate_database(SimulationConfig(device="tiny", n_materials=24, seed=4, n_turntable=1),
                                 root / "captures", dask_client).stores
    for capture in captures:
        ingest_capture(capture, root / "btf" / Path(capture).name, dask_client)
    return root / "btf"


@pytest.fixture(scope="module")
def built(database, tmp_path_factory, dask_client) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("model")
    return out, build_database(database, out, dask_client, settings=SMALL, ks=(2, 4, 8, 16, 24))


def test_table_1_trends_on_a_leave_one_out_database(built):
    _, summary = built
    assert len(summary["materials"]) == 24 and len(summary["table_1"]) == 6
    for r in summary["leave_one_out"]:
        for key in ("class_basis", "global_basis"):
            assert np.all(np.diff(r[key]) <= 1e-12), (r["material"], key)          # falls as k grows
        abtf = [e for e in r["abtf_class_basis"] if e is not None]               # k = 1, 2, 4, ..., patches blended
        assert abtf[-1] < abtf[0], r["material"]
    # per-class bases project held-out materials of their class better than the global basis of that size
    cells = [(cls, k) for cls in summary["table_1"] for k in summary["ks"]]
    wins = [summary["table_1"][cls][f"class_{k}"] < summary["table_1"][cls][f"global_{k}"] for cls, k in cells]
    assert sum(wins) >= 0.8 * len(wins), summary["table_1"]


def test_store_holds_every_basis_with_orthonormal_columns(built):
    out, summary = built
    group = zarr.open_group(str(out / "model.zarr"), mode="r")
    assert group.attrs["schema"] == "btf-model" and len(group.attrs["materials"]) == 24
    for where in ("materials/000-leather/log_y", "classes/leather/log_y", "classes/leather/abtf_log_y",
                  "global/log_y", "global/u_y", "global/als"):
        U, sigma = group[where]["U"][...], group[where]["sigma"][...]
        np.testing.assert_allclose(U.T @ U, np.eye(U.shape[1]), atol=1e-8, err_msg=where)
        assert np.all(np.diff(sigma) <= 1e-9 * sigma[0]) and group[where].attrs["key"]
    n_lv = summary["materials"][0]["n_lv"]
    assert group["classes/leather/abtf_log_y/U"].shape[0] == 9 * n_lv       # 3 x 3 patches of every light/view pair
    assert summary["fits"][0]["bases"]["als"] == "als"


def test_adding_a_material_recomputes_only_what_depends_on_it(built, database, tmp_path, dask_client):
    out, _ = built
    db = tmp_path / "db"
    shutil.copytree(database, db)
    extra = db / "024-extra-leather.zarr"
    shutil.copytree(db / "000-leather.zarr", extra)                   # a new leather (same data, new id)
    group = zarr.open_group(str(extra), mode="r+")
    group.attrs["material"] = {"material_id": "024-extra-leather", "class": "leather"}
    model = tmp_path / "model"
    shutil.copytree(out, model)
    before = zarr.open_group(str(model / "model.zarr"), mode="r")
    keys = {w: before[w].attrs["key"] for w in ("classes/cloth/log_y", "classes/leather/log_y", "global/log_y",
                                                "materials/001-cloth/log_y")}
    summary = build_database(db, model, dask_client, settings=SMALL, ks=(2, 4))
    reused = [f for f in summary["fits"] if set(f["bases"].values()) == {"reused"}]
    assert len(reused) == 24 and len(summary["fits"]) == 25
    after = zarr.open_group(str(model / "model.zarr"), mode="r")
    assert after["classes/cloth/log_y"].attrs["key"] == keys["classes/cloth/log_y"]
    assert after["materials/001-cloth/log_y"].attrs["key"] == keys["materials/001-cloth/log_y"]
    assert after["classes/leather/log_y"].attrs["key"] != keys["classes/leather/log_y"]
    assert after["global/log_y"].attrs["key"] != keys["global/log_y"]


def test_bad_databases_name_every_problem(database, tmp_path):
    db = tmp_path / "db"
    for name in ("000-leather", "001-cloth", "006-leather"):
        shutil.copytree(database / f"{name}.zarr", db / f"{name}.zarr")
    unfinished = zarr.open_group(str(db / "006-leather.zarr"), mode="r+")
    unfinished.attrs["complete"] = False
    with pytest.raises(ValueError) as err:
        discover(db)
    text = str(err.value)
    assert "006-leather.zarr: the ingest is unfinished" in text
    assert "class 'cloth' has 1 material" in text and "class 'leather' has 1 material" in text
    other = zarr.open_group(str(db / "001-cloth.zarr"), mode="r+")
    light = other["light_dir"][...]
    light[5] = [0.0, 0.0, 1.0]
    other["light_dir"][...] = light
    with pytest.raises(ValueError, match=r"001-cloth.zarr: another light/view sampling \(light_dir/view_dir\[5\]"):
        discover(db)


def test_cli_builds_the_report(run_btf, database, tmp_path):
    db = tmp_path / "db"
    for name in ("000-leather", "006-leather", "001-cloth", "007-cloth"):
        shutil.copytree(database / f"{name}.zarr", db / f"{name}.zarr")
    code, stdout, stderr = run_btf("build-db", db, "--out", tmp_path / "model", "--k-log-y", "12",
                                   "--k-chroma", "3", "--k-merged", "20")
    assert code == 0, stderr[-3000:]
    result = json.loads(stdout)
    report = json.loads((tmp_path / "model" / "report.json").read_text())
    assert result["trends"]["error_falls_with_k"] and set(report["table_1"]) == {"leather", "cloth"}
    html = (tmp_path / "model" / "report.html").read_text()
    assert "Thesis Table 1" in html and "model_spectra.png" in html
    assert (tmp_path / "model" / "report_files" / "model_000-leather_abrdf.png").exists()
    code, _, stderr = run_btf("build-db", db, "--out", tmp_path / "m2", "--k-log-y", "5000")
    assert code == 2 and "k = 5000" in stderr and "exceeds what the data allows" in stderr


def test_nan_in_a_btf_names_the_store_and_the_index(database, tmp_path, dask_client):
    db = tmp_path / "db"
    for name in ("000-leather", "006-leather", "001-cloth", "007-cloth"):
        shutil.copytree(database / f"{name}.zarr", db / f"{name}.zarr")
    btf = zarr.open_group(str(db / "007-cloth.zarr"), mode="r+")["btf"]
    band = btf[:, 0:2]
    band[3, 1, 5, 0] = np.nan
    btf[:, 0:2] = band
    with pytest.raises(ValueError, match=r"007-cloth.zarr: log_y basis: .*NaN") as err:
        build_database(db, tmp_path / "model", dask_client, settings=SMALL)
    assert "[3," in str(err.value) or "index" in str(err.value), str(err.value)


def test_scheduled_build_is_a_cron_deployment_and_needs_a_server(monkeypatch, capsys):
    from flows.cli import main
    from flows.schedule import build_db_deployment

    deployment = build_db_deployment("db", "model", "0 3 * * *", cluster="infra/local.yaml")
    assert [s.schedule.cron for s in deployment.schedules] == ["0 3 * * *"]
    assert deployment.parameters == {"db": "db", "out": "model", "cluster": "infra/local.yaml", "classes": None}
    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    assert main(["schedule", "build-db", "db", "--out", "model", "--cron", "0 3 * * *"]) == 3
    assert "set PREFECT_API_URL to a running server" in capsys.readouterr().err


def test_two_stores_of_one_material_id_are_named_before_any_fit(database, tmp_path):
    """A copy of a store under another file name keeps its material id: build-db names both stores
    instead of failing later in the leave-one-out merges (issue 19, found by the kill matrix)."""
    db = tmp_path / "db"
    for name in ("000-leather", "006-leather", "001-cloth", "007-cloth"):
        shutil.copytree(database / f"{name}.zarr", db / f"{name}.zarr")
    shutil.copytree(database / "000-leather.zarr", db / "000-leather-again.zarr")
    with pytest.raises(ValueError) as err:
        discover(db)
    text = str(err.value)
    assert "material_id '000-leather' is shared by 2 stores (000-leather-again.zarr, 000-leather.zarr)" in text, text
    assert "1 problem(s)" in text and "give each store its own file name and material id" in text
