"""Optimize page: a scenario (cycle from the library, a file or a loaded log; ambient; heater; grids;
strategies), run the case study of :mod:`optimize.casestudy` with progress, and see the comparison table,
the savings and the paper-style figures."""
import importlib.util
import json
import time

import streamlit as st

from calib import content_key
from iptm import dashboard as dash

state = st.session_state
st.title("Optimize")
# the run's progress is drawn here, at the top, whatever the page's length (the button is further down)
PROGRESS = st.container()

PREVIEW_DIFF = "iptm_preview_diff"  # {"key", "diff", "where"}: the preview's measured error
STRATS = {"rule": "Rule-based (tuned)", "baseline": "Baseline-DP", "thermal": "Thermal-DP",
          "thermal_cabin": "Thermal-Cabin-DP"}


def _solve(params, scenario, grids, strategy, steps=None):
    """One strategy of the case study through the one content-keyed cache (the entries of ``iptm run`` and
    ``iptm optimize``: solved once for the same parameters, scenario incl. cycle file hash and grids, by any of
    them). ``steps(done, total)``: the DP's backward pass, where the solver reports it."""
    from calib import Store
    from iptm.pipeline import optimize_cached

    return optimize_cached(params, scenario, grids, (strategy,), Store(dash.cache_dir()), progress=False,
                           on_steps=steps)


def _solve_all(order, params, scenario, grids, cyc, bars):
    """Every chosen strategy, one progress bar each (its DP steps when the solver reports them)."""
    base_key = content_key(params.to_dict()["parameters"], dash.scenario_key(scenario), grids.to_dict())
    parts = []
    for s in order:
        bars[s].progress(0.0, text=f"{STRATS[s]}: solving on {cyc.n_steps} steps ...")
        t0 = time.perf_counter()

        def steps(d, n, s=s):
            bars[s].progress(min(d / max(n, 1), 1.0), text=f"{STRATS[s]}: backward pass, step {d} of {n}")

        part = _solve(params, scenario, grids, s, steps)
        parts.append(part)
        o = part.outcomes.get(s)
        size = f"{o.n_states:,} states x {o.n_controls:,} controls, " if o is not None else ""
        bars[s].progress(1.0, text=f"{STRATS[s]}: done - {size}{time.perf_counter() - t0:.1f} s")
    return dash.merge_case_studies(parts), base_key


@st.cache_data(show_spinner=False, max_entries=64)
def _estimate(key, _params, _scenario, _grids, strategy):
    """The problem's size before it is solved (or the refusal with its figures), cached by content."""
    from optimize.formulations import estimate_problem

    try:
        return estimate_problem(strategy, _params, _scenario, _grids), None
    except Exception as exc:  # noqa: BLE001 - shown on the page, the button disabled
        return None, dash.error_message(exc)


from calib import available_cycles  # noqa: E402
from calib import ParameterSet, default_parameters  # noqa: E402
from optimize import FORMULATIONS, DPGrids, DPScenario  # noqa: E402
from optimize.formulations import TERMINALS  # noqa: E402
from iptm import present  # noqa: E402



def _run_sweep(_study, _bar):
    # The same call as `iptm sweep`: a local dask cluster of 2 worker processes, started and closed here
    # (only when a case is missing), and the one content-keyed cache, so cases computed before (by any
    # session, or by `iptm sweep`) are reused.
    from optimize import run_study

    return run_study(_study, client=None, store_dir=dash.cache_dir(), n_workers=2,
                     progress_callback=lambda done, total, rec: _bar.progress(
                         done / max(total, 1), text=f"case {done}/{total} (local dask cluster)"))


