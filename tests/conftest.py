from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("HOLEFILL_SHARED_DATA", REPO.parent / "shared" / "data"))


def pytest_report_header(config):
    import laspy
    import numba
    import pyproj
    import rasterio

    return (
        f"holefill: laspy {laspy.__version__}, numba {numba.__version__}, rasterio {rasterio.__version__} "
        f"(GDAL {rasterio.__gdal_version__}), pyproj {pyproj.__version__} (PROJ {pyproj.proj_version_str}); "
        f"shared data: {SHARED_DATA if SHARED_DATA.is_dir() else 'absent (real-data tests skipped)'}"
    )


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real surveys of ../shared/data; tests using it skip cleanly when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real survey data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def dask_client():
    """One real local Dask cluster (2 worker processes) shared by the tests that run the pipeline."""
    from distributed import Client, LocalCluster

    with (
        LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0", silence_logs=50
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


@pytest.fixture
def rng():
    import numpy as np

    return np.random.default_rng(20261123)
