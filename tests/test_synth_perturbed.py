"""The perturbed-structure synthesiser: its plant differs from the fitter's model where it says it does,
its logs look like an ordinary logger's, and its truth file says what a perfect fit would find."""
from __future__ import annotations

import json

import numpy as np
import pytest

from testcars.synth_perturbed import (
    ENGINE_CHANNELS,
    HEATER_CHANNELS,
    Drive,
    comparable_truth,
    draw_plant,
    f_cold,
    n_engine_rpm,
    simulate_plant,
    synthesise_perturbed,
)

SHORT = Drive("short_cold", "udds", -10.0, -10.0, -10.0, -8.0, 0.58, description="cold UDDS")


@pytest.fixture(scope="module")
def plant():
    return draw_plant(1)


@pytest.fixture(scope="module")
def truth_run(plant):
    return simulate_plant(plant, SHORT)


def test_plants_differ_by_seed_and_from_the_mean():
    a, b = draw_plant(1), draw_plant(2)
    assert a["C_eng_J_per_K"] != b["C_eng_J_per_K"]
    assert 0.015 <= a["fuel_meter_bias"] <= 0.04


def test_structure_is_not_the_fitters(plant, truth_run):
    from calib.model.params import default_parameters

    base = default_parameters()
    # engine-speed line and efficiency differ from the fitter's tables
    P = np.array([5e3, 15e3, 30e3])
    n_fit = np.interp(P, base.param("n_ool_rpm").x, base.param("n_ool_rpm").value)
    assert np.max(np.abs(n_engine_rpm(plant, P) - n_fit)) > 100
    # the cold factor is a smooth curve, not 1 at 80 degC
    assert f_cold(plant, 80.0) > 1.01
    # the coolant sensor lags the coolant while it warms
    tr = truth_run
    warming = np.flatnonzero(np.diff(tr["T_cl"]) > 0.02)
    assert np.mean(tr["T_cl"][warming] - tr["T_cl_sensor"][warming]) > 0.3
    # energy: SOC stays in a hybrid's window, the cabin warms, the engine warms
    assert 0.4 < tr["soc"].min() and tr["soc"].max() < 0.85
    assert tr["T_cab"][-1] > 10 and tr["T_cl"][-1] > 30


def test_logs_are_labelled_and_channels_can_be_dropped(plant):
    tr, streams, meta = synthesise_perturbed(SHORT, plant, seed=5, drop_channels=ENGINE_CHANNELS)
    assert meta.synthetic and "SYNTHETIC" in meta.notes[0]
    assert not set(ENGINE_CHANNELS) & set(streams)
    assert "heater_power_W" not in streams  # an ordinary car logs vent temperature and blower flow
    assert {"vent_temp_degC", "blower_flow_kg_per_s", "fuel_rate_g_per_s"} <= set(streams)
    # the fuel meter reads high by the bias
    fuel_logged = float(np.sum(streams["fuel_rate_g_per_s"].to_numpy()) * 0.1)
    assert fuel_logged == pytest.approx(tr["fuel_g"] * (1 + plant["fuel_meter_bias"]), rel=0.02)
    _, s2, _ = synthesise_perturbed(SHORT, plant, seed=5, drop_channels=HEATER_CHANNELS)
    assert not set(HEATER_CHANNELS) & set(s2)


def test_comparable_truth(plant):
    comp = comparable_truth(plant)
    v = comp["values"]
    from calib.model.params import default_parameters

    xs = default_parameters().param("f_cl").x
    r = xs.index(80.0)
    assert v["f_cl"][r] == pytest.approx(1.0)  # the fitter's warm reference
    # the plant's factor keeps falling above it: below 1 at the fitter's hot breakpoints
    assert 1.0 > v["f_cl"][r + 1] > v["f_cl"][-1] > 0.9
    assert v["f_cl_at_-10"] > v["f_cl_at_0"] > 1.0
    assert v["W_idle_g_per_s"] > plant["W_idle_g_per_s"]  # as the biased meter reads it
    assert "k_rad_W_per_K" in comp["no_counterpart"] and "fuel_scale" in comp["no_counterpart"]


def test_cli_synth_perturbed_writes_logs_and_truth(tmp_path):
    from iptm.cli import main

    assert main(["synth", "--perturbed", "--out", str(tmp_path), "--seed", "4"]) == 0
    truth = json.loads((tmp_path / "SYNTHETIC_perturbed_truth.json").read_text())
    assert truth["seed"] == 4 and "structure" in truth and "comparable" in truth
    csvs = sorted(p.name for p in tmp_path.glob("SYNTHETIC_*.csv"))
    assert len(csvs) == 3
    from calib.ingest import read_log

    log = read_log(tmp_path / csvs[0])
    assert log.meta.synthetic and "coolant_temp_degC" in log.channels()
