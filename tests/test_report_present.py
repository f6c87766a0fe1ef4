"""What the command line, the report and the dashboard say about a run is decided once (iptm.present): the
count of estimated parameters, the subsystems left at their priors, "not scored" for a channel a log lacks,
the converged and preview grids, the ordering advice; the main job shows one progress line per stage; a DP's
per-step progress reaches the display."""
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from calib.model.params import default_parameters
from iptm import pipeline, present
from iptm.report import validation_rows
from optimize.formulations.scenario import DEFAULT_GRIDS, FORMULATIONS, GRID_AXES, DPGrids, DPScenario, FormulationGrids


def _calibrated():
    ps = default_parameters()
    for n in ps:
        ps.param(n).status = "prior"
    ps.param("C_bat_Ah").status = "estimated"
    ps.param("kappa").status = "weak"
    table = next(n for n in ps if ps.param(n).is_table)
    p = ps.param(table)
    p.status = "estimated"
    p.entry_status = ["estimated"] + ["weak"] * (len(p.value) - 1)
    return ps, table


def test_one_count_of_estimated_parameters():
    """A table with some entries estimated counts as estimated (the report's 17), and is named as partly
    determined; the Calibrate page no longer counts only the fully estimated ones (its old 13)."""
    ps, _ = _calibrated()
    c = present.parameter_counts(ps)
    assert (c["estimated"], c["partly"], c["weak"]) == (2, 1, 1)
    assert c["prior"] == len(list(ps)) - 3
    assert present.counts_text(c) == ("2 parameters estimated (1 of them tables with only some entries "
                                      "determined), 1 weakly informed (posterior mostly the prior)")


def test_every_subsystem_left_at_its_priors_is_named_with_why():
    cal = {"calibration": {"subsystems": {
        "battery": {"logs": ["a.csv"], "message": None},
        "fuel": {"logs": [], "message": "no log has fuel rate (a.csv: missing channel(s) fuel_rate_g_per_s)",
                 "skipped": {"a.csv": "missing channel(s) fuel_rate_g_per_s"}},
        "thermal": {"logs": [], "skipped": {"a.csv": "missing channel(s) coolant_temp_degC"}}}}}
    subs = present.subsystems_at_prior(cal)
    assert [s["subsystem"] for s in subs] == ["fuel", "thermal"]
    assert "a.csv: missing channel(s) coolant_temp_degC" in subs[1]["reason"]
    lines = present.prior_banner(cal)
    assert len(lines) == 2 and lines[0].startswith("fuel parameters (") and "fuel_scale" in lines[0]
    assert "no log has fuel rate" in lines[0]
    # the section alone reads the same
    assert present.subsystems_at_prior(cal["calibration"]) == subs


class _Log:
    def __init__(self, channels):
        self.channels = set(channels)

    def has(self, name):
        return name in self.channels


def test_a_channel_the_log_lacks_is_not_scored():
    """The replay takes the measured fuel rate as zero where the engine is stopped: without a fuel-rate
    channel that would read RMSE 0, bias +0. It reads "not scored", naming the missing channel."""
    m = {"soc": {"rmse": 0.0015, "max_abs": 0.004, "bias": 0.0002, "unit": "-"},
         "fuel_rate": {"rmse": 0.0, "max_abs": 0.0, "bias": 0.0, "unit": "g/s"},
         "cumulative_fuel": {"measured_g": 0.0, "simulated_g": 0.0, "error_pct": float("nan")}}
    log = _Log(["soc", "coolant_temp_degC"])
    rows = {r["channel"]: r for r in present.channel_scores(m, log)}
    assert rows["soc"]["scored"] and rows["soc"]["rmse"] == 0.0015
    assert not rows["fuel_rate"]["scored"] and rows["fuel_rate"]["rmse"] is None
    assert "fuel_rate_g_per_s" in rows["fuel_rate"]["why"]
    text = present.scores_text(m, log)
    assert "fuel_rate not scored (the log has no fuel_rate_g_per_s)" in text and "RMSE 0 " not in text
    # the report's validation table: no RMSE and no cumulative-fuel error for it
    vr = validation_rows({"a.csv": m}, {"a.csv": log})
    fr = next(r for r in vr if r["channel"] == "fuel_rate")
    assert fr["RMSE"] == "not scored" and fr["bias"] == ""
    assert not any(r["channel"] == "cumulative fuel" for r in vr)
    # with the channel, the same metrics are scored
    full = _Log(["soc", "fuel_rate_g_per_s"])
    assert next(r for r in present.channel_scores(m, full) if r["channel"] == "fuel_rate")["scored"]


