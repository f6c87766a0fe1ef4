"""Copies of one drive in several formats are recognised as one drive (bundled SYNTHETIC warm restart)."""
from pathlib import Path

import pytest

from calib.ingest.drives import group_drives, same_drive, split_fit_validation
from calib.ingest import read_log

LOGS = Path(__file__).resolve().parent.parent / "logs"


@pytest.fixture(scope="module")
def logs():
    return {n: read_log(LOGS / n) for n in ("winter_warm_restart.blf", "winter_warm_restart.csv",
                                             "winter_warm_restart.log", "winter_cold_start.blf")}


def test_copies_in_other_formats_are_one_drive(logs):
    blf, csv, can, cold = (logs[n] for n in logs)
    assert same_drive(blf, can) and same_drive(blf, csv)  # csv differs by the CAN scaling only
    assert not same_drive(blf, cold)
    assert group_drives([blf, cold, csv, can]) == [[0, 2, 3], [1]]


def test_never_validate_on_a_fitted_drive(logs):
    blf, csv, can, cold = (logs[n] for n in logs)
    fit, val, warn = split_fit_validation([blf, csv, cold], [can])
    assert fit == [blf, cold] and val == []
    assert any("same drive" in w for w in warn) and any("not used for validation" in w for w in warn)
    fit, val, warn = split_fit_validation([cold], [blf])
    assert fit == [cold] and val == [blf] and warn == []
