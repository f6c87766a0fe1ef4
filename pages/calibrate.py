"""Calibrate page: choose logs for fitting and validation and the parameters to fit or fix, run
:func:`calib.fit.driver.calibrate`, see the parameter table with uncertainties and identifiability,
measured-vs-simulated plots, and download the calibration file."""
import matplotlib.pyplot as plt
import streamlit as st

from calib import content_key, result_key
from iptm import dashboard as dash
from iptm import present

state = st.session_state
st.title("Calibrate")
# the run's progress is drawn here, at the top, whatever the page's length (the button is further down)
PROGRESS = st.container()


def _calibrate(key, fit_logs, val_logs, base, fit, fix):
    """Through the one content-keyed cache (kind ``calibration``: the saved result, docs/results.md), keyed by
    ``key`` (the logs' SHA-256, truncation, base parameters, options and code version), never by session."""
    from calib import IptmError
    from calib import CalibrationResult, calibrate
    from calib import Store

    store = Store(dash.cache_dir())
    folder = store.get_dir("calibration", key)
    if folder is not None:
        try:
            return CalibrationResult.load(folder / "result")
        except IptmError:
            pass  # a damaged entry: calibrated again and replaced
    res = calibrate(fit_logs, base=base, fit=list(fit) if fit is not None else None, fix=list(fix),
                    validate=val_logs or None, progress=False)
    store.put_dir("calibration", key, lambda d: res.save(d / "result"))
    return res


@st.cache_resource(show_spinner=False, max_entries=32)
def _replay(key, _log, _params):
    from calib import replay

    return replay(_log, _params)




