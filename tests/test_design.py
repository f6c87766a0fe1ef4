"""Optimal experiment design (calib.design): the search on a model with a closed-form optimal design, the
linear algebra, the artifact as a prior, and drive plans whose information follows the physics."""
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from calib.design.oed import (Infeasible, central_sensitivities, d_criterion, fisher, marginal_posterior,
                              posterior_cov, search)
from calib.errors import ParameterError

TAU = 10.0
DT = 0.1


def first_order(tau, u, T0=0.0):
    """dT/dt = (u - T) / tau, exact for an input held over each step of DT."""
    a = math.exp(-DT / tau)
    T = np.empty(u.size + 1)
    T[0] = T0
    for k, uk in enumerate(u):
        T[k + 1] = a * T[k] + (1 - a) * uk
    return T


def test_search_finds_the_corner_frequency_of_a_first_order_model():
    """Input u = sin(w t), |u| <= 1: the steady-state sensitivity of T to tau has amplitude
    w / (1 + w^2 tau^2), largest at w = 1/tau (closed form); the search over a grid of w finds it, and the
    information it computes is the closed form's."""
    t = np.arange(0, 80 * TAU, DT)
    settle = t >= 10 * TAU  # measured once the start transient has died out
    grid = np.geomspace(0.2 / TAU, 5.0 / TAU, 41)

    def evaluate(w):
        u = np.sin(w * t)
        S = central_sensitivities(lambda th: first_order(th[0], u)[:-1][settle], [TAU], [1e-4 * TAU])
        F = fisher(S, 0.1)
        return -float(F[0, 0]), F

    ranked = search(list(grid), evaluate)
    w_best = ranked[0].design
    assert abs(math.log(w_best * TAU)) <= math.log(grid[1] / grid[0]) / 2 + 1e-9
    n = int(settle.sum())
    for s in ranked[:5]:
        w = s.design
        closed = n / 2 * (w / (1 + (w * TAU) ** 2)) ** 2 / 0.1 ** 2
        assert -s.value == pytest.approx(closed, rel=0.03)


def test_search_finds_the_most_informative_sampling_time_of_a_step_response():
    """Step input from rest, one sample: dT/dtau = -(t/tau^2) exp(-t/tau), largest at t = tau."""
    u = np.ones(int(5 * TAU / DT))
    times = np.arange(1, u.size + 1)

    def evaluate(k):
        S = central_sensitivities(lambda th: first_order(th[0], u)[[k]], [TAU], [1e-5])
        return -float(fisher(S, 1.0)[0, 0]), None

    best = search(list(times), evaluate)[0].design
    assert best * DT == pytest.approx(TAU, abs=DT)


def test_posterior_cov_and_marginal_agree_with_direct_inverses():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(4, 4))
    P0 = A @ A.T + 0.1 * np.eye(4)
    S = rng.normal(size=(50, 4))
    F = fisher(S, 0.5)
    direct = np.linalg.inv(np.linalg.inv(P0) + F)
    assert np.allclose(posterior_cov(P0, F), direct, rtol=1e-8, atol=1e-12)
    # a nuisance with a flat prior: the marginal of the first two is the Schur complement
    S2 = rng.normal(size=(60, 3))
    F2 = fisher(S2, 1.0)
    P = np.diag([2.0, 3.0, np.inf])
    prec = F2 + np.diag([0.5, 1 / 3, 0.0])
    schur = prec[:2, :2] - np.outer(prec[:2, 2], prec[2, :2]) / prec[2, 2]
    assert np.allclose(marginal_posterior(P, F2, [0, 1]), np.linalg.inv(schur), rtol=1e-6)
    assert d_criterion(np.diag([2.0, 3.0])) == pytest.approx(math.log(6.0))


def test_search_puts_infeasible_designs_last_with_their_reason():
    def ev(x):
        if x > 2:
            raise Infeasible(f"{x} is too much")
        return -x, None

    r = search([1, 3, 2], ev)
    assert [s.design for s in r] == [2, 1, 3] and r[-1].infeasible == "3 is too much"


