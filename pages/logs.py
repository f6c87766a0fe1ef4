"""Logs page: upload drive logs (CSV, MCAP, candump/ASC/BLF/TRC with an optional DBC, MDF4), see the channel
report, plot any channel."""
import streamlit as st

from calib.ingest import display_report, format_report
from iptm import dashboard as dash



def _page():
    state = st.session_state
    st.title("Logs")
    st.caption("Drive logs of this session. Uploads go to a private temporary folder of your session; other "
               "users do not see them.")

    limit_mb = dash.max_upload_bytes() / 2**20
    c1, c2 = st.columns([3, 2])
    with c1:
        uploads = st.file_uploader(
            f"Upload drive logs (CSV, MCAP, candump .log, .asc, .blf, .trc, .mf4; up to {limit_mb:g} MB each)",
            accept_multiple_files=True, key="log_upload")
    with c2:
        dbc_file = st.file_uploader("Optional CAN database (.dbc) for CAN logs (default: the bundled Prius DBC)",
                                    key="dbc_upload")

    seen = state.setdefault(dash.SEEN, set())
    if dbc_file is not None and ("dbc", dbc_file.file_id) not in seen:
        seen.add(("dbc", dbc_file.file_id))
        try:
            p = dash.set_dbc(state, dbc_file.name, dbc_file.getvalue())
            st.success(dash.plain(f"DBC {p.name} will be used for CAN logs uploaded from now on."))
        except Exception as exc:  # noqa: BLE001 - show it, keep the page alive
            st.error(dash.plain(dash.error_message(exc)))
    if dbc_file is None and state.get(dash.DBC):
        state.pop(dash.DBC, None)

    loaded_ids = state.setdefault(dash.UPLOAD_IDS, {})  # upload file id -> the session log it became
    for up in uploads or []:
        key = ("log", up.file_id)
        if key in seen:
            continue
        # Marked as handled only once its outcome is recorded: a rerun (another file added meanwhile) stops
        # this script mid-read, and the file must then be read again, not lost. A read that finished before
        # the rerun is not read twice.
        if up.file_id in loaded_ids and loaded_ids[up.file_id] in dash.logs(state):
            seen.add(key)
            continue
        try:
            if up.size > dash.max_upload_bytes():  # refuse before reading the bytes into memory
                dash.check_size(up.name, up.size)
            with st.spinner(f"reading {up.name}..."):
                entry = dash.add_upload(state, up.name, up.getvalue(), dbc=state.get(dash.DBC))
            loaded_ids[up.file_id] = entry.name
            notes = [n[len("warning: "):] for n in entry.log.meta.notes if n.startswith("warning: ")]
            msg = f"{entry.label}: {entry.log.duration_s:.0f} s, {len(entry.log.channels())} channels"
            dash.record_upload(state, up.name, True, msg + ("; " + "; ".join(notes) if notes else ""))
            trouble = dash.log_trouble(entry.log)
            if trouble:  # a log that lost data or carries estimates is never announced in green
                st.warning(dash.plain(msg + ": " + "; ".join(trouble)))
            else:
                st.success(dash.plain(msg))
        except Exception as exc:  # noqa: BLE001 - any failure is a message in the page, never a crash
            dash.record_upload(state, up.name, False, dash.error_message(exc))
        seen.add(key)

    # every upload of the session stays listed with its outcome: an error does not vanish with the next file
    hist = state.get(dash.UPLOADS, [])
    for h in reversed(hist):
        if h["status"] == "FAILED":
            st.error(dash.plain(f"Could not load {h['file']}: {h['message']}"))
    if hist:
        with st.expander(f"Uploads of this session ({len(hist)}; "
                         f"{sum(h['status'] == 'FAILED' for h in hist)} failed)", expanded=False):
            st.dataframe(dash.upload_history(state), hide_index=True, width="stretch")

    b1, b2 = st.columns([1, 2])
    with b2:
        other = st.checkbox("also the same warm-restart drive as CSV, MCAP and candump", value=False,
                            key="bundled_other_formats")
    with b1:
        if st.button("Load the bundled sample logs (SYNTHETIC)", key="load_bundled"):
            with st.spinner("reading the bundled logs..."):
                try:
                    got = dash.load_bundled(state, include_other_formats=other)
                    st.success(dash.plain("Loaded " + ", ".join(e.label for e in got)))
                except Exception as exc:  # noqa: BLE001
                    st.error(dash.plain(dash.error_message(exc)))

    session_logs = dash.logs(state)
    if not session_logs:
        st.info("No logs yet: upload one or load the bundled sample logs.")
        return

    st.subheader("Loaded logs")
    from calib import format_economy, log_fuel_distance

    overview = []
    for e in session_logs.values():
        fuel, dist = log_fuel_distance(e.log)
        overview.append({"log": e.label, "format": e.log.meta.format, "duration_s": round(e.log.duration_s, 1),
                         "distance km": round(dist, 2) if dist == dist else None,
                         "fuel g": round(fuel, 1) if fuel == fuel else None,
                         "economy": format_economy(fuel, dist) if fuel == fuel else "-",
                         "channels": len(e.log.channels()), "sha256": e.sha256[:12]})
    st.dataframe(overview, hide_index=True, width="stretch")
    for g in dash.drive_groups(state, list(session_logs)):
        if len(g) > 1:
            st.info(dash.plain("Same drive in several files: " + ", ".join(session_logs[n].label for n in g)
                    + ". Calibration fits it once and never validates on a copy of a fitted drive."))

    names = list(session_logs)
    sel = st.selectbox("Log", names, key="logs_selected",
                       format_func=lambda n: session_logs[n].label)
    entry = session_logs[sel]
    if entry.synthetic:
        st.warning(dash.plain(f"{entry.name} is SYNTHETIC: simulated by iptm, not measured on a vehicle."))
    for t in dash.log_trouble(entry.log):
        st.error(dash.plain(t))

    tab_plot, tab_report, tab_meta = st.tabs(["Plot", "Channel report", "Provenance"])
    with tab_report:
        st.dataframe(display_report(entry.report), hide_index=True, width="stretch")
        for n in entry.log.meta.notes:
            if n.startswith("warning: "):
                st.warning(dash.plain(n[len("warning: "):]))
        with st.expander("as text"):
            st.code(format_report(entry.report), language=None)
    with tab_plot:
        chans = entry.log.channels()
        default = [c for c in ("speed_mps", "coolant_temp_degC", "cabin_temp_degC") if c in chans][:2] or chans[:1]
        pick = st.multiselect("Channels", chans, default=default, key=f"chans_{sel}")
        if pick:
            separate = st.checkbox("one plot per channel", value=True, key=f"sep_{sel}")
            df = entry.log.data[pick]
            if separate:
                for c in pick:
                    st.caption(c)
                    st.line_chart(df[[c]], x_label="time [s]", height=200)
            else:
                st.line_chart(df, x_label="time [s]")
    with tab_meta:
        st.json({**entry.log.meta.to_dict(), "source": entry.name}, expanded=False)  # never the server's path

    if st.button(f"Remove {sel} from this session", key="remove_log"):
        dash.remove_log(state, sel)
        st.rerun()


_page()
dash.render_sidebar()
