"""Shared test fixtures and options."""

from __future__ import annotations

import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--ecvfl-port", default=None, help="serial port of a real Optotune Lens Driver 4 (enables hardware tests)")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--ecvfl-port"):
        return
    skip = pytest.mark.skip(reason="hardware test: pass --ecvfl-port PORT to run")
    for item in items:
        if "hardware" in item.keywords:
            item.add_marker(skip)
