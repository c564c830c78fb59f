"""Shared fixtures: the real data folder beside the checkout, and small worlds built in code."""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
sys.path.insert(0, str(Path(__file__).resolve().parent))


#: the state folder this process made in pytest_configure, under "path" (absent: it was given one, as xdist's
#: workers are)
_MADE_STATE_HOME: dict[str, str] = {}


def pytest_configure(config: pytest.Config) -> None:
    """`posegrid run` keeps a run's state under $XDG_STATE_HOME by default: point it, for this session and the
    processes it starts, at a temporary folder, so no test writes into the user's home."""
    if "POSEGRID_TEST_STATE_HOME" not in os.environ:
        _MADE_STATE_HOME["path"] = tempfile.mkdtemp(prefix="posegrid-state-")
        os.environ["POSEGRID_TEST_STATE_HOME"] = _MADE_STATE_HOME["path"]
    os.environ["XDG_STATE_HOME"] = os.environ["POSEGRID_TEST_STATE_HOME"]


def pytest_unconfigure(config: pytest.Config) -> None:
    """Remove the state folder pytest_configure made (in the process that made it: the session's, not a worker's),
    so a test run leaves nothing in the temporary folder."""
    made = _MADE_STATE_HOME.pop("path", None)
    if made is not None:
        shutil.rmtree(made, ignore_errors=True)
        os.environ.pop("POSEGRID_TEST_STATE_HOME", None)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The files that hold a test marked slow first, whole and each in its order (a file's module fixtures are
    set up once): xdist's workers then end on short tests and finish together, instead of one idling while the
    other runs a late long one."""
    slow_files = {item.path for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: item.path not in slow_files)


#: the test files whose tests start mappers (processes of their own, or through `posegrid run`)
STARTS_MAPPERS = {
    "test_api.py",
    "test_api_hardening.py",
    "test_hostile_peers.py",
    "test_output_paths.py",
    "test_persist.py",
    "test_persist_store.py",
    "test_pipeline.py",
    "test_pipeline_zenoh.py",
    "test_ros2.py",
    "test_ros2_bridge.py",
    "test_security.py",
    "test_supervise.py",
    "test_viewer.py",
}


@pytest.fixture(scope="session")
def fusion_kernels() -> None:
    """The fusion kernels a mapper loads as it starts, compiled (or loaded from numba's cache) in this test process
    first. On a fresh clone they take 30-60 s to compile on a busy 2-core machine; a mapper that a test starts would
    spend that before it says it is up, which the tests wait 60 s for, and a mapper stopped mid-compile keeps none of
    it. Compiled here (under mapping.jit's lock, so xdist's workers share the work), every mapper loads them."""
    from mapping.fusion import FusionThreads
    from mapping.grid import TILE_SIZE
    from mapping.sensor_model import SensorModel
    from services.state.shard import warm_fusion

    warm_fusion(SensorModel(), TILE_SIZE, FusionThreads(2))  # (a mapper on threads warms a lone scan in parts too)


@pytest.fixture(autouse=True)
def _fusion_kernels_before_mappers(request: pytest.FixtureRequest) -> None:
    """:func:`fusion_kernels` before the first test of a file that starts mappers (:data:`STARTS_MAPPERS`)."""
    if request.node.path.name in STARTS_MAPPERS:
        request.getfixturevalue("fusion_kernels")


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared real-data folder; tests that need it skip when it is absent (a user's fresh clone)."""
    if not DATA.is_dir():
        pytest.skip(f"real data folder {DATA} is absent (it sits beside the checkout in CI as ../shared/data)")
    return DATA


def shared_file(*parts: str) -> Path:
    """A file of the shared real-data folder (parts joined below it); skips the calling test, with the reason,
    when the file is absent."""
    path = DATA.joinpath(*parts)
    if not path.is_file():
        pytest.skip(f"real data {path} is absent (../shared/data sits beside the checkout in CI, not in a fresh clone)")
    return path
