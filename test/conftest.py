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
    # A private temporary folder per session: pytest prunes old runs in the shared default
    # (/tmp/pytest-of-<user>), which removes the files of another suite running at once.
    if not config.option.basetemp:
        import tempfile
        config.option.basetemp = tempfile.mkdtemp(prefix="neurncd-pytest-")
        config._neurncd_basetemp = config.option.basetemp
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


def pytest_unconfigure(config):
    import shutil
    folder = getattr(config, "_neurncd_basetemp", None)
    if folder:
        shutil.rmtree(folder, ignore_errors=True)
    # Tests kill nodes on purpose (SIGKILL): the Fast DDS shared memory those left behind
    # (128 MB each in /dev/shm, memory until reboot) goes with the session. Live
    # processes' segments are locked and never touched.
    from neurncd_ros.nodes.process import remove_stale_shm
    remove_stale_shm(min_age_s=5.0)
