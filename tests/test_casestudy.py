"""A small case study (short cycle, coarse grids): ordering, table, figures, JSON round trip."""
import json

import numpy as np
import pytest

from optimize.casestudy import run_case_study
from optimize.formulations.scenario import DPGrids, DPScenario

SCEN = DPScenario(duration_s=200.0)  # warm start as in the paper (cold starts: see report)
GRIDS = DPGrids(soc=0.01, tcl=2.0, tcab=1.0, pbat=1000.0, qheat=150.0)
TIE_G = 1e-6  # ordering tie tolerance (g)


@pytest.fixture(scope="module")
def cs(params):
    return run_case_study(params, SCEN, progress=False, grids=GRIDS)


def test_ordering(cs):
    """The ordering statement is computed from the corrected fuel, and each DP's V_0(x0) is reported."""
    f = {k: s.summary()["fuel_corrected_g"] for k, s in cs.sims.items()}
    keys = ["rule", "baseline", "thermal", "thermal_cabin"]
    holds = all(f[a] >= f[b] for a, b in zip(keys, keys[1:]))
    assert cs.ordering_ok() == holds
    st = cs.ordering_statement()
    assert ("holds" in st and "NOT" not in st) == holds
    assert f"{f['thermal']:.2f}" in st
    assert "grid error" not in st  # no convergence check, no grid error
    # Thermal-Cabin-DP generalises Thermal-DP (1500 W is on its heater grid): on its own objective it is
    # at most Thermal-DP's run, up to a grid tie band
    from optimize.formulations.solve import dp_objective

    tm = cs.outcomes["thermal_cabin"].extra["T_cab_terminal_min"]
    j = {k: dp_objective(cs.sims[k].mp, cs.sims[k], SCEN, 3, tm) for k in ("thermal", "thermal_cabin")}
    assert j["thermal_cabin"] <= j["thermal"] + 0.002 * abs(j["thermal"])
    assert all(s.soc[-1] >= SCEN.soc0 - SCEN.soc_tol for s in cs.sims.values())
    vc = cs.value_check()
    assert set(vc) == {"baseline", "thermal", "thermal_cabin"}
    assert "V_0(x0)" in cs.format_value_check()


def test_table_columns(cs):
    df = cs.table()
    for c in ["fuel_g", "fuel_corrected_g", "soc_final", "T_cl_final_degC", "T_cl_mean_degC",
              "T_cab_final_degC", "T_cab_mean_degC", "engine_starts", "idle_s", "saving_vs_rule_pct",
              "paper_vs_rule_pct", "saving_vs_baseline_pct", "paper_vs_baseline_pct", "raw_saving_vs_rule_pct",
              "raw_saving_vs_baseline_pct"]:
        assert c in df.columns
    assert len(df) == 5
    assert df.loc["Rule-based (tuned)", "saving_vs_rule_pct"] == 0.0
    assert df["charge_sustaining"].all()
    assert "sav/rule%" in cs.format_table()


def test_figures(cs, tmp_path):
    paths = cs.plot(tmp_path / "figs")
    names = {p.rsplit("/", 1)[-1] for p in paths}
    assert names == {f"{n}.png" for n in ("soc", "coolant", "engine_power", "battery_power", "engine_mode",
                                          "cumulative_fuel", "cabin", "heater_power", "fuel_bars")}
    for p in paths:
        with open(p, "rb") as fh:
            assert fh.read(8) == b"\x89PNG\r\n\x1a\n"


def test_json_roundtrip(cs, tmp_path):
    from calib.fileio import write_json

    d = cs.to_dict()
    p = tmp_path / "cs.json"
    write_json(p, d)
    back = json.loads(p.read_text())
    assert back["scenario"] == SCEN.to_dict()
    assert [r["key"] for r in back["table"]] == [r["key"] for r in d["table"]]
    fuel = {r["key"]: r["fuel_g"] for r in back["table"]}
    assert fuel["thermal"] == pytest.approx(cs.sims["thermal"].fuel_g, rel=1e-12)
    assert np.isfinite(back["dp"]["thermal"]["evals_per_second"])