# ------------------------------------------------------------------------------------------ artifacts
def write_artifact(path, sd_frac=None, noise=0.6):
    """A calibration artifact as `iptm calibrate` writes it, for the default Prius with given posterior sd
    (fraction of the prior sd) of the designable parameters."""
    from calib.design.prior import DESIGNABLE
    from calib.model.params import default_parameters, prior_sd_of

    ps = default_parameters()
    sd_frac = sd_frac or {}
    for names in DESIGNABLE.values():
        for n in names:
            p = ps.param(n)
            psd = float(prior_sd_of(p))
            f = sd_frac.get(n, 0.1)
            p.prior_sd, p.prior_value, p.stderr, p.status = psd, p.value, f * psd, "estimated"
    d = ps.to_dict()
    d["calibration"] = {"subsystems": {
        "thermal": {"logs": ["a"], "metrics": {"noise_sd_degC": noise}},
        "cabin": {"logs": ["a"], "metrics": {"noise_sd_degC": noise}}}}
    path.write_text(json.dumps(d))
    return path


def test_artifact_prior_ranks_weak_parameters_and_refuses_other_files(tmp_path):
    from calib.design.prior import ArtifactPrior

    art = write_artifact(tmp_path / "cal.json", {"T_open_degC": 0.95, "k_rad_W_per_K": 0.8, "gamma_exh": 0.5})
    ap = ArtifactPrior.load(art)
    assert ap.weakest() == ["T_open_degC", "k_rad_W_per_K"]
    assert ap.weakest(5) == ["T_open_degC", "k_rad_W_per_K"]  # only those the calibration calls weak
    assert ap.noise["thermal"][0] == 0.6
    d = json.loads(art.read_text())
    d["calibration"]["subsystems"]["thermal"]["metrics"] = "damaged"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(d))
    with pytest.raises(ParameterError, match=r"\[calibration.subsystems.thermal.metrics\] is not a table"):
        ArtifactPrior.load(bad)
    plain = tmp_path / "params.json"
    plain.write_text(json.dumps({"parameters": {}}))
    with pytest.raises(ParameterError, match="not a calibration artifact"):
        ArtifactPrior.load(plain)


def test_planner_refuses_targets_it_cannot_design_for(tmp_path):
    from calib.design.drive import Planner
    from calib.design.prior import ArtifactPrior

    ap = ArtifactPrior.load(write_artifact(tmp_path / "cal.json"))
    with pytest.raises(ParameterError, match="fuel_scale: a drive plan can target"):
        Planner(ap, ["fuel_scale"])


@pytest.fixture(scope="module")
def prior(tmp_path_factory):
    from calib.design.prior import ArtifactPrior

    frac = {n: 0.9 for n in ("T_open_degC", "k_rad_W_per_K", "C_eng_J_per_K", "gamma_exh", "hA_eng_W_per_K")}
    return ArtifactPrior.load(write_artifact(tmp_path_factory.mktemp("a") / "cal.json", frac))


def _ratio(planner, design, target):
    value, info = planner.evaluate(design)
    return info["sd"][target] / planner.prior.sd[target]


def test_thermostat_is_informed_only_by_a_drive_that_reaches_it(prior):
    """A cold urban drive at -10 degC never warms the coolant to the thermostat: T_open keeps (almost) its sd;
    a highway drive does, and narrows it."""
    from calib.design.drive import Design, Planner

    pl = Planner(prior, ["T_open_degC"])
    urban = _ratio(pl, Design(("nycc",), 0.0, "auto", -10.0, -10.0), "T_open_degC")
    fast = _ratio(pl, Design(("hwfet", "us06"), 0.0, "auto", 20.0, 20.0), "T_open_degC")
    assert urban > 0.95
    assert fast < 0.5


