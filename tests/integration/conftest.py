"""The services these tests start load the tracker's compiled loops before they report ready, and
the tests give them seconds to be ready: on a machine where the loops were never compiled (a
fresh clone: ~12 s, once), they are compiled here, before the first test, not in a service."""

import pytest

from fusion.jit import load_kernels


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels() -> None:
    load_kernels()
