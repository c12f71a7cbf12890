"""Shared pytest fixtures: where the real RGB-D fixtures live, slow-test switch."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _find_real_data() -> Path | None:
    env = os.environ.get("NEURNCD_REAL_DATA")
    candidates = [Path(env)] if env else []
    # A clone sits beside shared/ (CI: fresh clone with shared/ next to it).
    for base in [REPO, *REPO.parents]:
        candidates.append(base / "shared" / "data" / "real")
    for c in candidates:
        if (c / "README.md").is_file():
            return c
    return None


@pytest.fixture(scope="session")
def real_data_dir() -> Path:
    """Folder of the real RGB-D fixtures (../shared/data/real); skips if absent."""
    path = _find_real_data()
    if path is None:
        pytest.skip("real RGB-D fixtures (shared/data/real) not found beside the repository")
    return path


@pytest.fixture(scope="session")
def esanet_key_list() -> Path:
    """The recorded ESANet R34-NBt1D state_dict key list; skips if absent."""
    path = _find_real_data()
    f = path.parent / "esanet" / "r34_nbt1d_state_dict.json" if path else None
    if f is None or not f.is_file():
        pytest.skip("shared/data/esanet/r34_nbt1d_state_dict.json not found")
    return f


def pytest_addoption(parser):
    parser.addoption("--slow", action="store_true", default=False,
                     help="also run tests marked slow")


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: long test, run with --slow (make test-all)")
    config.addinivalue_line("markers", "ros: needs rclpy and local DDS")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--slow"):
        return
    skip = pytest.mark.skip(reason="slow: run with --slow (make test-all)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