def test_heater_off_window_separates_heat_capacity_from_exhaust_fraction(prior):
    """The calibration's advice: with the heater off for a while, the heater's draw no longer moves with the
    coolant and C_eng separates from gamma_exh. The same trace with the heater switched off scores better."""
    from calib.design.drive import Design, Planner

    pl = Planner(prior, ["C_eng_J_per_K", "gamma_exh"], comfort_min=10.0)  # physics here, not comfort
    on, _ = pl.evaluate(Design(("us06", "hwfet"), 0.0, "auto", -5.0, -5.0))
    off, _ = pl.evaluate(Design(("us06", "hwfet"), 0.0, "off 300 s at 50 %", -5.0, -5.0))
    assert off < on


def test_make_plan_picks_the_best_candidate_and_writes_a_playable_csv(prior, tmp_path):
    import pandas as pd

    from calib.design.drive import Design, Planner, make_plan, plan_frame, plot_plan, write_plan_csv
    from calib.model.cycles import load_cycle

    seqs = [(("nycc",), 2.0), (("us06",), 0.0), (("wltc_extrahigh",), 278.0)]
    plan = make_plan(prior, ["T_open_degC", "k_rad_W_per_K"], minutes=10, ambient=-5.0, soaks=[-5.0, 40.0],
                     sequences_override=seqs)
    pl = Planner(prior, ["T_open_degC", "k_rad_W_per_K"])
    assert plan.value == pytest.approx(pl.evaluate(plan.design)[0])
    every = search([Design(s, p, h, c, -5.0) for s, p in seqs for h in ("auto", "off 300 s at 50 %")
                    for c in (-5.0, 40.0)], pl.evaluate)
    feasible = [x.value for x in every if not x.infeasible]
    assert feasible and plan.value <= min(feasible) + 1e-12
    out = tmp_path / "plan.csv"
    write_plan_csv(plan, out)
    df = pd.read_csv(out, comment="#")
    assert list(df.columns)[:4] == ["time_s", "speed_kph", "heater_on", "segment"]
    assert df["time_s"].iloc[-1] == pytest.approx(600.0)
    assert set(df["heater_on"]) <= {0, 1}
    cyc = load_cycle(str(out))  # a cycle file the simulator and a dyno can play
    assert cyc.n_steps == len(df) - 1
    assert plan_frame(plan)["speed_kph"].max() > 0
    for r in plan.table():
        assert 0 < r["ratio"] <= 1.0
    plot_plan(plan, tmp_path / "plan.png")
    assert (tmp_path / "plan.png").stat().st_size > 10_000


def test_comfort_floor_rejects_a_cold_cabin_after_it_was_warm():
    from calib.design.drive import comfort_violation

    assert comfort_violation(np.array([0.0, 10.0, 19.0, 20.0, 17.0])) == ""
    assert "falls to 12.0" in comfort_violation(np.array([0.0, 19.0, 12.0]))


def test_cli_plan_refuses_a_non_artifact_with_one_line(tmp_path):
    bad = tmp_path / "x.toml"
    bad.write_text("[parameters]\n")
    r = subprocess.run([sys.executable, "-m", "iptm.cli", "plan", str(bad), "--ambient", "-5"], capture_output=True,
                       text=True)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "not a calibration artifact" in r.stderr


