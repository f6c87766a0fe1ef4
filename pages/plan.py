"""Plan page: from this session's calibration (or an uploaded artifact), design the drive that would inform
the parameters the logs left weak (:func:`calib.design.make_plan`), see the predicted posterior sd, the plan
figure, and download the plan CSV."""
import matplotlib.pyplot as plt
import streamlit as st

from calib import atomic_path
from iptm import dashboard as dash

state = st.session_state
st.title("Plan the next drive")
PLAN = "iptm_plan"


def _artifact_bytes():
    """The artifact to plan from: this session's calibration, or an upload."""
    cal = state.get(dash.CALIB)
    opts = (["calibrated in this session"] if cal else []) + ["upload a calibration artifact"]
    src = st.radio("Calibration", opts, horizontal=True, key="plan_source")
    if src == "calibrated in this session":
        return cal["artifact"], "toml"
    up = st.file_uploader("Calibration artifact (TOML/JSON, written by iptm calibrate or the Calibrate page)",
                          key="plan_upload")
    if up is None:
        return None, None
    suffix = "json" if up.name.lower().endswith(".json") else "toml"
    return up.getvalue(), suffix


def _page():
    from calib.design import ArtifactPrior, make_plan, plot_plan
    from calib.design import header_lines, plan_frame
    from calib.design import DESIGNABLE

    data, suffix = _artifact_bytes()
    if data is None:
        st.info("Run a calibration on the Calibrate page, or upload a calibration artifact.")
        return
    path = dash.session_dir(state) / "plan" / f"artifact.{suffix}"
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    try:
        prior = ArtifactPrior.load(path)
    except Exception as exc:  # noqa: BLE001 - the page stays usable
        st.error(dash.plain(f"Not usable: {dash.error_message(exc)}"))
        return
    names = [n for ns in DESIGNABLE.values() for n in ns if n in prior.sd]
    weak = prior.weakest()
    st.caption(dash.plain("Posterior sd relative to prior: "
                          + ", ".join(f"{n} {100 * prior.ratio(n):.0f} %" for n in names)))
    c1, c2, c3 = st.columns(3)
    with c1:
        targets = st.multiselect("Parameters to inform", names, default=weak, key="plan_targets")
        dyno = st.toggle("Dynamometer (cell soak, whole cycles)", key="plan_dyno")
    with c2:
        minutes = st.number_input("Minutes", 6.0, 50.0, 20.0, 1.0, key="plan_minutes")
        ambient = st.number_input("Forecast ambient (degC)", -40.0, 45.0, -10.0, 1.0, key="plan_ambient",
                                  disabled=dyno)
    with c3:
        soak_txt = st.text_input("Soak temperatures (degC, comma-separated; road: coolant at the start; dyno: cell)",
                                 "-10", key="plan_soaks")
        heater = st.toggle("The driver may switch the heater off", value=True, key="plan_heater")
    if st.button("Design the drive", type="primary", disabled=not targets, key="plan_run"):
        state.pop(PLAN, None)
        try:
            soaks = [float(x) for x in soak_txt.replace(";", ",").split(",") if x.strip()]
        except ValueError:
            st.error(dash.plain(f"Soak temperatures: {soak_txt!r} is not a comma-separated list of numbers"))
            return
        bar = st.progress(0.0, text="scoring candidate drives")
        try:
            plan = make_plan(prior, targets, minutes=minutes, ambient=None if dyno else ambient, soaks=soaks or None,
                             dyno=dyno, heater=heater,
                             progress=lambda d, n: bar.progress(min(d / n, 1.0), text=f"scored {d} of {n} drives"))
            state[PLAN] = plan
            bar.empty()
        except Exception as exc:  # noqa: BLE001 - the page stays usable
            bar.empty()
            st.error(dash.plain(f"No plan: {dash.error_message(exc)}"))
            return
    plan = state.get(PLAN)
    if plan is None:
        return
    st.subheader("The plan")
    st.code("\n".join(header_lines(plan)), language=None)
    st.dataframe([{"parameter": r["name"], "sd now": r["sd_now"], "sd predicted": r["sd_predicted"],
                   "predicted / now": r["ratio"]} for r in plan.table()], hide_index=True, width="stretch")
    fig = plot_plan(plan)
    st.pyplot(fig, clear_figure=True)
    plt.close(fig)
    text = "".join(f"# {line}\n" for line in header_lines(plan)) + plan_frame(plan).to_csv(index=False)
    st.download_button("Download the plan (CSV)", text, file_name="plan.csv", mime="text/csv", key="plan_download")


_page()
dash.render_sidebar()
