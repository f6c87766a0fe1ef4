"""Report page: run the whole chain (:func:`iptm.pipeline.run`: ingest -> calibrate -> optimise -> report) on
the session's logs and the Optimize page's scenario, and download the HTML report and its JSON."""
import json
import time
from pathlib import Path

import streamlit as st

from iptm import dashboard as dash
from iptm import present

state = st.session_state
st.title("Report")
# the run's progress, at the top of the page: one bar over the run's stages (iptm.pipeline.StageProgress)
PROGRESS = st.container()



def _page():
    session_logs = dash.logs(state)
    if not session_logs:
        st.info("Load logs on the Logs page first.")
        st.page_link("pages/logs.py", label="Go to Logs")
        return

    from optimize.formulations import DPScenario  # noqa: E402

    names = list(session_logs)
    sel = st.multiselect("Logs (the last one is held out for validation)", names, default=names,
                         format_func=lambda n: session_logs[n].label, key="rep_logs")
    sc = state.get(dash.SCENARIO)
    if sc is not None:
        scenario, grids, strategies = sc["scenario"], sc["grids"], sc["strategies"]
        st.caption("Scenario, grids and strategies: as set on the Optimize page.")
    else:
        scenario = DPScenario(duration_s=120.0)
        grids = present.converged_grids()  # as `iptm run`
        strategies = ("rule", "baseline", "thermal", "thermal_cabin")
        st.caption("Scenario: the default (first 120 s of the cycle, each formulation's converged grid, as "
                   "`iptm run`); change it on the Optimize page.")
    with st.expander("Scenario used"):
        st.json({"scenario": scenario.to_dict(), "grids": grids.to_dict(), "strategies": list(strategies)},
                expanded=False)

    if st.button("Build the report", type="primary", disabled=not sel or not strategies, key="rep_run"):
        from iptm.pipeline import RunConfig, run

        state.pop("iptm_report", None)  # a failed run leaves no earlier report that reads as this one's
        with PROGRESS:
            bar = st.progress(0.0, text="starting (cached steps are reused)")

        def on_progress(k, n, stage, fraction, text):
            # a cycle or log in the session folder is named by its file name, never by the server's path
            bar.progress(min(((k - 1) + fraction) / n, 1.0),
                         text=dash.plain(dash.scrub_paths(f"[{k}/{n}] {stage}: {text}")))

        try:
            t0 = time.perf_counter()
            cfg = RunConfig(logs=[str(session_logs[n].path) for n in sel], scenario=scenario, grids=grids,
                            strategies=tuple(strategies), reports_dir=dash.session_dir(state) / "reports",
                            cache_dir=dash.cache_dir(), progress=False, on_progress=on_progress,
                            command_line="streamlit dashboard (Report page)")
            out = run(cfg)
            rd = Path(out.report_dir)
            state["iptm_report"] = {"dir": str(rd), "summary": out.summary, "wall_s": out.wall_s,
                                    "html": (rd / "index.html").read_bytes(), "json": (rd / "report.json").read_bytes()}
            bar.progress(1.0, text=f"done in {time.perf_counter() - t0:.1f} s")
        except Exception as exc:  # noqa: BLE001 - the page stays usable
            bar.empty()  # the bar of a failed run goes; the error says why
            PROGRESS.error(dash.plain(f"Report failed: {dash.error_message(exc)}"))

    rep = state.get("iptm_report")
    if rep is None:
        st.info("Build the report to download it.")
        return

    st.success(dash.plain(f"Report {Path(rep['dir']).name} built in {rep['wall_s']:.1f} s."))
    c1, c2 = st.columns(2)
    c1.download_button("Download the HTML report", rep["html"], file_name="report.html", mime="text/html",
                       key="rep_dl_html")
    c2.download_button("Download the JSON", rep["json"], file_name="report.json", mime="application/json",
                       key="rep_dl_json")
    import pandas as pd

    from iptm.report import summary_table

    full = json.loads(rep["json"])
    summ = full["summary"]
    st.subheader("Summary")
    if summ.get("synthetic_data"):
        st.warning("Built from SYNTHETIC logs.")
    st.dataframe(summary_table(pd.DataFrame(full["case_study"]["table"])), hide_index=True, width="stretch")
    for w in summ.get("at_prior") or []:
        st.warning(dash.plain(f"Not fitted: {w}"))
    m1, m2, m3 = st.columns(3)
    m1.metric("parameters estimated", summ.get("n_estimated", 0))
    m2.metric("weakly informed (mostly prior)", summ.get("n_weak", 0))
    if summ.get("calibration_text"):
        st.caption(summ["calibration_text"] + ".")
    m3.metric("corrected-fuel ordering rule > Baseline > Thermal > Thermal-Cabin",
              "holds" if summ.get("ordering_ok") else "does not hold")
    with st.expander("Summary as JSON"):
        st.json(summ, expanded=False)
    st.subheader("Preview")
    st.caption("The HTML report as downloaded (self-contained, figures embedded).")
    import streamlit.components.v1 as components

    components.html(rep["html"].decode("utf-8"), height=900, scrolling=True)


_page()
dash.render_sidebar()
