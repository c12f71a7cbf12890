"""Shared pytest fixtures: where the real RGB-D fixtures live, slow-test switch."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


DATA = REPO / "test" / "data"
"""Fixtures shipped with the repository (see test/data/README.md for sources and licences)."""


@pytest.fixture(scope="session")
def real_data_dir() -> Path:
    """Folder of the small real RGB-D sequences (test/data/real)."""
    path = DATA / "real"
    assert (path / "README.md").is_file(), f"{path} is missing: the repository is incomplete"
    return path


@pytest.fixture(scope="session")
def esanet_key_list() -> Path:
    """The recorded ESANet R34-NBt1D state_dict key list (test/data/esanet)."""
    path = DATA / "esanet" / "r34_nbt1d_state_dict.json"
    assert path.is_file(), f"{path} is missing: the repository is incomplete"
    return path


def pytest_addoption(parser):
    parser.addoption("--slow", action="store_true", default=False,
                     help="also run tests marked slow")


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: long test, run with --slow (make test-all)")
    config.addinivalue_line("markers", "ros: needs rclpy and local DDS")


def pytest_collection_modifyitems(config, items):
    """Slow tests are deselected (not skipped) unless --slow: the fast default reports
    every test it runs as passed or failed, nothing as skipped."""
    if config.getoption("--slow"):
        return
    slow = [item for item in items if "slow" in item.keywords]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = [item for item in items if "slow" not in item.keywords]
