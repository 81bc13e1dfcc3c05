"""Shared fixtures: one real Prefect server and one real Dask LocalCluster per session."""

from __future__ import annotations

import os
import tempfile

import pytest

from tasks.shared_data import shared_data_dir

# A developer's running `btf server` (its state file under $XDG_STATE_HOME) must not serve the
# tests' runs: every test and every `btf` subprocess sees a private, empty state folder.
os.environ["XDG_STATE_HOME"] = tempfile.mkdtemp(prefix="btf-test-state-")


def pytest_collection_modifyitems(config, items):
    if shared_data_dir() is not None:
        return
    skip = pytest.mark.skip(reason="../shared/data is absent (set BTF_SHARED_DATA to its folder to run this test)")
    for item in items:
        if "shared_data" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def runtime_session():
    """(profile, prefect_url, client) of the default profile: a real temporary Prefect
    server shared with a real 2-worker LocalCluster."""
    from flows.runtime import runtime

    with runtime() as rt:
        yield rt


@pytest.fixture(scope="session")
def dask_client(runtime_session):
    return runtime_session[2]


@pytest.fixture(scope="session")
def tiny_database(tmp_path_factory, runtime_session):
    """A two-material `tiny` database simulated once through the real flow."""
    from flows.simulate import simulate_flow
    from tasks.simulate import SimulationConfig

    out = tmp_path_factory.mktemp("tiny-db")
    config = SimulationConfig(device="tiny", n_materials=2, seed=7, classes=("stone", "metal"))
    report = simulate_flow(config, str(out), runtime_session[2].scheduler.address, progress=False)
    return config, out, report


@pytest.fixture(scope="session")
def tiny_btf(tmp_path_factory, dask_client):
    """A tiny capture (one turntable position: 4 views x 16 LEDs, 8x8 texels) ingested to a BTF store."""
    from tasks.ingest import ingest_capture
    from tasks.simulate import SimulationConfig, simulate_database

    out = tmp_path_factory.mktemp("tiny-btf")
    config = SimulationConfig(device="tiny", n_materials=1, seed=8, classes=("leather",), n_turntable=1,
                              texture_size=8)
    capture = simulate_database(config, out, dask_client).stores[0]
    ingest_capture(capture, out / "btf.zarr", dask_client)
    return out / "btf.zarr"


@pytest.fixture(scope="session")
def tiny_btf_nonideal(tmp_path_factory, dask_client):
    """``tiny_btf``'s capture under the "realistic" dome that is not ideal (LED drift, 10 dB single-light gain,
    registration error, hot pixels; docs/simulator-physics.md, "A dome that is not ideal"), ingested."""
    from btfcore.simulate.nonideal import PRESETS
    from tasks.ingest import ingest_capture
    from tasks.simulate import SimulationConfig, simulate_database

    out = tmp_path_factory.mktemp("tiny-btf-nonideal")
    config = SimulationConfig(device="tiny", n_materials=1, seed=8, classes=("leather",), n_turntable=1,
                              texture_size=8, non_ideal=PRESETS["realistic"])
    capture = simulate_database(config, out, dask_client).stores[0]
    ingest_capture(capture, out / "btf.zarr", dask_client)
    return out / "btf.zarr"


_CFA_CODES = {"R": 0, "G": 1, "B": 2}


def _write_dng(path, cfa, pattern: str, exposure_s: float, black: int = 64, white: int = 4095) -> None:
    """A minimal CFA DNG (DNG 1.4 tags) that LibRaw reads, written by tifffile."""
    import tifffile

    tags = [
        (33421, "H", 2, (2, 2), False),                                   # CFARepeatPatternDim
        (33422, "B", 4, bytes(_CFA_CODES[c] for c in pattern), False),    # CFAPattern
        (33434, "2I", 1, (int(round(exposure_s * 1e6)), 1_000_000), False),  # ExposureTime
        (50706, "B", 4, (1, 4, 0, 0), False),                             # DNGVersion
        (50708, "s", 0, "btf-pipeline test camera", False),               # UniqueCameraModel
        (50714, "I", 1, (black,), False),                                 # BlackLevel
        (50717, "I", 1, (white,), False),                                 # WhiteLevel
        (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), False),  # ColorMatrix1
        (50778, "H", 1, (21,), False),                                    # CalibrationIlluminant1 D65
    ]
    tifffile.imwrite(path, cfa, photometric=32803, extratags=tags, subfiletype=0)


@pytest.fixture(scope="session")
def write_dng():
    """``write_dng(path, cfa, pattern, exposure_s)``: a real DNG file for LibRaw."""
    return _write_dng


def _kill_btf_when(args: list[str], ready, timeout: float = 240.0) -> None:
    """Run ``python -m flows.cli ARGS`` and SIGKILL its whole process group (the CLI, its
    Prefect server and its Dask workers) as soon as ``ready()`` is true."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    proc = subprocess.Popen([sys.executable, "-m", "flows.cli", "--no-progress", *args],
                            cwd=Path(__file__).resolve().parents[1], start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + timeout
        while not ready() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert proc.poll() is None, "the run finished before it could be killed"
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)


@pytest.fixture(scope="session")
def kill_btf_when():
    """``kill_btf_when(args, ready)``: a real mid-run SIGKILL of a `btf` command."""
    return _kill_btf_when


class _ChunkFiles:
    """The chunk files of a Zarr v3 store on disk, to damage them as a failing disk or copy would."""

    @staticmethod
    def path(store, array: str, chunk: tuple[int, ...]):
        """The file of chunk ``chunk`` of array ``array`` (``/``-separated) in ``store``."""
        from pathlib import Path

        return Path(store).joinpath(*array.split("/"), "c", *map(str, chunk))

    @staticmethod
    def flip_byte(path, offset: int = 7) -> None:
        """XOR one byte of a chunk file (the data, not the checksum at its end)."""
        from pathlib import Path

        data = bytearray(Path(path).read_bytes())
        data[offset] ^= 0x5A
        Path(path).write_bytes(bytes(data))


@pytest.fixture(scope="session")
def chunk_files():
    """``chunk_files.path(store, array, chunk)`` and ``chunk_files.flip_byte(path)``."""
    return _ChunkFiles
