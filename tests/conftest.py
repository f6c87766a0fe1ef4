import os

import matplotlib
import pytest

matplotlib.use("Agg")
os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture(scope="session")
def params():
    from calib.params import default_parameters

    return default_parameters()


@pytest.fixture(scope="session")
def mp(params):
    return params.model_params()
