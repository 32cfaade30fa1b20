"""Fixtures shared by the package's tests."""

import os
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def cli() -> Path:
    exe = os.environ.get("GROUNDWORK_CLI")
    assert exe, "GROUNDWORK_CLI names the groundwork binary (test.sh sets it)"
    return Path(exe)
