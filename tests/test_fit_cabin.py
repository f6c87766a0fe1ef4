"""Cabin and heater-core fit: truth recovery, Q_sun with truth 0 undetermined, missing channels."""
import functools

import pytest

from calib.fit.cabin import fit_cabin
from calib.ingest import to_drivelog
from calib.model.params import default_parameters
from calib.synth import Scenario, draw_truth, synthesise

FIT = [Scenario("cold", "udds", -10.0, 0.60, -10.0, -10.0, T_bat=-5.0, with_bay_temp=True),
       Scenario("warm", "hwfet", -5.0, 0.55, 65.0, 15.0, T_bat=5.0)]


@functools.lru_cache(maxsize=None)
def logs_for(seed, drop=()):
    truth = draw_truth(seed)
    out = []
    for sc in FIT:
        sc = Scenario(**{**sc.__dict__, "drop_channels": list(drop)})
        out.append(to_drivelog(*synthesise(sc, truth, seed=seed)[1:]))
    return truth, out


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_cabin_recovers_truth(seed):
    truth, logs = logs_for(seed)
    fit = fit_cabin(logs, default_parameters())
    for n in ("C_cab_J_per_K", "UA_cab_W_per_K", "eps_hc"):
        e = fit.estimates[n]
        assert e.status == "estimated", (n, e.note)
        tv = truth[n]
        assert abs(e.value - tv) <= 3 * e.stderr, (n, e.value, e.stderr, tv)
        assert abs(e.value - tv) <= 0.1 * abs(tv), (n, e.value, tv)
    # truth Q_sun is 0: the posterior holds it within its (posterior) uncertainty
    q = fit.estimates["Q_sun_W"]
    assert abs(q.value) <= 3 * q.stderr and q.stderr < q.prior_sd


def test_cabin_without_cabin_temperature_is_not_fitted():
    truth, logs = logs_for(1, drop=("cabin_temp_degC",))
    fit = fit_cabin(logs, default_parameters())
    for n in ("C_cab_J_per_K", "UA_cab_W_per_K", "Q_sun_W"):
        assert fit.estimates[n].status == "prior"
        assert "cabin_temp_degC" in fit.estimates[n].note
    # eps_hc needs vent/coolant/blower only
    assert fit.estimates["eps_hc"].status == "estimated"


def test_eps_without_vent_temperature_is_not_fitted():
    truth, logs = logs_for(1, drop=("vent_temp_degC",))
    fit = fit_cabin(logs, default_parameters())
    assert fit.estimates["eps_hc"].status == "prior"
    assert "vent_temp_degC" in fit.estimates["eps_hc"].note


# ---------------------------------------------------------------------------------------------------
# eps_hc on hand-made vent/coolant logs (no cabin channel: the heater inlet air is the ambient), against
# the documented rule worked out here in closed form: binding samples = the upper cluster of
# r = (T_vent - T_in) / (T_cl - T_in) reached from its 90th percentile, within 3 noise sd
# s_r = 0.35 sqrt(1 + r^2) / (T_cl - T_in) of the estimate; eps = their 1/s_r^2-weighted mean
# ---------------------------------------------------------------------------------------------------
T_AMB = -10.0


def _vent_log(x, r):
    import numpy as np
    import pandas as pd

    from calib.drivelog import DriveLog, LogMeta

    x, r = np.asarray(x, float), np.asarray(r, float)
    d = pd.DataFrame({"ambient_temp_degC": T_AMB, "coolant_temp_degC": T_AMB + x, "vent_temp_degC": T_AMB + r * x,
                      "blower_flow_kg_per_s": 0.05}, index=pd.Index(np.arange(x.size, dtype=float), name="time_s"))
    return DriveLog(data=d, meta=LogMeta(source="hand-made vent log", format="test", synthetic=True))


def _weighted(x, ys, counts):
    """1/s_r^2-weighted mean of the ratios y / x of clusters (all samples at coolant - inlet = x)."""
    import numpy as np

    r = np.asarray(ys, float) / x
    w = np.asarray(counts) / (0.35 * np.sqrt(1 + r ** 2) / x) ** 2
    return float(w @ r / w.sum())


# ratio clusters 0.30, 0.62, 0.66, 0.70 (400, 100, 409, 91 samples, in that order in time), all 50 K of
# coolant above the inlet air: the 90th percentile is in the 0.66 cluster (the 91st in the 0.70 one);
# 3 s_r is about 0.025, so 0.66 and 0.70 bind together and 0.62 does not
CLUSTERS = ((0.30, 400), (0.62, 100), (0.66, 409), (0.70, 91))


