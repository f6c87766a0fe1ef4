"""Sparse channels in the fitters: a channel polled every 5-10 s (0.1-0.2 Hz) is used where it has samples, an
input is bridged across short gaps only, and a long gap is never read as zero or as an engine off.

Logs come from the fitter's own synthesiser (calib.synth, known truth); the polled channels are taken from its
streams at the poll times, and each log is checked as the resampler makes it and with the polled channels only
in the rows that hold a sample (NaN between polls), so the fits do not depend on how the table was filled."""
import functools

import numpy as np
import pytest

from calib.drivelog import DriveLog, LogMeta
from calib.fit.battery import fit_battery
from calib.fit.cabin import fit_cabin
from calib.fit.fuel import fit_fuel
from calib.fit.replay import fill_short, gap_limit, log_arrays, running_cue
from calib.fit.thermal import fit_thermal
from calib.ingest import to_drivelog
from calib.model.equations import OFF
from calib.model.params import default_parameters
from calib.synth import Scenario, draw_truth, synthesise

COLD = Scenario("cold", "udds", -10.0, 0.60, -10.0, -10.0, T_bat=-5.0, heater_off=[(800.0, 1100.0)])
SCENARIOS = {"cold": COLD, "bat_cold": Scenario("bat_cold", "nycc", -10.0, 0.60, -10.0, -10.0, T_bat=-5.0),
             "bat_mild": Scenario("bat_mild", "us06", -5.0, 0.55, 75.0, 15.0, T_bat=5.0)}


def poll(s, every, phase=1.3):
    """The samples of stream ``s`` a tool polling it every ``every`` s would read (the first at or after each
    poll time)."""
    t = s.index.to_numpy(float)
    j = np.searchsorted(t, np.arange(phase, t[-1], every))
    return s.iloc[np.unique(j[j < t.size])]


def binned_only(log, streams, channels):
    """The table with each of ``channels`` kept only in the rows that hold one of its samples."""
    d = log.data.copy()
    for ch in channels:
        idx = np.floor(streams[ch].index.to_numpy(float) / log.dt + 0.5).astype(int)
        keep = np.zeros(len(d), bool)
        keep[idx[idx < len(d)]] = True
        d.loc[~keep, ch] = np.nan
    return DriveLog(d, log.meta)


@functools.lru_cache(maxsize=None)
def polled_log(scenario="cold", channels=(), every=10.0, table="binned", seed=1):
    """(truth, full-rate log, log with ``channels`` polled every ``every`` s)."""
    truth = draw_truth(seed)
    _, streams, meta = synthesise(SCENARIOS[scenario], truth, seed=seed)
    full = to_drivelog(streams, meta)
    st = dict(streams)
    for c in channels:
        st[c] = poll(streams[c], every)
    log = to_drivelog(st, meta)
    if table == "binned":
        log = binned_only(log, st, channels)
    elif table == "recorded":  # the resampler's table, with the rows that hold a sample recorded beside it
        log.sampled = {c: np.isfinite(binned_only(log, st, channels).data[c].to_numpy(float)) for c in channels}
    return truth, full, log


# ---------------------------------------------------------------------------------------------- helpers
def test_fill_short_bridges_short_gaps_only():
    a = np.full(100, np.nan)
    a[[0, 10, 20, 30, 90]] = [0.0, 10.0, 20.0, 30.0, 90.0]  # polled every 10 s, then a 60-s dropout
    assert gap_limit(a) == 25.0  # 2.5 times its own 10-s interval
    f = fill_short(a)
    assert np.allclose(f[:31], np.arange(31.0))  # linear between polls
    assert np.isnan(f[31:90]).all() and np.isnan(f[91:]).all()  # nothing across the dropout or after the end
    # a state (nearest sample): each sample holds for half the limit (12.5 s) into the dropout and beyond the end
    n = fill_short(a, nearest=True)
    assert n[4] == 0.0 and n[6] == 10.0
    assert np.all(n[31:43] == 30.0) and np.isnan(n[43:78]).all() and np.all(n[78:90] == 90.0)
    assert np.all(n[90:] == 90.0)
    b = np.arange(60.0)
    b[10:14] = np.nan  # a 1 Hz channel: a 4-s dropout is bridged, a 6-s one is not (limit 5 s)
    b[30:36] = np.nan
    g = fill_short(b)
    assert np.allclose(g[10:14], np.arange(10.0, 14.0)) and np.isnan(g[30:36]).all()