def test_dashboard_grids_are_the_cli_defaults_and_the_preview_is_coarser():
    assert present.converged_grids() is DEFAULT_GRIDS  # the object iptm optimize and iptm run fall back to
    assert present.coarser_than_converged(DEFAULT_GRIDS) == []
    prev = present.preview_grids()
    assert present.coarser_than_converged(prev) == list(FORMULATIONS)
    for f in FORMULATIONS:
        for a in GRID_AXES[f]:
            assert getattr(prev.of(f), a) == pytest.approx(2 * getattr(DEFAULT_GRIDS.of(f), a))


def test_preview_difference_is_computed_from_both_results():
    def cs(g):
        return SimpleNamespace(sims={k: SimpleNamespace(summary=lambda v=v: {"fuel_corrected_g": v})
                                     for k, v in g.items()})

    d = present.preview_difference(cs({"thermal": 101.0, "rule": 5.0}), cs({"thermal": 100.0, "baseline": 9.0}))
    assert list(d) == ["thermal"] and d["thermal"]["diff_pct"] == pytest.approx(1.0)
    assert present.difference_text(d) == "Thermal-DP +1.00 %"


@pytest.mark.parametrize("grids, terminal, expect, never", [
    (DEFAULT_GRIDS, "valued", "not of a setting", ("Try", "solve on", "compare with")),
    (DEFAULT_GRIDS, "free", "valued terminal condition (in use: free", ("solve on",)),
    (FormulationGrids.uniform(DPGrids(soc=0.02, tcl=2.0)), "valued", "solve on the converged grids",
     ("compare with",)),
])
def test_ordering_advice_never_suggests_what_is_in_use(grids, terminal, expect, never):
    cs = SimpleNamespace(grids=grids, scenario=DPScenario(terminal=terminal))
    text = present.ordering_advice(cs)
    assert expect in text
    assert not any(n in text for n in never), text
    # a caller that cannot set the grids is not told to
    assert "solve on" not in present.ordering_advice(cs, settable=("terminal",))


def test_one_progress_line_per_stage(capsys):
    calls = []
    sp = pipeline.StageProgress(["ingest", "optimise", "report"], True,
                                lambda k, n, s, f, t: calls.append((k, n, s, round(f, 3), t)))
    sp.start("ingest", "2 log(s)")
    sp.update(0.5, "read a.csv (1 of 2)")
    sp.close()
    sp.start("optimise", "rule, thermal")
    bar = pipeline._StageBar(sp, 1, 2, "Thermal-DP")
    bar.steps(30, 120)
    bar.set_postfix_str("solved in 1.0 s")
    bar.update(1)
    sp.close()
    sp.start("report")
    sp.abort()
    err = capsys.readouterr().err
    # tqdm redraws a line with carriage returns: one line per stage, no counter nested inside a stage
    lines = [ln for ln in err.replace("\r", "\n").split("\n") if ln.strip()]
    assert {ln.split(":")[0] for ln in lines} == {"[1/3] ingest", "[2/3] optimise", "[3/3] report"}
    assert "[1/2]" not in err and "[2/2]" not in err
    assert calls[0] == (1, 3, "ingest", 0.0, "2 log(s)") and (1, 3, "ingest", 0.5, "read a.csv (1 of 2)") in calls
    opt = [c for c in calls if c[2] == "optimise"]
    # strategy 2 of 2 covers the stage's second half; its DP steps move the bar within it
    assert (2, 3, "optimise", 0.625, "Thermal-DP: solving, step 30 of 120") in opt
    assert [c[3] for c in opt] == sorted(c[3] for c in opt) and opt[-1][3] == 1.0
    # the failed stage is not reported as done
    assert calls[-1] == (3, 3, "report", 0.0, "")