def _cluster_log():
    import numpy as np

    r = np.concatenate([np.full(n, v) for v, n in CLUSTERS])
    return _vent_log(np.full(r.size, 50.0), r)


def test_eps_is_the_weighted_mean_of_the_binding_cluster():
    from calib.fit.cabin import _eps
    from calib.fit.toolkit import SubsystemFit

    fit = SubsystemFit("t", ())
    (eps, se, nb), msg = _eps([_cluster_log()], default_parameters(), fit)
    assert msg == "" and nb == 409 + 91
    assert fit.metrics == {"eps_binding_samples": 500, "eps_candidate_samples": 1000}
    assert eps == pytest.approx(_weighted(50.0, [33.0, 35.0], [409, 91]), rel=1e-12)
    assert eps == pytest.approx(0.667061, abs=1e-6)


def test_eps_standard_error_inflated_for_correlated_residuals_and_sensor_offsets():
    """The binding residuals are two constant runs (one per cluster): the batch-means estimate of their
    autocorrelation time (blocks of 22 samples), a lower bound of the one applied, inflates the iid
    standard error; the 0.5 K offset of each sensor adds the change of eps it causes, in quadrature."""
    import numpy as np

    from calib.fit.cabin import _eps
    from calib.fit.toolkit import T_SENSOR_SD, SubsystemFit, inflation

    lg = _cluster_log()
    (eps, se0, _), _ = _eps([lg], default_parameters(), SubsystemFit("t", ()), _propagate=False)
    res = np.r_[np.full(409, 33.0 - eps * 50), np.full(91, 35.0 - eps * 50)]
    se_iid = np.sqrt(np.sum(res ** 2) / 499 / (500 * 50.0 ** 2))
    r0 = res - res.mean()
    tau_bm = 22 * np.var(r0[:484].reshape(22, 22).mean(axis=1)) / np.mean(r0 ** 2)
    assert tau_bm > 5
    assert se0 >= se_iid * np.sqrt(499 / (500 / tau_bm - 1)) * (1 - 1e-12)
    assert se0 == pytest.approx(se_iid * inflation([res], 1), rel=1e-9)  # inflation: tests/test_fit_toolkit.py
    (_, se, _), _ = _eps([lg], default_parameters(), SubsystemFit("t", ()))
    d_cl = _weighted(50.0 + T_SENSOR_SD, [33.0, 35.0], [409, 91]) - eps
    d_vent = _weighted(50.0, [33.0 + T_SENSOR_SD, 35.0 + T_SENSOR_SD], [409, 91]) - eps
    assert se == pytest.approx(np.sqrt(se0 ** 2 + d_cl ** 2 + d_vent ** 2), rel=1e-9)


def test_eps_candidates_have_the_coolant_at_least_10_K_above_the_inlet_air():
    import numpy as np

    from calib.fit.cabin import _eps
    from calib.fit.toolkit import SubsystemFit

    # 70 samples exactly 10 K above (candidates), 30 at 9.5 K (not)
    lg = _vent_log(np.r_[np.full(70, 10.0), np.full(30, 9.5)], np.full(100, 0.7))
    fit = SubsystemFit("t", ())
    (eps, _, nb), _ = _eps([lg], default_parameters(), fit)
    assert fit.metrics["eps_candidate_samples"] == 70 and nb == 70
    assert eps == pytest.approx(0.7, rel=1e-12)
    # 50 candidates: fewer than the 60 needed, said before any estimate is tried
    lg = _vent_log(np.r_[np.full(50, 10.0), np.full(100, 9.0)], np.full(150, 0.7))
    out, msg = _eps([lg], default_parameters(), SubsystemFit("t", ()))
    assert out is None and msg.startswith("fewer than 60 samples")
    out, msg = _eps([_vent_log(np.full(100, 5.0), np.full(100, 0.7))], default_parameters(), SubsystemFit("t", ()))
    assert out is None and msg.startswith("fewer than 60 samples")


