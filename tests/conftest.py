import os

import matplotlib
import pytest

matplotlib.use("Agg")
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the application sets it (iptm/__init__.py)


@pytest.fixture(scope="session")
def params():
    from calib.model.params import default_parameters

    return default_parameters()


@pytest.fixture(scope="session")
def mp(params):
    return params.model_params()