def _page():
    session_logs = dash.logs(state)
    if not session_logs:
        st.info("Load logs on the Logs page first.")
        st.page_link("pages/logs.py", label="Go to Logs")
        return

    names = list(session_logs)
    label = lambda n: session_logs[n].label  # noqa: E731
    # one log per drive by default (the same drive may be loaded as BLF, CSV, MCAP...): fit on all drives
    # but the last, hold the last out
    groups = dash.drive_groups(state, names)
    firsts = [g[0] for g in groups]
    c1, c2 = st.columns(2)
    with c1:
        fit_names = st.multiselect("Logs for fitting", names, default=firsts[:max(1, len(firsts) - 1)],
                                   format_func=label, key="cal_fit_logs")
    # a copy of a fitted drive cannot validate the fit: it is not offered
    copies = {n: dash.same_drive_as(state, n, fit_names) for n in names if n not in fit_names}
    val_opts = [n for n in names if n not in fit_names and copies.get(n) is None]
    with c2:
        val_default = [firsts[-1]] if len(firsts) > 1 else []
        val_names = st.multiselect("Held-out logs for validation (drives not used for fitting)", val_opts,
                                   default=[n for n in val_default if n in val_opts], format_func=label,
                                   key="cal_val_logs")
    for g in dash.drive_groups(state, fit_names) if len(fit_names) > 1 else []:
        if len(g) > 1:
            st.warning(dash.plain("These logs are the same drive: " + ", ".join(label(n) for n in g)
                       + ". Fitting on copies counts that drive several times; keep one."))
    hidden = [n for n, twin in copies.items() if twin is not None]
    if hidden:
        st.caption(dash.plain("Not offered for validation (same drive as a fitted log): "
                   + ", ".join(f"{label(n)} = {label(copies[n])}" for n in hidden)))

    allp = dash.calibratable_parameters()
    c3, c4 = st.columns(2)
    with c3:
        fit_sel = st.multiselect("Parameters to fit (the others stay at the base value)", allp, default=allp,
                                 key="cal_fit_params")
    with c4:
        fix_sel = st.multiselect("Parameters to fix at the base value", allp, default=[], key="cal_fix_params")

    c5, c6 = st.columns(2)
    with c5:
        base_file = st.file_uploader("Base parameter set (TOML/JSON; default: the built-in 2017 Prius)",
                                     key="cal_base_upload")
    with c6:
        trunc = st.number_input("Use only the first ... seconds of each log (0 = whole log)", min_value=0.0,
                                value=0.0, step=60.0, key="cal_truncate_s")

    base = None
    base_ok = True
    if base_file is not None:
        from calib import ParameterSet

        try:
            p = dash.save_upload(state, base_file.name, base_file.getvalue(), subdir="params")
            base = ParameterSet.load(p)
            st.caption(dash.plain(f"base parameters: {base_file.name}"))
        except Exception as exc:  # noqa: BLE001
            st.error(dash.plain(f"Could not use {base_file.name} as base parameters: {dash.error_message(exc)}"))
            base_ok = False

    run = st.button("Run calibration", type="primary", disabled=not fit_names or not base_ok, key="cal_run")
    if run:
        from calib import default_parameters

        state.pop(dash.CALIB, None)  # a failed run leaves no earlier result that reads as this one's
        with PROGRESS:
            bar = st.progress(0.0, text="preparing the logs")
        try:
            fit_logs = [dash.truncate(session_logs[n].log, trunc) for n in fit_names]
            val_logs = [dash.truncate(session_logs[n].log, trunc) for n in val_names]
            base_ps = base or default_parameters()
            fit = tuple(fit_sel) if set(fit_sel) != set(allp) else None
            fix = tuple(fix_sel)
            key = result_key("calibration", params=base_ps.to_dict()["parameters"], code=("calib",),
                             inputs=[[session_logs[n].sha256 for n in fit_names],
                                     [session_logs[n].sha256 for n in val_names], float(trunc)],
                             options={"fit": fit, "fix": fix})
            bar.progress(0.1, text=f"fitting on {len(fit_logs)} log(s) (battery, fuel, thermal, cabin)")
            with st.spinner("calibrating..."):
                res = _calibrate(key, fit_logs, val_logs, base_ps, fit, fix)
            bar.progress(0.7, text="replaying the logs with the calibrated parameters")
            plots = []
            show = list(fit_names) + [n for n in val_names if n not in fit_names]
            for i, n in enumerate(show):
                lg = dash.truncate(session_logs[n].log, trunc)
                rep = _replay(content_key(key, session_logs[n].sha256, float(trunc)), lg, res.params)
                plots.append((session_logs[n].label, rep, n in val_names))
                bar.progress(0.7 + 0.3 * (i + 1) / len(show), text=f"replayed {session_logs[n].label}")
            art = dash.session_dir(state) / "calibration" / "calibration.toml"
            res.to_artifact(art)
            state[dash.CALIB] = {"result": res, "plots": plots, "artifact": art.read_bytes(), "key": key,
                                 "fit": fit_names, "val": val_names}
            bar.progress(1.0, text=f"done in {res.wall_s:.1f} s")
        except Exception as exc:  # noqa: BLE001 - the page stays usable
            bar.empty()
            PROGRESS.error(dash.plain(f"Calibration failed: {dash.error_message(exc)}"))

    cal = state.get(dash.CALIB)
    if cal is None:
        st.info("Choose logs and parameters, then run the calibration.")
        return

    res = cal["result"]
    st.subheader("Calibrated parameters")
    for w in present.prior_banner(res):
        st.warning(dash.plain(f"Not fitted: {w}"))
    tbl = dash.parameter_table(res.params)
    counts = present.parameter_counts(res.params)  # the same count as the report and `iptm run`
    m1, m2, m3 = st.columns(3)
    m1.metric("parameters estimated", counts["estimated"])
    m2.metric("weakly informed (mostly prior)", counts["weak"])
    m3.metric("wall time", f"{res.wall_s:.1f} s")
    st.caption(present.counts_text(counts) + ".")
    if res.params.meta.get("synthetic"):
        st.warning("Calibrated from SYNTHETIC logs.")
    st.dataframe(tbl, hide_index=True, width="stretch")

    st.download_button("Download the calibration file (TOML)", cal["artifact"], file_name="calibration.toml",
                       mime="application/toml", key="cal_download")

    # each log as calibrated (truncated as chosen), by its label: a channel it lacks is "not scored"
    by_label = {session_logs[n].label: session_logs[n].log for n in session_logs}
    if res.validation:
        st.subheader("Validation on held-out logs")
        from iptm.report import validation_rows

        st.dataframe(validation_rows(res.validation, by_label), hide_index=True, width="stretch")

    st.subheader("Measured vs simulated")
    st.caption("Interactive: drag to pan, mouse wheel to zoom the time axis (all panels of a log follow), "
               "hover for values; double-click resets. Solid: measured; dashed: simulated.")
    from iptm.charts import validation_chart  # noqa: E402

    tabs = st.tabs([f"{lbl} ({'held out' if held_out else 'fitted'})" for lbl, _, held_out in cal["plots"]]
                   + ["residuals"])
    for tab, (lbl, rep, _held_out) in zip(tabs, cal["plots"]):
        with tab:
            st.caption(present.scores_text(rep.metrics(), by_label.get(lbl)))
            chart = validation_chart(rep)
            if chart is not None:
                st.altair_chart(chart, width="stretch")
    with tabs[-1]:
        from calib.fit import plot_residual_comparison

        fig = plot_residual_comparison([(f"{lbl} ({'held out' if h else 'fitted'})", rep) for lbl, rep, h in cal["plots"]])
        st.pyplot(fig, clear_figure=True)
        plt.close(fig)

    with st.expander("Fit report (text)"):
        st.code(res.report(), language=None)


_page()
dash.render_sidebar()
