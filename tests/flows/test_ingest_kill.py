"""A killed `btf ingest` resumes without redoing finished views, bit-identical to a clean run."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import zarr

from tasks.ingest import ingest_capture
from tasks.simulate import SimulationConfig, simulate_database

ROOT = Path(__file__).resolve().parents[2]


def _written(btf: Path) -> int:
    return sum(1 for _ in btf.glob("written/c/*/*"))


def test_killed_ingest_resumes_bit_identically(tmp_path, dask_client, kill_btf_when):
    # a pruned bonn-dome2 capture: 11 views of 198 brackets, slow enough to kill mid-run
    config = SimulationConfig(device="bonn-dome2", n_materials=1, seed=4, classes=("leather",),
                              n_turntable=1, texture_size=32)
    capture = simulate_database(config, tmp_path / "db", dask_client).stores[0]
    btf = tmp_path / "btf.zarr"
    args = ["ingest", capture, "--out", str(btf)]
    kill_btf_when(args, lambda: _written(btf) >= 2)
    done_before = _written(btf)
    assert 2 <= done_before < 11

    again = subprocess.run([sys.executable, "-m", "flows.cli", "--no-progress", *args], cwd=ROOT,
                           capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-3000:]
    stage = json.loads(again.stdout)["stages"]["ingest"]
    # a view counts as done only once its marker is on disk, and markers follow the data
    assert stage["views_skipped"] == done_before and stage["views_processed"] == 11 - done_before

    clean = tmp_path / "clean.zarr"
    ingest_capture(capture, clean, dask_client)
    resumed, reference = zarr.open_group(str(btf), mode="r"), zarr.open_group(str(clean), mode="r")
    np.testing.assert_array_equal(resumed["btf"][...], reference["btf"][...])
    np.testing.assert_array_equal(resumed["valid_fraction"][...], reference["valid_fraction"][...])