def test_engine_state_comes_from_the_nearest_cue_never_from_a_missing_sample():
    n = 200
    rpm = np.full(n, np.nan)
    rpm[0:80:10] = 1000.0  # polled every 10 s while the engine runs
    rpm[150:200:10] = 0.0  # stopped later
    fuel = np.full(n, np.nan)
    fuel[115] = 0.3  # one fuel sample in the 70-s silence of the engine speed
    state, cues = running_cue({"engine_speed_rpm": rpm, "fuel_rate_g_per_s": fuel})
    assert cues == ["engine_speed_rpm", "fuel_rate_g_per_s"]
    assert (state[:80] == 1).all()  # running between polls, and for half the gap limit after the last
    assert (state[90:110] == 0).all() and (state[120:135] == 0).all()  # no cue reaches these: unknown, not off
    assert (state[113:118] == 1).all() and (state[140:] == -1).all()


def test_long_gap_of_every_engine_cue_is_left_out_of_the_thermal_fit():
    """A log without engine torque (engine power from the balance, engine mode from the engine speed and fuel
    cues): 120 s with neither engine speed, fuel rate nor speed is unknown, not engine off; the coolant replay
    restarts after it and the fit matches the one on the complete log (read as engine off and no fuel, the gap
    spoils it: coolant RMSE 1.8 degC instead of 0.36)."""
    drop = ["engine_torque_Nm"]
    scs = [Scenario(**{**COLD.__dict__, "drop_channels": drop}),
           Scenario("warm", "hwfet", -5.0, 0.55, 65.0, 15.0, T_bat=5.0, drop_channels=drop)]
    truth = draw_truth(1)
    logs = [to_drivelog(*synthesise(sc, truth, seed=1)[1:]) for sc in scs]
    d = logs[0].data.copy()
    gap = (d.index >= 300.0) & (d.index < 420.0)
    d.loc[gap, ["engine_speed_rpm", "fuel_rate_g_per_s", "speed_mps"]] = np.nan
    holed = DriveLog(d, logs[0].meta)
    base = default_parameters()
    la = log_arrays(holed, base.model_params())
    inner = (d.index >= 303.0) & (d.index < 417.0)  # the cues on each side hold for 2.5 s (half the 5-s limit)
    assert (la.mode[inner] == 0).all() and not la.known[inner].any() and not (la.mode[gap] == OFF).any()
    ref, fit = fit_thermal(logs, base), fit_thermal([holed] + logs[1:], base)
    assert "2 run(s)" in fit.used[holed.label()]["left out"]
    assert fit.metrics["rmse_degC"] < 0.5
    for n in ("C_eng_J_per_K", "gamma_exh", "hA_eng_W_per_K"):
        e, r = fit.estimates[n], ref.estimates[n]
        assert e.status == "estimated" and abs(e.value - r.value) <= 2 * r.stderr, (n, e.value, r.value, r.stderr)


# ---------------------------------------------------------------------------------------------- fuel
@pytest.mark.parametrize("table", ["binned", "recorded"])
def test_fuel_fit_with_fuel_and_coolant_at_0_1_hz(table):
    """Fuel rate and coolant polled every 10 s: the fuel rate is used in the rows where it was logged (about one
    stable bin in ten), the coolant bridged between its polls; W_idle and the cold factor come out as from the
    complete log."""
    truth, full, log = polled_log(channels=("fuel_rate_g_per_s", "coolant_temp_degC"), table=table)
    base = default_parameters()
    ref, fit = fit_fuel([full], base), fit_fuel([log], base)
    assert 0.05 * ref.metrics["samples"] < fit.metrics["samples"] < 0.15 * ref.metrics["samples"]
    assert "warning" not in fit.used[log.label()]
    w = fit.estimates["W_idle_g_per_s"]
    assert w.status == "estimated" and abs(w.value / truth["W_idle_g_per_s"] - 1) < 0.05
    f, ft = fit.estimates["f_cl"], truth["f_cl"]
    assert abs(f.value[0] / ft[0] - 1) < 0.05 and abs(f.value[1] / ft[1] - 1) < 0.05