def _sweep_section(params, scenario, grids, strategies):
    """A sweep over the ambient temperature with the scenario above (optimize.sweep)."""
    with st.expander("Sweep over the ambient temperature (optimize.sweep on a local dask cluster)"):
        st.caption("Grids: " + ("the custom steps above, for every formulation." if isinstance(grids, DPGrids)
                                else "each formulation's converged grid (as `iptm sweep` without [grids]; a preview "
                                     "is not used here)."))
        txt = st.text_input("Ambient temperatures [degC], comma separated", "-20, -10, 0", key="sweep_Tamb")
        if not st.button("Run sweep", key="sweep_run"):
            res = state.get("iptm_sweep")
        else:
            res = None
            bar = st.progress(0.0, text="sweep")
            try:
                from optimize import ParamSpec, Study, plot_study

                try:
                    temps = [float(x) for x in txt.replace(";", ",").split(",") if x.strip()]
                except ValueError:
                    raise dash.IptmError(f"ambient temperatures {txt!r}: give numbers, e.g. -20, -10, 0") from None
                if not temps:
                    raise dash.IptmError("give at least one ambient temperature")
                base = {k: v for k, v in scenario.to_dict().items() if k != "T_amb"}
                order = [k for k in STRATS if k in strategies]
                # a sweep replaces every formulation's converged steps by one set (or none: the converged)
                study = Study(name="dashboard", strategies=tuple(order), reference=order[0],
                              grids=grids.to_dict() if isinstance(grids, DPGrids) else {}, scenario=base,
                              vary={"T_amb": temps},
                              param_sets=[ParamSpec("session", None, params)])
                key = content_key([c["key"] for c in study.expand()], dash.scenario_key(scenario))
                df = _run_sweep(study, bar)
                figs = plot_study(df, dash.session_dir(state) / "sweep" / key)
                res = state["iptm_sweep"] = {"df": df, "figures": figs}
                bar.progress(1.0, text=f"done: {len(df)} rows")
            except Exception as exc:  # noqa: BLE001
                bar.empty()
                st.error(dash.plain(f"Sweep failed: {dash.error_message(exc)}"))
        if res is not None:
            from optimize import summary_pivot

            try:
                st.dataframe(summary_pivot(res["df"]), width="stretch")
            except Exception:  # noqa: BLE001 - the tidy table is enough
                pass
            st.dataframe(res["df"], width="stretch", hide_index=True)
            for f in res["figures"]:
                st.image(f, width="stretch")


def _preview_section(opt, cs):
    """A preview result says so, with its error against the converged grids once measured (both solved on
    this scenario; the converged solve is cached like any other)."""
    last = state.get(PREVIEW_DIFF)
    if last and last["key"] == opt["key"]:
        st.info(f"Preview grids: corrected fuel differs from the converged grids' by {present.difference_text(last['diff'])} "
                "(preview minus converged, measured on this scenario).")
        return
    st.info("Preview grids: every step of the converged grids doubled. Its error on this scenario is not measured "
            "yet.")
    if st.button("Measure the preview against the converged grids", key="opt_measure_preview"):
        order = [k for k in STRATS if k in cs.sims and k in FORMULATIONS]
        with PROGRESS:
            box = st.empty()
            with box.container():
                bars = {k: st.progress(0.0, text=f"{STRATS[k]} (converged grids): waiting") for k in order}
        try:
            conv_cs, _ = _solve_all(order, opt["params"], cs.scenario, present.converged_grids(),
                                    cs.scenario.load_cycle(), bars)
            state[PREVIEW_DIFF] = {"key": opt["key"], "diff": present.preview_difference(cs, conv_cs),
                                   "where": f"{opt['cycle']['name']}, {cs.scenario.T_amb:g} degC"}
            st.rerun()
        except Exception as exc:  # noqa: BLE001
            box.empty()
            PROGRESS.error(dash.plain(f"Measuring the preview failed: {dash.error_message(exc)}"))


