"""End-to-end calibration: truth recovery, held-out validation, artifact round trip, CLI, honesty flags."""
import functools
import json
import math

import numpy as np
import pytest

from calib.fit.driver import calibrate
from calib.errors import ParameterError
from calib.ingest import to_drivelog
from calib.model.params import ParameterSet, default_parameters
from calib.model.simulate import simulate
from calib.synth import Scenario, draw_truth, synthesise
from calib.fit.validate import plot_validation, replay

FIT = [Scenario("fit_cold", "udds", -10.0, 0.60, -10.0, -10.0, T_bat=-5.0, with_bay_temp=True,
                heater_off=[(800.0, 1100.0)]),  # identification protocol (logs/README.md)
       Scenario("fit_warm", "hwfet", -5.0, 0.55, 65.0, 15.0, T_bat=5.0),
       Scenario("fit_hot", "us06", -3.0, 0.60, 80.0, 18.0, T_bat=8.0)]
HELD_OUT = Scenario("held_out", "nycc", -8.0, 0.58, 20.0, 5.0, T_bat=0.0)


@functools.lru_cache(maxsize=None)
def data(seed):
    truth = draw_truth(seed)
    logs = [to_drivelog(*synthesise(sc, truth, seed=seed)[1:]) for sc in FIT]
    val = to_drivelog(*synthesise(HELD_OUT, truth, seed=seed + 100)[1:])
    return truth, logs, val


@functools.lru_cache(maxsize=None)
def result(seed):
    truth, logs, val = data(seed)
    return calibrate(logs, validate=[val], progress=False)


def failures(params, truth):
    bad = []
    for n in params.names():
        p = params.param(n)
        if p.status != "estimated" or n == "eta_ool":  # eta_ool carries the level: tests/test_fit_fuel.py
            continue
        if p.is_table:
            for x, v, s, t, inf in zip(p.x, p.value, p.stderr, truth[n], p.informed):
                tol = 3 * s
                if inf >= 0.3 and math.isfinite(s) and s > 0 and (abs(v - t) > tol or abs(v - t) > 0.1 * abs(t)):
                    bad.append((n, x, v, s, t))
        elif abs(p.value - truth[n]) > 3 * p.stderr or (truth[n] != 0 and abs(p.value - truth[n]) > 0.1 * abs(truth[n])):
            bad.append((n, p.value, p.stderr, truth[n]))
    return bad


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_recovery_of_a_random_truth(seed):
    truth, _, _ = data(seed)
    res = result(seed)
    ps = res.params
    estimated = [n for n in ps.names() if ps.param(n).status == "estimated"]
    # the data determine most of the model ...
    for n in ("C_bat_Ah", "R_int_ohm", "C_eng_J_per_K", "gamma_exh", "kappa", "C_cab_J_per_K", "UA_cab_W_per_K",
              "eps_hc", "W_idle_g_per_s", "eta_ool", "f_cl"):
        assert n in estimated, (n, ps.param(n).note)
    # ... every parameter flagged estimated is within 3 posterior sd and 10 % of the truth
    assert failures(ps, truth) == []
    # every calibrated parameter carries its prior, prior sd, posterior sd and how much the data informed it
    prior = default_parameters()
    for n in ps.names():
        p = ps.param(n)
        if p.status in ("estimated", "weak"):
            assert p.logs and p.stderr is not None and p.prior_sd is not None and p.informed is not None, n
            assert np.allclose(p.prior_value, prior[n]), n


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_validation_on_a_held_out_log(seed):
    res = result(seed)
    (m,) = res.validation.values()
    # measured on these seeds: coolant 0.28-0.92 degC, SOC 0.0016, fuel -0.9 to -1.2 %; the uncalibrated
    # defaults score 1.2-4.6 degC, 0.0027-0.0057 and -1.2 to -4.3 % on the same held-out logs
    assert m["coolant_temp"]["rmse"] < 1.0
    assert m["soc"]["rmse"] < 0.0025
    assert abs(m["cumulative_fuel"]["error_pct"]) < 1.5
    truth, logs, val = data(seed)
    (d,) = calibrate(logs[:1], fit=[], validate=[val], progress=False).validation.values()
    assert m["coolant_temp"]["rmse"] < 0.8 * d["coolant_temp"]["rmse"]  # calibration must beat the defaults
    assert m["soc"]["rmse"] < d["soc"]["rmse"]
    for ch in ("soc", "coolant_temp", "cabin_temp", "fuel_rate"):
        assert {"rmse", "max_abs", "bias"} <= set(m[ch])


def test_validation_with_the_defaults_is_worse():
    """The metrics can fail: the uncalibrated defaults miss the held-out log by more."""
    truth, logs, val = data(2)
    (m,) = calibrate(logs[:1], fit=[], validate=[val], progress=False).validation.values()
    assert m["coolant_temp"]["rmse"] > 1.5 or abs(m["cumulative_fuel"]["error_pct"]) > 3.0


