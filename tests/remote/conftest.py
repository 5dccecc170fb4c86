"""Fixtures of the link tests: a :class:`netns.Net` per test, cleaned up however the test
ends, and a session-wide sweep of ``pf-*`` namespaces a killed run left behind."""
from __future__ import annotations

import pytest

from . import netns


@pytest.fixture(scope="session", autouse=True)
def _sweep_namespaces():
    if netns.unavailable_reason() is None:
        netns.sweep_leftovers()
    yield
    if netns.unavailable_reason() is None:
        netns.sweep_leftovers()


@pytest.fixture
def net(tmp_path):
    netns.require_netns()
    n = netns.Net(tmp_path)
    try:
        yield n
    finally:
        n.close()
        assert not [ns for ns in netns.list_namespaces() if ns.startswith(f"{netns.PREFIX}{n.tag}")]
