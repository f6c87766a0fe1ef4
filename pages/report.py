"""Report page: run the whole chain (:func:`iptm.pipeline.run`: ingest -> calibrate -> optimise -> report) on
the session's logs and the Optimize page's scenario, and download the HTML report and its JSON."""
import json
import time
from pathlib import Path

import streamlit as st

from iptm import dashboard as dash

state = st.session_state
st.title("Report")



def _page():
    session_logs = dash.logs(state)
    if not session_logs:
        st.info("Load logs on the Logs page first.")
        st.page_link("pages/logs.py", label="Go to Logs")
        return

    from optimize.formulations.scenario import DPGrids, DPScenario  # noqa: E402

    names = list(session_logs)
    sel = st.multiselect("Logs (the last one is held out for validation)", names, default=names,
                         format_func=lambda n: session_logs[n].label, key="rep_logs")
    sc = state.get(dash.SCENARIO)
    if sc is not None:
        scenario, grids, strategies = sc["scenario"], sc["grids"], sc["strategies"]
        st.caption("Scenario, grids and strategies: as set on the Optimize page.")
    else:
        scenario = DPScenario(duration_s=120.0)
        grids = DPGrids(soc=0.02, tcl=2.0, tcab=2.0, pbat=1000.0, qheat=100.0)
        strategies = ("rule", "baseline", "thermal", "thermal_cabin")
        st.caption("Scenario: the default (first 120 s of the cycle, coarse grids); change it on the Optimize page.")
    with st.expander("Scenario used"):
        st.json({"scenario": scenario.to_dict(), "grids": grids.to_dict(), "strategies": list(strategies)},
                expanded=False)

    if st.button("Build the report", type="primary", disabled=not sel or not strategies, key="rep_run"):
        from iptm.pipeline import RunConfig, run

        bar = st.progress(0.1, text="ingest, calibration, optimisation and report (cached steps are reused)")
        try:
            t0 = time.perf_counter()
            with st.spinner("building the report..."):
                cfg = RunConfig(logs=[str(session_logs[n].path) for n in sel], scenario=scenario, grids=grids,
                                strategies=tuple(strategies), reports_dir=dash.session_dir(state) / "reports",
                                cache_dir=dash.cache_dir(), progress=False,
                                command_line="streamlit dashboard (Report page)")
                out = run(cfg)
            rd = Path(out.report_dir)
            state["iptm_report"] = {"dir": str(rd), "summary": out.summary, "wall_s": out.wall_s,
                                    "html": (rd / "index.html").read_bytes(), "json": (rd / "report.json").read_bytes()}
            bar.progress(1.0, text=f"done in {time.perf_counter() - t0:.1f} s")
        except Exception as exc:  # noqa: BLE001 - the page stays usable
            bar.empty()
            st.error(dash.plain(f"Report failed: {dash.error_message(exc)}"))

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
    m1, m2, m3 = st.columns(3)
    m1.metric("parameters estimated", summ.get("n_estimated", 0))
    m2.metric("weakly informed (mostly prior)", summ.get("n_weak", 0))
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
