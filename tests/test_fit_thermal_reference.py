"""The engine thermal fit on a log made without the model's code: the coolant temperature integrated here
from eq. 3 of spec/model.md (explicit Euler at the log's 1 s step, the model's stated discretisation) with
noise-free inputs. The fit must return the values used, to a tolerance far below the bias of a residual
that compares the simulation with the wrong sample."""
import numpy as np
import pandas as pd
import pytest

from calib.drivelog import DriveLog, LogMeta
from calib.fit.thermal import fit_thermal
from calib.model.params import default_parameters

LHV = 42.6e3  # J/g
TRUE = dict(C_eng_J_per_K=95e3, gamma_exh=0.42, hA_eng_W_per_K=34.0)
KAPPA = 0.3  # the prior: kappa is not fitted without the engine-bay temperature


def _log(n=1500, T0=-5.0, T_amb=-8.0, bay_samples=0, kappa=KAPPA):
    t = np.arange(n, dtype=float)
    rpm = 1800.0 + 400.0 * np.sin(2 * np.pi * t / 300.0)  # off the optimal operating line: P = n tau
    torque = 25.0 + 12.0 * np.sin(2 * np.pi * t / 170.0)
    P = rpm * 2 * np.pi / 60.0 * torque
    W = P / (0.33 * LHV) + 0.03 * (1 + np.sin(2 * np.pi * t / 90.0))  # g/s
    Q_heat = np.where((t % 400) < 250, 5000.0, 0.0)  # heater on/off: separates C_eng from gamma_exh
    T = np.empty(n)
    T[0] = T0
    for k in range(n - 1):  # eq. 3 with eqs. 6-8, below the thermostat (no radiator)
        Q_fuel = LHV * W[k]
        Q_exh = TRUE["gamma_exh"] * (Q_fuel - P[k])
        Q_air = TRUE["hA_eng_W_per_K"] * (1.0 - kappa) * (T[k] - T_amb)
        T[k + 1] = T[k] + (Q_fuel - P[k] - Q_exh - Q_air - Q_heat[k]) / TRUE["C_eng_J_per_K"]
    data = pd.DataFrame({"engine_speed_rpm": rpm, "engine_torque_Nm": torque, "fuel_rate_g_per_s": W,
                         "heater_power_W": Q_heat, "coolant_temp_degC": T, "ambient_temp_degC": T_amb,
                         "speed_mps": 12.0}, index=pd.Index(t, name="time_s"))
    if bay_samples:  # engine-bay temperature (eq. 8) logged for the last few samples only
        bay = T_amb + kappa * (T - T_amb)
        bay[:-bay_samples] = np.nan
        data["bay_temp_degC"] = bay
    return DriveLog(data=data, meta=LogMeta(source="independent eq. 3 integration", format="test",
                                            synthetic=True))


@pytest.mark.filterwarnings("ignore:rel_change")  # lmfit conf_interval on noise-free data
def test_thermal_fit_returns_the_values_of_an_independent_integration():
    log = _log()
    assert log.data["coolant_temp_degC"].max() < default_parameters()["T_open_degC"] - 10
    fit = fit_thermal([log], default_parameters())
    for n, v in TRUE.items():
        e = fit.estimates[n]
        assert e.status == "estimated", (n, e.note)
        assert e.value == pytest.approx(v, rel=1e-3), n
    assert fit.metrics["rmse_degC"] < 1e-3
    assert fit.nuisance["T0_0"] == pytest.approx(-5.0, abs=1e-3)


@pytest.mark.filterwarnings("ignore:rel_change")
def test_kappa_needs_sixty_bay_temperature_samples():
    fit = fit_thermal([_log(bay_samples=40)], default_parameters(), allowed={"kappa"})
    e = fit.estimates["kappa"]  # too few samples: the posterior is the prior, uninformed
    assert e.status == "weak" and e.informed == 0.0 and e.value == default_parameters()["kappa"]
    fit = fit_thermal([_log(bay_samples=200)], default_parameters(), allowed={"kappa"})
    assert fit.estimates["kappa"].status == "estimated"
    assert fit.estimates["kappa"].value == pytest.approx(KAPPA, rel=1e-9)