def test_fuel_fit_says_when_it_cannot_tell_logged_rows():
    """The resampler's table without the record of which rows hold a sample: the fit says that interpolated
    fuel rates were taken as logged."""
    chans = ("fuel_rate_g_per_s", "coolant_temp_degC")
    _, _, log = polled_log(channels=chans, table="resampled")
    kept = int(np.isfinite(polled_log(channels=chans, table="binned")[2].data["fuel_rate_g_per_s"]).sum())
    if not np.isfinite(log.data["fuel_rate_g_per_s"]).sum() > 2 * kept:
        pytest.skip("this resampler leaves the rows between polls empty")
    meta = LogMeta.from_dict(log.meta.to_dict())
    meta.channel_counts = {"fuel_rate_g_per_s": {"kept": kept}}
    meta.interpolated_rows = {}  # a table that does not record which rows were filled
    log = DriveLog(log.data, meta)
    fit = fit_fuel([log], default_parameters())
    assert f"fuel_rate_g_per_s: {kept} samples filled into" in fit.used[log.label()]["warning"]


# ---------------------------------------------------------------------------------------------- cabin
@pytest.mark.parametrize("table", ["binned", "resampled"])
def test_cabin_fit_with_heater_power_cabin_and_ambient_at_0_2_hz(table):
    truth, _, log = polled_log(channels=("heater_power_W", "cabin_temp_degC", "ambient_temp_degC"), every=5.0,
                               table=table)
    fit = fit_cabin([log], default_parameters())
    for n in ("C_cab_J_per_K", "UA_cab_W_per_K"):
        e = fit.estimates[n]
        assert e.status == "estimated" and abs(e.value / truth[n] - 1) < 0.1, (n, e.value, truth[n])


def test_cabin_heater_dropout_restarts_the_replay():
    """300 s without heater power (the heater ran then): left out, the cabin replay restarts after it, the
    estimates as from the complete log; read as 0 W the cabin would be simulated cooling where it warmed."""
    truth, full, _ = polled_log()
    d = full.data.copy()
    d.loc[(d.index >= 300.0) & (d.index < 600.0), "heater_power_W"] = np.nan
    holed = DriveLog(d, full.meta)
    fit = fit_cabin([holed], default_parameters())
    assert "2 run(s)" in fit.used[holed.label()]["left out"]
    for n in ("C_cab_J_per_K", "UA_cab_W_per_K"):
        e = fit.estimates[n]
        assert e.status == "estimated" and abs(e.value / truth[n] - 1) < 0.1, (n, e.value, truth[n])


def test_heater_heat_unknown_at_every_sample_is_not_read_as_zero():
    """Vent temperature logged in the first half only, blower flow in the second only: the heater heat
    W_bl c_p (T_vent - T_in) is known nowhere, so the cabin fit has no data (it says so) instead of simulating
    the cabin with 0 W."""
    truth, full, _ = polled_log()
    d = full.data.drop(columns=["heater_power_W"])
    half = d.index < d.index[-1] / 2
    d.loc[~half, "vent_temp_degC"] = np.nan
    d.loc[half, "blower_flow_kg_per_s"] = np.nan
    log = DriveLog(d, full.meta)
    fit = fit_cabin([log], default_parameters(), allowed={"C_cab_J_per_K", "UA_cab_W_per_K", "Q_sun_W"})
    assert "heater heat and the ambient known" in fit.skipped[log.label()]
    assert all(fit.estimates[n].status == "prior" for n in ("C_cab_J_per_K", "UA_cab_W_per_K", "Q_sun_W"))