def test_artifact_round_trip_and_simulation(tmp_path):
    res = result(1)
    f = tmp_path / "cal.toml"
    res.to_artifact(f)
    text = f.read_text()
    assert "[calibration]" in text and "[validation." in text and "SYNTHETIC" in text
    ps = ParameterSet.load(f)
    for n in res.params.names():
        assert ps.param(n).status == res.params.param(n).status
        v0, v1 = res.params[n], ps[n]
        assert np.allclose(v0, v1)
        for key in ("prior_sd", "prior_value", "informed"):
            a, b = getattr(res.params.param(n), key), getattr(ps.param(n), key)
            assert (a is None) == (b is None) and (a is None or np.allclose(a, b)), (n, key)
    import tomllib

    d = tomllib.loads(text)
    cal = d["calibration"]
    assert cal["software"].startswith("iptm/calib") and cal["date_utc"]
    assert len(cal["logs"]) == 3 and all(lg["synthetic"] for lg in cal["logs"])
    assert "sha256" in cal["logs"][0]
    assert set(cal["subsystems"]) == {"battery", "fuel", "thermal", "cabin"}
    sim = simulate(ps, "nycc", T_amb=-5.0)
    assert sim.fuel_g > 0
    j = tmp_path / "cal.json"
    res.to_artifact(j)
    assert ParameterSet.load(j)["C_eng_J_per_K"] == pytest.approx(res.params["C_eng_J_per_K"])


def test_report_and_plot(tmp_path):
    res = result(1)
    rep = res.report()
    for s in ("[battery]", "[thermal]", "informed", "prior", "Validation", "RMSE", "Residual diagnostics",
              "engine on", "acf(1s)"):
        assert s in rep
    truth, logs, val = data(1)
    f = tmp_path / "v.png"
    plot_validation(replay(val, res.params), f)
    assert f.stat().st_size > 10_000
    fig = res.plot(tmp_path / "c.png")
    bars = {t.get_text(): b.get_width() for t, b in zip(fig.axes[0].get_yticklabels(), fig.axes[0].patches, strict=True)}
    e = res.fits["thermal"].estimates["C_eng_J_per_K"]
    assert bars["C_eng_J_per_K (thermal)" + (" [weak]" if e.status == "weak" else "")] == pytest.approx(float(e.informed))
    assert all(0.0 <= w <= 1.0 for w in bars.values()) and (tmp_path / "c.png").stat().st_size > 0


def test_log_without_coolant_calibrates_battery_and_says_why_not_thermal():
    truth = draw_truth(4)
    sc = Scenario("no_coolant", "nycc", -10.0, 0.6, -10.0, -10.0, T_bat=-5.0, drop_channels=["coolant_temp_degC"])
    log = to_drivelog(*synthesise(sc, truth, seed=4)[1:])
    res = calibrate([log], progress=False)
    ps = res.params
    assert ps.param("R_int_ohm").status == "estimated"
    for n in ("C_eng_J_per_K", "gamma_exh", "hA_eng_W_per_K", "T_open_degC", "k_rad_W_per_K"):
        p = ps.param(n)
        assert p.status == "prior" and "not fitted" in p.note and "coolant_temp_degC" in p.note
        assert p.value == default_parameters()[n] and p.stderr == pytest.approx(p.prior_sd)
    assert "coolant_temp_degC" in res.fits["thermal"].message
    assert "coolant_temp_degC" in res.report()


def test_fit_subset_and_fix():
    truth, logs, _ = data(2)
    res = calibrate(logs[:2], fit=["C_bat_Ah", "C_eng_J_per_K", "gamma_exh"], fix=["gamma_exh"], progress=False)
    ps = res.params
    assert ps.param("C_bat_Ah").status == "estimated"
    assert ps.param("gamma_exh").status == "fixed" and ps["gamma_exh"] == default_parameters()["gamma_exh"]
    assert ps.param("UA_cab_W_per_K").status == "prior"  # not in the subset
    with pytest.raises(ParameterError):
        calibrate(logs[:1], fit=["nope"], progress=False)


def test_cli_calibrate(tmp_path, capsys):
    from calib.ingest.writers import write_streams
    from iptm.cli import main

    truth = draw_truth(1)
    paths = []
    for i, sc in enumerate(FIT[:2] + [HELD_OUT]):
        _, streams, meta = synthesise(sc, truth, seed=1 + i)
        p = tmp_path / f"{sc.name}.csv"
        write_streams(streams, meta, p, "csv")
        paths.append(str(p))
    out, js, plots = tmp_path / "cal.toml", tmp_path / "cal.json", tmp_path / "plots"
    rc = main(["calibrate", paths[0], paths[1], "--validate", paths[2], "--out", str(out), "--json", str(js),
               "--plots", str(plots), "--quiet"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "[thermal]" in text and "Validation" in text
    ps = ParameterSet.load(out)
    assert ps.param("C_bat_Ah").status == "estimated"
    d = json.loads(js.read_text())
    assert d["calibration"]["logs"][0]["sha256"]
    assert list(plots.glob("*.png"))


@pytest.mark.slow
def test_full_size_bundled_calibration():
    """Full size (the three bundled scenarios, ~80 min): recovery (its time: ``iptm bench calib``)."""
    from calib.synth import BUNDLED

    truth = draw_truth(11)
    logs = [to_drivelog(*synthesise(sc, truth, seed=11 + i)[1:]) for i, sc in enumerate(BUNDLED)]
    res = calibrate(logs, progress=False)
    assert failures(res.params, truth) == []