def test_kappa_uses_samples_with_the_coolant_more_than_10_K_above_ambient():
    """Bay temperature on 90 samples: 60 (the least that is enough) with the coolant 10.5 K above ambient
    (used), 30 exactly 10 K above (not used; their bay temperature says kappa = 0.9, which would pull the
    estimate up)."""
    log = _log(n=390, T0=-5.0, T_amb=-8.0)
    d = log.data
    d["coolant_temp_degC"] = np.r_[d["coolant_temp_degC"].to_numpy()[:300], np.full(60, 2.5), np.full(30, 2.0)]
    bay = np.full(390, np.nan)
    bay[300:360] = -8.0 + KAPPA * 10.5
    bay[360:] = -8.0 + 0.9 * 10.0
    d["bay_temp_degC"] = bay
    fit = fit_thermal([log], default_parameters(), allowed={"kappa"})
    assert fit.metrics["kappa_samples"] == 60
    assert fit.estimates["kappa"].status == "estimated"
    assert fit.estimates["kappa"].value == pytest.approx(KAPPA, rel=1e-9)


@pytest.mark.filterwarnings("ignore:rel_change")
def test_time_metrics_count_seconds_at_a_2_s_sample_step():
    """Every other sample of the 1-s log (a 2-s log): 75 heater-off samples with the coolant 38 K above
    ambient, of which 10 at 200.5 W count as on (above 200 W): 130 s; the last 20 samples within 5 K of the
    thermostat are 40 s."""
    log = _log(n=600)
    d = log.data.iloc[::2].copy()
    q = d["heater_power_W"].to_numpy().copy()
    q[np.flatnonzero(q == 0.0)[:10]] = 200.5
    d["heater_power_W"] = q
    T = np.full(len(d), 30.0)
    T[-20:] = default_parameters()["T_open_degC"] - 4.0
    d["coolant_temp_degC"] = T
    log = DriveLog(data=d, meta=log.meta)
    assert log.dt == 2.0 and int(np.sum(d["heater_power_W"].to_numpy() <= 200.5)) == 75
    fit = fit_thermal([log], default_parameters(), allowed={"T_open_degC", "k_rad_W_per_K"})
    assert fit.metrics["heater_off_warm_s"] == 130.0
    assert fit.metrics["time_near_thermostat_s"] == 40.0


@pytest.mark.filterwarnings("ignore:rel_change")
@pytest.mark.parametrize("near", [119, 120])
def test_thermostat_parameters_need_120_s_near_the_opening(near):
    """T_open and k_rad are flagged as prior-only when the coolant spent less than 120 s within 5 K of the
    prior opening temperature (1-s log: one second per sample)."""
    T_open = default_parameters()["T_open_degC"]
    log = _log(n=600)
    T = log.data["coolant_temp_degC"].to_numpy().copy()
    T[-near:] = T_open - 4.0
    log.data["coolant_temp_degC"] = T
    fit = fit_thermal([log], default_parameters(), allowed={"T_open_degC", "k_rad_W_per_K"})
    assert fit.metrics["time_near_thermostat_s"] == near
    for n in ("T_open_degC", "k_rad_W_per_K"):
        assert ("coolant never reached the thermostat" in fit.estimates[n].note) == (near < 120), n


def test_a_channel_of_only_infinite_values_counts_as_missing():
    """An ambient channel holding only infinities (a sensor's fault value) is no ambient temperature: the
    thermal fit names it missing instead of filling it with a default."""
    log = _log(n=300)
    log.data["ambient_temp_degC"] = np.inf
    assert "ambient_temp_degC" in log.missing(["ambient_temp_degC", "coolant_temp_degC"])
    fit = fit_thermal([log], default_parameters(), allowed={"C_eng_J_per_K"})
    assert fit.estimates["C_eng_J_per_K"].status == "prior" and "ambient_temp_degC" in fit.skipped[log.label()]


def test_kappa_standard_error_from_the_regression_residuals():
    """60 bay samples 10.5 K of coolant above ambient, bay = T_amb + 0.3 * 10.5 +- 0.1 alternating (independent
    residuals: no inflation): k = 0.3, se = sqrt(r.r / (n - 1) / x.x); the posterior combines it with the
    prior by precision."""
    from calib.model.params import prior_sd_of

    log = _log(n=360, T0=-5.0, T_amb=-8.0)
    d = log.data
    d["coolant_temp_degC"] = np.r_[d["coolant_temp_degC"].to_numpy()[:300], np.full(60, 2.5)]
    bay = np.full(360, np.nan)
    bay[300:] = -8.0 + KAPPA * 10.5 + 0.1 * np.tile([1.0, -1.0], 30)
    d["bay_temp_degC"] = bay
    base = default_parameters()
    fit = fit_thermal([log], base, allowed={"kappa"})
    se = np.sqrt(60 * 0.01 / 59 / (60 * 10.5 ** 2))
    psd = float(prior_sd_of(base.param("kappa")))
    w1, w0 = 1 / se ** 2, 1 / psd ** 2
    e = fit.estimates["kappa"]
    assert e.value == pytest.approx((w1 * KAPPA + w0 * base["kappa"]) / (w1 + w0), rel=1e-9)
    assert e.stderr == pytest.approx((w1 + w0) ** -0.5, rel=1e-9)