def test_cabin_with_heater_declared_off():
    """Cabin and ambient logged, no heater channel: skipped unless the heater is declared off; then fitted with
    zero heat, which ``used`` says."""
    truth, full, _ = polled_log()
    d = full.data.drop(columns=["heater_power_W", "vent_temp_degC", "blower_flow_kg_per_s"])
    log = DriveLog(d, full.meta)
    cab = {"C_cab_J_per_K", "UA_cab_W_per_K", "Q_sun_W"}
    assert log.label() in fit_cabin([log], default_parameters(), allowed=cab).skipped
    fit = fit_cabin([log], default_parameters(), allowed=cab, heater="off")
    assert fit.used[log.label()]["heater heat"] == "none: declared off (heater='off')"
    assert "heater declared off" in fit.estimates["C_cab_J_per_K"].note


# ---------------------------------------------------------------------------------------------- battery
@functools.lru_cache(maxsize=None)
def battery_logs(every=None, table="binned"):
    out = []
    for sc in ("bat_cold", "bat_mild"):
        truth, full, log = polled_log(sc, ("soc",) if every else (), every or 10.0, table)
        out.append(log if every else full)
    return truth, out


@pytest.mark.parametrize("table", ["binned", "recorded"])
def test_capacity_with_soc_at_0_1_hz(table):
    """SOC polled every 10 s: level crossings between consecutive polls; the capacity within 3 % of the
    truth, as from the SOC logged every second."""
    truth, logs = battery_logs(10.0, table)
    _, ref_logs = battery_logs()
    allowed = {"C_bat_Ah"}
    fit, ref = fit_battery(logs, default_parameters(), allowed=allowed), fit_battery(ref_logs, default_parameters(),
                                                                                     allowed=allowed)
    assert fit.metrics["capacity_soc_crossings"] < 0.8 * ref.metrics["capacity_soc_crossings"]
    e = fit.estimates["C_bat_Ah"]
    assert e.status == "estimated" and abs(e.value / truth["C_bat_Ah"] - 1) < 0.03, (e.value, truth["C_bat_Ah"])


def _with_gap(log, channel, t0=200.0, t1=400.0):
    d = log.data.copy()
    d.loc[(d.index >= t0) & (d.index < t1), channel] = np.nan
    return DriveLog(d, log.meta)


def test_current_dropout_restarts_the_charge_count():
    """200 s of the US06 without battery current (11 A on average): no charge is counted there, the count
    restarts with its own initial SOC, and the capacity stays within 3 % of the truth."""
    truth, logs = battery_logs()
    holed = [logs[0], _with_gap(logs[1], "bat_current_A")]
    fit = fit_battery(holed, default_parameters(), allowed={"C_bat_Ah"})
    assert fit.metrics["capacity_runs"] == 3 and "no charge is counted" in fit.used[holed[1].label()]["left out"]
    e = fit.estimates["C_bat_Ah"]
    assert abs(e.value / truth["C_bat_Ah"] - 1) < 0.03 and "restarts after 1 long gap" in e.note


def test_power_dropout_restarts_the_soc_balance():
    """Battery power and SOC only (the SOC balance): 200 s without power are left out, the balance restarts
    after them, and the capacity matches the one from the complete logs within its posterior sd."""
    truth, logs = battery_logs()
    power = []
    for lg in logs:
        d = lg.data.copy()
        d["bat_power_W"] = d["bat_current_A"] * d["bat_voltage_V"]
        power.append(DriveLog(d.drop(columns=["bat_current_A", "bat_voltage_V"]), lg.meta))
    holed = [power[0], _with_gap(power[1], "bat_power_W")]
    allowed = {"C_bat_Ah", "R_int_ohm", "U_hyst_V"}
    ref, fit = (fit_battery(power, default_parameters(), allowed=allowed),
                fit_battery(holed, default_parameters(), allowed=allowed))
    assert "the SOC balance restarts" in fit.used[holed[1].label()]["left out"]
    e, r = fit.estimates["C_bat_Ah"], ref.estimates["C_bat_Ah"]
    assert abs(e.value - r.value) < r.stderr and abs(e.value / truth["C_bat_Ah"] - 1) < 0.05
