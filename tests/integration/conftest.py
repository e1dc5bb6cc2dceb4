"""The services these tests start load the compiled kernels before they report ready: on a machine
where they were never compiled (a fresh clone), they are compiled here, once, before the first test
(what ``v2i warm`` does: the services' kernels and the evaluator's), not in a service."""

import pytest

from v2i.core.jit import load_kernels
from v2i.offline.kernels import ALL_KERNEL_MODULES


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels() -> None:
    load_kernels(ALL_KERNEL_MODULES)
