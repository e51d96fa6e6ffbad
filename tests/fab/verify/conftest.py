"""Fixtures shared by verify's tests: a random design and a retrieved one."""

import numpy as np
import pytest
from verify_helpers import K, L, N


@pytest.fixture(scope="session")
def levels():
    return np.random.default_rng(7).integers(0, L, (N, N)).astype(np.uint8)


@pytest.fixture(scope="session")
def designed():
    """A retrieved, high-efficiency design (most light in the window, weak outside)."""
    from doe.retrieval import retrieve_phase
    from doe.targets import make_target

    return retrieve_phase(make_target("asymmetric", K), N, L, seed=0).levels
