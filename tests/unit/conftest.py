"""Fixtures shared by unit tests."""

import signal

import pytest


@pytest.fixture
def alarm():
    """Fail (not hang) a test whose read blocks for 10 s (SIGALRM; the main thread only)."""
    def _timeout(signum, frame):
        raise AssertionError("a read blocked")

    old = signal.signal(signal.SIGALRM, _timeout)
    signal.alarm(10)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)