def test_eps_note_names_missing_channels_only_when_no_log_has_them():
    """One short log with every eps channel (30 samples: too few) and one without vent temperature: the
    channels are there in one log, so the note gives the real reason (too few samples), not 'missing'."""
    import numpy as np

    short = _vent_log(np.full(30, 50.0), np.full(30, 0.66))
    no_vent = _vent_log(np.full(200, 50.0), np.full(200, 0.66))
    no_vent.data = no_vent.data.drop(columns=["vent_temp_degC"])
    fit = fit_cabin([short, no_vent], default_parameters(), allowed=["eps_hc"])
    note = fit.estimates["eps_hc"].note
    assert "fewer than 60 samples" in note and "missing channel" not in note
    # with the channel in no log, the note names it
    fit2 = fit_cabin([no_vent], default_parameters(), allowed=["eps_hc"])
    assert "missing channel(s) vent_temp_degC" in fit2.estimates["eps_hc"].note


def _cooldown_log(**heater):
    """A cabin cooling from 20 degC at -10 degC ambient with no heat (eq. 10 integrated here by explicit
    Euler at 1 s: C_cab = 80 kJ/K, UA_cab = 40 W/K, Q_sun = 0), plus the heater channels given."""
    import numpy as np
    import pandas as pd

    from calib.drivelog import DriveLog, LogMeta

    n = 1800
    T = np.empty(n)
    T[0] = 20.0
    for k in range(n - 1):
        T[k + 1] = T[k] + 40.0 * (T_AMB - T[k]) / 80e3
    d = pd.DataFrame({"cabin_temp_degC": T, "ambient_temp_degC": T_AMB, **heater},
                     index=pd.Index(np.arange(n, dtype=float), name="time_s"))
    return DriveLog(data=d, meta=LogMeta(source="hand-made cooldown", format="test", synthetic=True))


def test_eps_iteration_stops_only_below_3_binding_samples():
    """Ratios 0.30 (54 samples) and 0.60, 0.62, 0.64, 0.90, 0.92, 0.97, all 50 K above the inlet air (3 s_r
    about 0.027): the 90th percentile 0.33 binds the six high ones, their weighted mean 0.752 binds 0.90,
    0.92 and 0.97, three, which still give an estimate: 0.929, which binds 0.92 and 0.97 only (0.90 is
    below 0.929 - 0.028). Two binding samples end the iteration, and the fit is refused with that count."""
    import numpy as np

    from calib.fit.cabin import _eps
    from calib.fit.toolkit import SubsystemFit

    r = np.r_[np.full(54, 0.30), [0.60, 0.62, 0.64, 0.90, 0.92, 0.97]]
    fit = SubsystemFit("t", ())
    out, msg = _eps([_vent_log(np.full(r.size, 50.0), r)], default_parameters(), fit)
    assert out is None and msg == "the heater-core limit bound in only 2 samples (need 60)"
    assert fit.metrics == {"eps_binding_samples": 2, "eps_candidate_samples": 60}


def test_eps_candidates_need_a_blower_flow_above_5_g_per_s():
    """Air through the heater core: samples with the blower at exactly 5 g/s (its off threshold) are no
    candidates, those at 5.1 g/s are (70 at 5.1 g/s with ratio 0.7; 30 at 5.0 g/s with ratio 0.9, which would
    bind and pull the estimate up)."""
    import numpy as np

    from calib.fit.cabin import _eps
    from calib.fit.toolkit import SubsystemFit

    lg = _vent_log(np.full(100, 40.0), np.r_[np.full(70, 0.7), np.full(30, 0.9)])
    lg.data["blower_flow_kg_per_s"] = np.r_[np.full(70, 0.0051), np.full(30, 0.005)]
    fit = SubsystemFit("t", ())
    (eps, _, nb), _ = _eps([lg], default_parameters(), fit)
    assert fit.metrics["eps_candidate_samples"] == 70 and nb == 70
    assert eps == pytest.approx(0.7, rel=1e-12)


def test_initial_cabin_temperature_is_held_within_5_K_of_the_mean_of_the_first_five_samples():
    """The cooldown from 20 degC with its first five samples reading 30 degC (a sensor settling at key-on):
    the fitted initial temperature wants 20 degC but is held within 5 K of the mean of the first five valid
    samples, 30 degC, so it ends at the window's lower edge, 25 degC (six samples would put it at 23.3)."""
    import numpy as np

    log = _cooldown_log(heater_power_W=0.0)
    T = log.data["cabin_temp_degC"].to_numpy().copy()
    T[0] = np.nan  # the first *valid* samples count
    T[1:6] = 30.0
    log.data["cabin_temp_degC"] = T
    fit = fit_cabin([log], default_parameters(), allowed={"C_cab_J_per_K", "UA_cab_W_per_K"})
    assert fit.nuisance["Tc0_0"] == pytest.approx(25.0, abs=1e-6)
