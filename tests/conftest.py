"""Shared fixtures: the real sample at ../shared/data, skipped cleanly when absent."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SAMPLE = SHARED_DATA / "sample_dataset"
USS_BENCH = SHARED_DATA / "uss_characterisation"


@pytest.fixture(scope="session")
def sample_dir() -> Path:
    if not (SAMPLE / "office").is_dir():
        pytest.skip(f"real sample not found at {SAMPLE} (it lives in ../shared/data beside the repo)")
    return SAMPLE


@pytest.fixture(scope="session")
def sample_recording(sample_dir):
    from virus_nerf.data.ethz import load_recording

    return load_recording(sample_dir, "office")


@pytest.fixture(scope="session")
def tiny_office(tmp_path_factory) -> Path:
    """A 3 s simulated office drive at quarter resolution, shared read-only by the trainer tests."""
    from virus_nerf.sim.command import simulate

    out = tmp_path_factory.mktemp("sim") / "office_data"
    simulate(scene="office", out=out, seed=3, duration=3.0, resolution_scale=0.25)
    return out


@pytest.fixture(scope="session")
def uss_bench_dir() -> Path:
    if not USS_BENCH.is_dir():
        pytest.skip(f"USS bench data not found at {USS_BENCH}")
    return USS_BENCH


@pytest.fixture(scope="session", autouse=True)
def _frame_cache_in_tmp(tmp_path_factory):
    """Decoded-frame cache of the test session in a temporary folder, not the user's ~/.cache."""
    import os

    old = os.environ.get("VIRUS_NERF_CACHE_DIR")
    os.environ["VIRUS_NERF_CACHE_DIR"] = str(tmp_path_factory.mktemp("frame_cache"))
    yield
    if old is None:
        os.environ.pop("VIRUS_NERF_CACHE_DIR", None)
    else:
        os.environ["VIRUS_NERF_CACHE_DIR"] = old


SIMULATED_RUN_FIXTURES = {"tiny_office", "sim_root", "tiny"}  # fixtures that simulate a drive


def pytest_collection_modifyitems(config, items):
    """Mark as `slow` every test that simulates a drive or trains on one (directly or through a
    fixture built on `tiny_office`), so `pytest -m "not slow"` is a quick loop over the rest."""
    for item in items:
        if SIMULATED_RUN_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)
