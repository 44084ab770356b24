"""Fixtures shared by the test modules."""

import pytest


@pytest.fixture
def count_calls(monkeypatch):
    """``count_calls(module, name)`` replaces ``module.name`` for the test by a wrapper that calls
    the original and counts the calls; returns the dict whose ``"calls"`` holds the count."""

    def install(module, name: str) -> dict:
        real, seen = getattr(module, name), {"calls": 0}

        def counting(*args, **kwargs):
            seen["calls"] += 1
            return real(*args, **kwargs)

        monkeypatch.setattr(module, name, counting)
        return seen

    return install