def _page():
    # ---- parameter set ------------------------------------------------------------------------------
    st.subheader("Model parameters")
    psrc_opts = (["calibrated in this session"] if state.get(dash.CALIB) else []) + ["default 2017 Prius",
                                                                                      "upload a parameter file"]
    psrc = st.radio("Parameter set", psrc_opts, horizontal=True, key="opt_params_src")
    params, params_ok = None, True
    if psrc == "calibrated in this session":
        params = state[dash.CALIB]["result"].params
    elif psrc == "default 2017 Prius":
        params = default_parameters()
    else:
        pf = st.file_uploader("Parameter set or calibration artifact (TOML/JSON)", key="opt_params_upload")
        if pf is None:
            params_ok = False
        else:
            try:
                params = ParameterSet.load(dash.save_upload(state, pf.name, pf.getvalue(), subdir="params"))
            except Exception as exc:  # noqa: BLE001
                st.error(dash.plain(f"Could not use {pf.name}: {dash.error_message(exc)}"))
                params_ok = False

    # ---- scenario -----------------------------------------------------------------------------------
    st.subheader("Scenario")
    d = DPScenario()
    session_logs = dash.logs(state)
    speed_logs = [n for n, e in session_logs.items() if e.log.has("speed_mps")]
    csrc = st.radio("Drive cycle", ["from the library", "from a file", "from a loaded log"], horizontal=True,
                    key="opt_cycle_src")
    cycle, cycle_ok = None, True
    if csrc == "from the library":
        cycs = available_cycles()
        cycle = st.selectbox("Cycle", cycs, index=cycs.index(d.cycle) if d.cycle in cycs else 0, key="opt_cycle")
    elif csrc == "from a file":
        cf = st.file_uploader("Cycle CSV (time_s and speed_kph or speed_mps)", key="opt_cycle_upload")
        if cf is None:
            cycle_ok = False
        else:
            try:
                from calib import load_cycle

                p = dash.save_upload(state, cf.name, cf.getvalue(), subdir="cycles")
                c = load_cycle(str(p))
                st.caption(dash.plain(f"{cf.name}: {c.describe()['duration_s']:.0f} s, {c.describe()['distance_km']:.2f} km"))
                cycle = str(p)
            except Exception as exc:  # noqa: BLE001
                st.error(dash.plain(f"Could not use {cf.name} as a cycle: {dash.error_message(exc)}"))
                cycle_ok = False
    else:
        if not speed_logs:
            st.warning("No loaded log has a speed channel: load one on the Logs page.")
            cycle_ok = False
        else:
            ln = st.selectbox("Log", speed_logs, format_func=lambda n: session_logs[n].label, key="opt_cycle_log")
            try:
                cycle = str(dash.cycle_csv_from_log(state, session_logs[ln]))
            except Exception as exc:  # noqa: BLE001
                st.error(dash.plain(dash.error_message(exc)))
                cycle_ok = False

    c1, c2, c3, c4 = st.columns(4)
    T_amb = c1.number_input("Ambient [degC]", -40.0, 40.0, float(d.T_amb), 1.0, key="opt_Tamb")
    soc0 = c2.number_input("Initial SOC [-]", 0.4, 0.8, float(d.soc0), 0.01, key="opt_soc0")
    T_cl0 = c3.number_input("Initial coolant [degC]", -40.0, 100.0, float(d.T_cl0), 1.0, key="opt_Tcl0")
    T_cab0 = c4.number_input("Initial cabin [degC]", -40.0, 40.0, float(d.T_cab0), 1.0, key="opt_Tcab0")
    c5, c6, c7, c8 = st.columns(4)
    Q_heat = c5.number_input("Heater demand [W] (rule, Baseline, Thermal)", 0.0, 6000.0, float(d.Q_heat), 100.0,
                             key="opt_Qheat")
    Q_min = c6.number_input("Thermal-Cabin heater min [W]", 0.0, 6000.0, float(d.Q_heat_min), 100.0, key="opt_Qmin")
    Q_max = c7.number_input("Thermal-Cabin heater max [W]", 0.0, 6000.0, float(d.Q_heat_max), 100.0, key="opt_Qmax")
    dur = c8.number_input("Use the first ... s of the cycle (0 = whole)", 0.0, 100000.0, 0.0, 60.0, key="opt_duration")

    terminal = st.selectbox(
        "Terminal condition on coolant and cabin (as `iptm optimize --terminal`)", TERMINALS,
        index=TERMINALS.index(d.terminal), key="opt_terminal",
        help="valued: heat left in coolant and cabin is worth its fuel equivalent (the corrected fuel; the "
             "default); match: at least the rule-based run's final coolant and cabin; continued: the final state "
             "valued by a common continuation drive; free: the paper's, no condition (a DP may end colder).")

    st.markdown("**DP grids**")
    conv, prev = present.converged_grids(), present.preview_grids()
    grid_opts = ["converged", "preview", "custom"]
    # the preview's error, measured on this session's last scenario where both grids were solved
    last = state.get(PREVIEW_DIFF)

    def _grid_label(o):
        if o == "converged":
            return "converged: each formulation's own grid, as `iptm optimize` and `iptm run` use"
        if o == "custom":
            return "custom steps, the same for every formulation"
        return ("preview: every converged step doubled, faster; corrected fuel vs converged "
                + (f"measured {present.difference_text(last['diff'])} ({last['where']})" if last and last["diff"]
                   else "not measured yet (run the preview, then measure it)"))

    gsel = st.radio("DP grids", grid_opts, format_func=_grid_label, key="opt_grid_choice", label_visibility="collapsed")
    if gsel == "custom":
        p0 = DPGrids()  # the paper's Table II as the starting point
        st.caption("The paper's Table II steps are the starting point; coarser steps run faster and cost accuracy.")
        g1, g2, g3, g4, g5 = st.columns(5)
        gs = g1.number_input("SOC [-]", 0.001, 0.1, p0.soc, 0.005, format="%.3f", key="opt_g_soc")
        gt = g2.number_input("coolant [degC]", 0.1, 10.0, p0.tcl, 0.5, key="opt_g_tcl")
        gc = g3.number_input("cabin [degC]", 0.1, 10.0, p0.tcab, 0.5, key="opt_g_tcab")
        gp = g4.number_input("battery [W]", 50.0, 5000.0, p0.pbat, 100.0, key="opt_g_pbat")
        gq = g5.number_input("heater [W]", 10.0, 1000.0, p0.qheat, 10.0, key="opt_g_qheat")
        chosen_grids = DPGrids(soc=gs, tcl=gt, tcab=gc, pbat=gp, qheat=gq)
    else:
        chosen_grids = conv if gsel == "converged" else prev
        st.caption(("Grid steps: " if gsel == "converged" else "Preview grid steps: ") + chosen_grids.describe())
    strategies = st.multiselect("Strategies", list(STRATS), default=list(STRATS), format_func=STRATS.get,
                                key="opt_strategies")


    scenario, grids = None, None
    if cycle_ok and cycle is not None:
        try:
            scenario = DPScenario(cycle=cycle, T_amb=T_amb, soc0=soc0, T_cl0=T_cl0, T_cab0=T_cab0, Q_heat=Q_heat,
                                  Q_heat_min=Q_min, Q_heat_max=Q_max, duration_s=dur or None, terminal=terminal)
            grids = chosen_grids
            state[dash.SCENARIO] = {"scenario": scenario, "grids": grids, "strategies": tuple(strategies)}
        except Exception as exc:  # noqa: BLE001
            st.error(dash.plain(f"Invalid scenario: {dash.error_message(exc)}"))

    ready = params_ok and scenario is not None and bool(strategies)
    if ready:
        # the size of each DP before the button: a grid that would take hours or exhaust memory is refused
        # here, with its figures, not after minutes of work
        ekey = content_key(params.to_dict()["parameters"], dash.scenario_key(scenario), grids.to_dict())
        lines = []
        for s in [s for s in STRATS if s in strategies and s in FORMULATIONS]:
            est, err = _estimate(content_key(ekey, s), params, scenario, grids.of(s) if hasattr(grids, "of") else grids, s)
            if err:
                st.error(dash.plain(f"{STRATS[s]}: {err}"))
                ready = False
            else:
                lines.append(f"{STRATS[s]}: {est['states']:,} states x {est['controls']:,} controls x "
                             f"{est['steps']:,} steps = {est['evaluations'] / 1e9:.2g} G evaluations")
        if lines:
            st.caption("Problem size: " + "; ".join(lines))
    if st.button("Run optimisation", type="primary", disabled=not ready, key="opt_run"):
        order = [s for s in STRATS if s in strategies]
        state.pop(dash.OPT, None)  # a failed run leaves no earlier result or bar that reads as this one's
        with PROGRESS:
            # one bar per strategy, named, with its state count when solved: a single bar's time-left estimate
            # jumps as strategies of very different sizes follow each other
            box = st.empty()
            with box.container():
                bars = {s: st.progress(0.0, text=f"{STRATS[s]}: waiting") for s in order}
                bar = st.progress(0.0, text="loading the cycle")
        try:
            cyc = scenario.load_cycle()  # a bad cycle or duration fails here, before any DP
            cs, base_key = _solve_all(order, params, scenario, grids, cyc, bars)
            bar.progress(0.5, text="drawing the figures")
            figs = cs.plot(dash.session_dir(state) / "figures" / base_key)
            state[dash.OPT] = {"cs": cs, "figures": figs, "cycle": cyc.describe(), "key": base_key,
                               "grid_choice": gsel, "params": params}
            bar.progress(1.0, text=f"done ({sum(cs.timings.values()):.1f} s of solver time)")
        except Exception as exc:  # noqa: BLE001
            box.empty()  # the bars of a failed run go; the error says why
            PROGRESS.error(dash.plain(f"Optimisation failed: {dash.error_message(exc)}"))

    if importlib.util.find_spec("optimize.sweep") is not None and params_ok and scenario is not None and strategies:
        _sweep_section(params, scenario, grids, strategies)

    opt = state.get(dash.OPT)
    if opt is None:
        st.info("Set the scenario, then run the optimisation (coarse grids and a short cycle take seconds; the "
                "paper's grids on a whole cycle take minutes).")
        return

    cs = opt["cs"]
    st.subheader("Comparison")
    cy = opt["cycle"]
    st.caption(dash.plain(f"cycle {cy['name']}: {cy['duration_s']:.0f} s, {cy['distance_km']:.2f} km; ambient "
               f"{cs.scenario.T_amb:g} degC; grid steps {cs.grids.describe([f for f in FORMULATIONS if f in cs.outcomes])}"))
    tbl = cs.table()
    cols = st.columns(3)
    for col, key, ref in ((cols[0], "thermal", "vs_rule"), (cols[1], "thermal_cabin", "vs_rule"),
                          (cols[2], "thermal", "vs_baseline")):
        row = tbl[tbl["key"] == key]
        if row.empty:
            continue
        v = float(row[f"saving_{ref}_pct"].iloc[0])
        paper = row[f"paper_{ref}_pct"].iloc[0]
        other = "rule-based" if ref == "vs_rule" else "Baseline-DP"
        # the paper's figure is a reference, not a change: a caption, not a delta arrow
        col.metric(f"{STRATS[key]} saving vs {other} (corrected fuel)", f"{v:.2f} %" if v == v else "-")
        if paper == paper:
            col.caption(f"paper (Gong et al.): {paper:.2f} % ({present.PAPER_CONDITION})")
    st.caption(f"Terminal condition on coolant and cabin: {cs.scenario.terminal}. " + cs.ordering_statement() + ".")
    if not cs.ordering_ok():
        st.warning("Corrected fuel is not ordered rule >= Baseline >= Thermal >= Thermal-Cabin. "
                   + present.ordering_advice(cs))
    if opt.get("grid_choice") == "preview":
        _preview_section(opt, cs)
    from iptm.report import comparison_table

    st.dataframe(comparison_table(tbl.reset_index()), hide_index=True, width="stretch")
    st.download_button("Download the results (JSON)", json.dumps(cs.to_dict(), indent=1, default=str),
                       file_name="case_study.json", mime="application/json", key="opt_download")

    st.subheader("Trajectories")
    st.caption("Interactive: drag to pan, mouse wheel to zoom the time axis (every panel follows), hover to "
               "compare the strategies point by point; double-click resets.")
    from iptm.charts import trajectories_chart
    from optimize import LABELS

    chart = trajectories_chart(cs.sims, LABELS)
    if chart is not None:
        st.altair_chart(chart, width="stretch")

    st.subheader("Figures")
    figs = opt["figures"]
    bars_png = [f for f in figs if f.endswith("fuel_bars.png")]
    if bars_png:
        st.image(bars_png[0])
    with st.expander("The report's static figures (paper style)"):
        rest = [f for f in figs if f not in bars_png]
        for i in range(0, len(rest), 2):
            cc = st.columns(2)
            for col, f in zip(cc, rest[i:i + 2]):
                col.image(f, width="stretch")


_page()
dash.render_sidebar()
