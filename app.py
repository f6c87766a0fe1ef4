"""The workbench dashboard: ``streamlit run app.py``.

Five pages (one file each under ``pages/``): Logs, Calibrate, Optimize, Report, Plan. The pages call the same
library functions as the command line (``calib.*``, ``optimize.*``, ``iptm.pipeline``) and hold no
physics; session state and upload handling are in :mod:`iptm.dashboard`.
"""
import matplotlib

matplotlib.use("Agg")

import streamlit as st  # noqa: E402


st.set_page_config(page_title="iptm - Prius winter workbench", layout="wide")


@st.cache_resource
def _clean_stale_sessions_once() -> int:
    """Once per server start: remove the upload folders of sessions that ended long ago."""
    from iptm.dashboard import remove_stale_sessions

    return remove_stale_sessions()


_clean_stale_sessions_once()

pages = [
    st.Page("pages/logs.py", title="Logs", icon=":material/upload_file:", default=True),
    st.Page("pages/calibrate.py", title="Calibrate", icon=":material/tune:"),
    st.Page("pages/optimize.py", title="Optimize", icon=":material/speed:"),
    st.Page("pages/report.py", title="Report", icon=":material/description:"),
    st.Page("pages/plan.py", title="Plan", icon=":material/route:"),
]
nav = st.navigation(pages)

nav.run()
# The sidebar (session summary, SYNTHETIC-data notice) is drawn by each page after its content
# (iptm.dashboard.render_sidebar), so it reflects logs loaded in the same run.
