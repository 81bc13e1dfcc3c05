"""Shared fixtures: one real Prefect server and one real Dask LocalCluster per session."""

from __future__ import annotations

import os

import pytest

from tasks.shared_data import shared_data_dir


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