@pytest.mark.filterwarnings("ignore:rel_change")
def test_hA_eng_note_gives_the_identified_product_hA_eng_times_1_minus_kappa():
    """Without the engine-bay temperature only hA_eng (1 - kappa) enters eq. 3: the note states that product,
    34 W/K x (1 - 0.3) = 23.8 W/K for the log made here, and the kappa it assumes."""
    import re

    fit = fit_thermal([_log()], default_parameters())
    e = fit.estimates["hA_eng_W_per_K"]
    m = re.search(r"identified only as hA_eng \(1 - kappa\) = ([0-9.eE+-]+) W/K; kappa not logged, this value "
                  r"assumes kappa = 0.3 \(its prior\)", e.note)
    assert m, e.note
    assert float(m.group(1)) == pytest.approx(TRUE["hA_eng_W_per_K"] * (1.0 - KAPPA), rel=1e-3)
    assert m.group(1) == f"{e.value * (1.0 - KAPPA):.4g}"


def test_a_parameter_the_data_never_reach_keeps_its_prior_sd():
    """The reference drive never reaches the thermostat, so the radiator conductance k_rad is informed by
    its prior alone: its posterior sd is the prior sd (750 W/K), not cut to 0 by the pseudo-inverse."""
    from calib.fit.thermal import fit_thermal
    from calib.model.params import default_parameters

    fit = fit_thermal([_log()], default_parameters())
    est = fit.estimates["k_rad_W_per_K"]
    assert est.prior_sd == pytest.approx(750.0)
    assert est.stderr == pytest.approx(est.prior_sd, rel=0.01)


@pytest.mark.filterwarnings("ignore:rel_change")
def test_heater_off_warm_time_counts_coolant_more_than_20_K_above_ambient():
    """Heater-off seconds with a warm engine (coolant more than 20 K above ambient, the condition under
    which heater-off stretches separate C_eng from gamma_exh): on a 1-s log with the heater off (200 W,
    the threshold, counts as off), 100 samples 20.5 K above ambient count, 100 at exactly 20 K, 100 at
    19.5 K and 100 at 5 K do not; the same 100 warm samples at 200.5 W (on) do not either."""
    log = _log(n=400, T_amb=-8.0)
    d = log.data
    d["heater_power_W"] = 200.0
    d["coolant_temp_degC"] = np.r_[np.full(100, -8.0 + 20.5), np.full(100, -8.0 + 20.0), np.full(100, -8.0 + 19.5),
                                   np.full(100, -8.0 + 5.0)]
    fit = fit_thermal([log], default_parameters(), allowed={"C_eng_J_per_K"})
    assert fit.metrics["heater_off_warm_s"] == 100.0
    d["heater_power_W"] = 200.5
    assert fit_thermal([log], default_parameters(), allowed={"C_eng_J_per_K"}).metrics["heater_off_warm_s"] == 0.0


@pytest.mark.filterwarnings("ignore:rel_change")
def test_input_uncertainty_adds_the_shift_of_refits_with_each_input_moved_both_ways(monkeypatch):
    """Each logged input (fuel rate, engine power through the torque, heater power) carries a 1 %
    calibration uncertainty. Its share of the posterior variance must be the square of the estimate's
    shift, measured here by refitting the log with that input scaled by 1.01 and by 0.99 (half the
    difference of the two refits, summed in quadrature over the three inputs); a fit without input
    uncertainty gives the variance the three shares are added to."""
    import calib.fit.thermal as thermal

    log, base, names = _log(), default_parameters(), list(TRUE)
    rel = thermal.INPUT_REL_SD
    assert rel == 0.01
    full = fit_thermal([log], base)
    share = dict.fromkeys(names, 0.0)
    for channel in ("fuel_rate_g_per_s", "engine_torque_Nm", "heater_power_W"):
        moved = []
        for sign in (1.0, -1.0):
            data = log.data.copy()
            data[channel] = data[channel] * (1.0 + sign * rel)
            moved.append(fit_thermal([DriveLog(data=data, meta=log.meta)], base).estimates)
        for n in names:
            share[n] += (0.5 * (moved[0][n].value - moved[1][n].value)) ** 2
    monkeypatch.setattr(thermal, "INPUT_REL_SD", 0.0)
    bare = fit_thermal([log], base)
    for n in names:
        assert share[n] > 0.05 * bare.estimates[n].stderr ** 2, n  # a share the comparison can see
        added = full.estimates[n].stderr ** 2 - bare.estimates[n].stderr ** 2
        assert added == pytest.approx(share[n], rel=0.02), n