def test_cli_optimize(tmp_path, capsys):
    from iptm.cli import main

    # coolant above the catalyst-heating threshold: the DP has no catalyst-heating mode, so after a start
    # below it the rule-based run's coolant (50 s of catalyst heating) is not a target the DP can be held to
    rc = main(["optimize", "--duration", "60", "--tcl0", "62", "--formulation", "rule,baseline,thermal",
               "--grid", "pbat=2000,tcl=2", "--terminal", "match", "--json", str(tmp_path / "o.json")])
    out = capsys.readouterr().out
    assert rc == 0
    assert "Thermal-DP" in out and "paper%" in out and "terminal match" in out and "V_0(x0)" in out
    d = json.loads((tmp_path / "o.json").read_text())
    assert d["table"] and d["terminal"] == "match"
    # match: Thermal-DP's final coolant is at least the tuned rule-based run's
    t_cl = {r["key"]: r["T_cl_final_degC"] for r in d["table"]}
    assert t_cl["thermal"] >= t_cl["rule"] - 1e-6
    assert main(["optimize", "--formulation", "nope"]) == 2


def test_cli_params_file_and_scenario_file(params, tmp_path, capsys):
    """A parameter file (as a calibration artifact is) and a TOML scenario file drive `iptm optimize`."""
    from iptm.cli import main

    p = tmp_path / "calibrated.toml"
    params.with_values(C_eng_J_per_K=60e3).save(p)
    sc = tmp_path / "scen.toml"
    sc.write_text('[scenario]\ncycle = "nycc"\nT_amb = -5.0\nduration_s = 60.0\n')
    rc = main(["optimize", "--params", str(p), "--scenario", str(sc), "--formulation", "baseline,thermal",
               "--grid", "pbat=2000"])
    out = capsys.readouterr().out
    assert rc == 0 and "nycc" in out and "-5 degC" in out
    rc = main(["optimize", "--params", str(p), "--duration", "30", "--formulation", "baseline", "--convergence",
               "--grid", "pbat=2000"])
    assert rc == 0 and "change %" in capsys.readouterr().out


def test_cli_optimize_no_hold_drops_the_hold_control(tmp_path, capsys):
    """``--no-hold`` solves Thermal-Cabin-DP on the heater grid alone: one control fewer per power control
    (the printed control count), and a separate cache entry from the default run."""
    import re

    from iptm.cli import main

    args = ["optimize", "--duration", "20", "--formulation", "thermal_cabin", "--cache", str(tmp_path / "c"),
            "--grid", "soc=0.02,tcl=4,pbat=2500,qheat=200"]
    counts = {}
    for extra in ([], ["--no-hold"]):
        assert main(args + extra) == 0
        out = capsys.readouterr().out
        m = re.search(r"thermal_cabin: (\d+) states x (\d+) controls", out)
        assert m and "(from the cache)" not in out, out
        counts[bool(extra)] = int(m.group(2))
    n_heat = 4  # 1200:200:1800 W
    assert counts[False] * n_heat == counts[True] * (n_heat + 1)


def test_ordering_names_steps_within_the_measured_grid_error(cs):
    """With convergence rows, a step of the ordering closer than the sum of its two strategies' changes on
    halving is named with that error; a step farther apart is not."""
    from copy import copy

    f = {k: s.summary()["fuel_corrected_g"] for k, s in cs.sims.items()}
    gap = abs(f["rule"] - f["baseline"])
    c = copy(cs)
    c.convergence = [{"formulation": "baseline", "fuel_corrected_g": 100.0, "fuel_corrected_g_half": 100.0 - 2 * gap - 0.01},
                     {"formulation": "thermal", "fuel_corrected_g": 100.0, "fuel_corrected_g_half": 100.0}]
    st = c.ordering_statement()
    assert f"rule - baseline = {f['rule'] - f['baseline']:+.2f} g is within the grid error {2 * gap + 0.01:.2f} g" in st
    # thermal's change on halving is 0 and thermal_cabin has no row: that step has no grid error to name
    assert f["thermal"] != f["thermal_cabin"] and "thermal - thermal_cabin" not in st
