import os
import sys

import pytest

# make helper modules in test/ (e.g. pin_pgs_reference) importable
sys.path.insert(0, os.path.dirname(__file__))


@pytest.fixture(scope="session")
def starleth_hmj():
    from starleth_sim import Simulator
    return Simulator.from_preset("HmJ")
