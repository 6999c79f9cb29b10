"""Every test gets its own calibration-history database (nodes started by a test inherit it), so no
test re-publishes a calibration another test stored."""
import os

import pytest

# Parallel runs (pytest -n N, pytest-xdist): each worker gets its own DDS domain, so two ROS
# tests running at the same time never see each other's topics. Set at import, before any test
# starts a node or a subprocess (both read the variable when they initialise).
_worker = os.environ.get("PYTEST_XDIST_WORKER", "")
if _worker.startswith("gw"):
    _base = int(os.environ.get("ROS_DOMAIN_ID", "0") or 0)
    os.environ["ROS_DOMAIN_ID"] = str((_base + 47 * (int(_worker[2:]) + 1)) % 101 + 1)


@pytest.fixture(scope="session", autouse=True)
def _session_history_db(tmp_path_factory):
    old = os.environ.get("METRO_HISTORY_DB")
    os.environ["METRO_HISTORY_DB"] = str(tmp_path_factory.mktemp("history") / "session_history.sqlite")
    yield
    if old is None:
        os.environ.pop("METRO_HISTORY_DB", None)
    else:
        os.environ["METRO_HISTORY_DB"] = old


@pytest.fixture(autouse=True)
def _test_history_db(tmp_path, monkeypatch):
    monkeypatch.setenv("METRO_HISTORY_DB", str(tmp_path / "history.sqlite"))