def test_cli_plan_writes_the_plan(tmp_path):
    art = write_artifact(tmp_path / "cal.json", {"T_open_degC": 0.9})
    out = tmp_path / "p.csv"
    r = subprocess.run([sys.executable, "-m", "iptm.cli", "plan", str(art), "--minutes", "10", "--ambient", "-5",
                        "--target", "T_open_degC", "-o", str(out), "--quiet", "--json", str(tmp_path / "p.json")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "T_open_degC:" in r.stdout and out.exists()
    js = json.loads((tmp_path / "p.json").read_text())
    assert js["targets"][0]["name"] == "T_open_degC" and js["targets"][0]["ratio"] < 1.0


def test_dashboard_plan_page_designs_a_drive_from_the_session_calibration(tmp_path, monkeypatch):
    from pathlib import Path

    from streamlit.testing.v1 import AppTest

    monkeypatch.setenv("IPTM_SESSION_ROOT", str(tmp_path / "sessions"))

    from iptm import dashboard as dash

    art = write_artifact(tmp_path / "cal.toml.json", {"T_open_degC": 0.9, "k_rad_W_per_K": 0.8})
    at = AppTest.from_file(str(Path(__file__).resolve().parents[1] / "pages" / "plan.py"), default_timeout=300)
    at.run()
    assert not at.exception
    assert any("upload a calibration artifact" in str(r.options) for r in at.radio)
    # a calibration in the session (the artifact the Calibrate page keeps); a JSON artifact read as TOML fails
    at.session_state[dash.CALIB] = {"artifact": art.read_bytes()}
    at.run()
    at.radio(key="plan_source").set_value("calibrated in this session").run()
    assert any("Not usable" in e.value for e in at.error)
    from calib.model.params import ParameterSet

    toml = tmp_path / "cal.toml"
    import tomli_w

    d = json.loads(art.read_text())
    toml.write_text(tomli_w.dumps(ParameterSet.from_dict(d).to_dict() | {"calibration": d["calibration"]}))
    at.session_state[dash.CALIB] = {"artifact": toml.read_bytes()}
    at.run()
    assert not at.exception and not at.error
    at.number_input(key="plan_minutes").set_value(10.0)
    at.number_input(key="plan_ambient").set_value(-5.0)
    at.text_input(key="plan_soaks").set_value("-5")
    at.button(key="plan_run").click()
    at.run()
    assert not at.exception and not at.error, [e.value for e in at.error]
    assert any("predicted posterior sd" in c.value for c in at.code)


def test_dyno_plan_soaks_the_cell_and_needs_its_temperatures(prior):
    from calib.design.drive import make_plan

    with pytest.raises(ParameterError, match="--dyno: give the candidate cell soak temperatures"):
        make_plan(prior, ["T_open_degC"], minutes=20, dyno=True)
    plan = make_plan(prior, ["T_open_degC"], minutes=20, dyno=True, soaks=[-20.0, 0.0], heater=False,
                     sequences_override=[(("hwfet",), 435.0), (("nycc",), 602.0)])
    d = plan.design
    assert d.dyno and d.T_amb == d.T_cl0 and d.T_amb in (-20.0, 0.0) and d.heater == "auto"
    assert plan.sim.t[-1] == pytest.approx(1200.0)


def test_standard_cut_and_doc_block(tmp_path):
    from calib.errors import IptmError
    from calib.model.cycles import load_cycle
    from iptm.benchmarks.plan import render_doc, standard_cut

    hw = load_cycle("hwfet").v
    c = standard_cut("hwfet", 1200)
    assert c.n_steps == 1200 and np.array_equal(c.v[:hw.size], hw) and np.array_equal(c.v[hw.size:], hw[:1201 - hw.size])
    page = tmp_path / "p.md"
    page.write_text("a\n<!-- figures:plan-bench -->\nold\n<!-- /figures:plan-bench -->\nb\n")
    render_doc(page, "new table")
    assert "new table" in page.read_text() and "old" not in page.read_text()
    page.write_text("no block\n")
    with pytest.raises(IptmError, match="no <!-- figures:plan-bench -->"):
        render_doc(page, "x")


def test_prediction_on_a_log_agrees_with_the_prediction_on_its_simulation(prior):
    """The same linearisation fed with a logger's view of a drive (noise, quantisation, dropouts, inputs as
    the fits read them) gives the sd it gives on the simulation the log was sampled from."""
    from calib.design.drive import Planner, log_inputs
    from calib.ingest import to_drivelog
    from calib.synth import Scenario, synthesise

    sc = Scenario("design_check", "us06+hwfet", -5.0, 0.6, -5.0, -5.0, T_bat=-5.0)
    sim, streams, meta = synthesise(sc, prior.params, seed=1)
    pl = Planner(prior, ["T_open_degC", "hA_eng_W_per_K", "C_cab_J_per_K"])
    on_sim = pl.predict(sim)["sd"]
    on_log = pl.predict(inputs=log_inputs(to_drivelog(streams, meta), prior.params))["sd"]
    for t in on_sim:
        assert on_sim[t] < 0.9 * prior.sd[t]  # the drive informs each of them
        assert on_log[t] == pytest.approx(on_sim[t], rel=0.05), t