@pytest.mark.filterwarnings("ignore:rel_change")
def test_initial_coolant_temperature_is_held_within_5_K_of_the_mean_of_the_first_five_samples():
    """The reference drive (coolant from -5 degC) with its first five samples reading 10 K warm (a sensor
    settling at key-on): the fitted initial temperature wants -5 degC but is held within 5 K of the mean of
    the first five valid samples, so it ends at that mean minus 5 K (six samples would move it 1.7 K)."""
    log = _log()
    T = log.data["coolant_temp_degC"].to_numpy().copy()
    T[0] = np.nan  # the first *valid* samples count
    T[1:6] += 10.0
    log.data["coolant_temp_degC"] = T
    fit = fit_thermal([log], default_parameters())
    assert fit.nuisance["T0_0"] == pytest.approx(float(np.mean(T[1:6])) - 5.0, abs=1e-6)


@pytest.mark.filterwarnings("ignore:rel_change")
def test_an_estimated_kappa_is_the_one_the_coolant_fit_uses():
    """The reference drive with kappa 0.5 (the prior is 0.3) and the engine-bay temperature logged over its
    last 300 samples (+-0.05 K of noise): kappa is estimated from the bay temperature, and the coolant fit, which sees only
    hA_eng (1 - kappa), returns hA_eng itself (34 W/K) only if it uses that kappa (with the prior's it would
    read 34 x 0.5 / 0.7 = 24.3 W/K)."""
    log = _log(bay_samples=300, kappa=0.5)
    log.data.loc[log.data.index[-300:], "bay_temp_degC"] += 0.05 * np.tile([1.0, -1.0], 150)  # sensor noise
    fit = fit_thermal([log], default_parameters(), allowed={"kappa", "C_eng_J_per_K", "gamma_exh", "hA_eng_W_per_K"})
    assert fit.estimates["kappa"].status == "estimated"
    assert fit.estimates["kappa"].value == pytest.approx(0.5, rel=1e-3)
    assert fit.estimates["hA_eng_W_per_K"].value == pytest.approx(TRUE["hA_eng_W_per_K"], rel=1e-3)


def test_radiator_advice_tells_a_coolant_that_never_got_there_from_one_the_model_does_not_fit():
    from calib.fit.advice import advise
    from calib.fit.toolkit import ParamEstimate, SubsystemFit

    fit = SubsystemFit("thermal", ("coolant_temp_degC",), logs=["a"])
    fit.estimates["T_open_degC"] = ParamEstimate("T_open_degC", 88.0, 4.0, "weak", "", prior=88.0, prior_sd=4.0,
                                                 informed=0.0)
    fit.estimates["k_rad_W_per_K"] = ParamEstimate("k_rad_W_per_K", 1500.0, 750.0, "weak", "", prior=1500.0,
                                                   prior_sd=750.0, informed=0.0)
    fit.metrics["coolant_max_degC"] = 72.0
    (a,) = [x for x in advise({"thermal": fit}) if "thermostat" in x]
    assert a.startswith("No log reaches the thermostat (coolant max 72 degC): T_open and k_rad come from the prior")
    fit.metrics["coolant_max_degC"] = 146.0  # FASTSim's engine: hot, with a radiator that cools only at a stop
    (a,) = [x for x in advise({"thermal": fit}) if "thermostat" in x]
    assert "reaches 146 degC, above the thermostat (88 degC)" in a and "No log reaches" not in a
    fit.estimates["T_open_degC"] = ParamEstimate("T_open_degC", 88.0, 0.5, "estimated", "", prior=88.0, prior_sd=4.0,
                                                 informed=0.9)
    (a,) = [x for x in advise({"thermal": fit}) if "thermostat" in x]
    assert "yet k_rad stays weakly informed" in a