def test_dp_step_progress_reaches_the_display(monkeypatch):
    """A solver that reports its backward pass (``progress(done, total)``) gets the display's callback; one that
    does not is called as before."""
    import optimize.casestudy as csm

    sim = SimpleNamespace(fuel_g=1.0, soc=np.array([0.6, 0.6]))

    def with_progress(params, scen, grids, progress=None):
        for k in (1, 2):
            progress(k, 2)
        return SimpleNamespace(sim=sim, on_thermal=sim, t_total=0.0, t_backward=0.0)

    def without(params, scen, grids):
        return SimpleNamespace(sim=sim, on_thermal=sim, t_total=0.0, t_backward=0.0)

    monkeypatch.setattr(csm, "solve_thermal", with_progress)
    monkeypatch.setattr(csm, "solve_baseline", without)
    seen = []
    scen = replace(DPScenario(), duration_s=10.0)
    cs = csm.run_case_study(default_parameters(), scen, ("baseline", "thermal"), progress=False,
                            step_progress=lambda d, t: seen.append((d, t)))
    assert seen == [(1, 2), (2, 2)] and set(cs.sims) == {"baseline", "baseline_warm", "thermal"}


def test_sweep_prints_the_corrected_saving_first(monkeypatch, tmp_path, capsys):
    import argparse

    import pandas as pd

    import optimize as sw  # the command uses the sweep through optimize's front door
    from iptm.commands import sweep as cmd

    study = SimpleNamespace(name="s", strategies=("rule", "thermal"), reference="rule", grids={}, source="s.toml",
                            expand=lambda: [{}])
    df = pd.DataFrame({"case_id": [0, 0], "status": ["ok", "ok"], "cached": [True, True]})
    monkeypatch.setattr(sw, "load_study", lambda p: study)
    monkeypatch.setattr(sw, "run_study", lambda *a, **k: df)
    monkeypatch.setattr(sw, "write_table", lambda d, p: p)
    monkeypatch.setattr(sw, "plot_study", lambda *a, **k: [])
    monkeypatch.setattr(sw, "summary_pivot", lambda d, m: pd.DataFrame({"-10": [{"saving_corrected_pct": -1.5,
                                                                                "saving_pct": 4.0}[m]]}))
    args = argparse.Namespace(study="s.toml", scheduler=None, workers=1, out=str(tmp_path), plots=None,
                              metric="both", store=None, retry_failed=False, quiet=True, json=None)
    assert cmd.run(args) == 0
    out = capsys.readouterr().out
    assert out.index("corrected-fuel saving") < out.index("raw fuel saving") and "-1.50" in out


def test_dp_step_progress_from_the_real_solver_reaches_the_stage_line():
    """End to end: the main job's optimisation stage advances with Baseline-DP's backward pass."""
    calls = []
    sp = pipeline.StageProgress(["optimise"], False, lambda k, n, s, f, t: calls.append((f, t)))
    sp.start("optimise")
    pipeline.optimize_cached(default_parameters(), DPScenario(duration_s=20.0), None, ("baseline",), None,
                             progress=False, stage=sp)
    sp.close()
    steps = [f for f, t in calls if "step" in t]
    assert len(steps) >= 2 and steps == sorted(steps) and steps[0] < steps[-1] == 1.0
    assert any(t.endswith("step 20 of 20") for _, t in calls)
