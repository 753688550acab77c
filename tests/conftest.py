"""Fixtures shared by the tests in this folder (helpers live in ``_service_helpers``)."""

from __future__ import annotations

import pytest

from _service_helpers import Broker


@pytest.fixture(scope="module")
def broker():
    """An in-process amqtt broker on a free loopback port, for one test module."""
    import amqtt  # noqa: F401  (a test extra: missing means a broken install)
    import paho.mqtt  # noqa: F401  (a test extra: missing means a broken install)
    b = Broker().start()
    yield b
    b.stop()
