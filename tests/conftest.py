"""Shared fixtures: the real data folder beside the checkout, and small worlds built in code."""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
sys.path.insert(0, str(Path(__file__).resolve().parent))


def pytest_configure(config: pytest.Config) -> None:
    """`posegrid run` keeps a run's state under $XDG_STATE_HOME by default: point it, for this session and the
    processes it starts, at a temporary folder, so no test writes into the user's home."""
    if "POSEGRID_TEST_STATE_HOME" not in os.environ:
        os.environ["POSEGRID_TEST_STATE_HOME"] = tempfile.mkdtemp(prefix="posegrid-state-")
    os.environ["XDG_STATE_HOME"] = os.environ["POSEGRID_TEST_STATE_HOME"]


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
