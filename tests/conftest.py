"""Every test gets its own calibration-history database (nodes started by a test inherit it), so no
test re-publishes a calibration another test stored."""
import os

import pytest


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
