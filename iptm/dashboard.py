"""Session state and upload handling for the Streamlit dashboard (``app.py``, ``pages/*.py``).

Pure functions over a mutable mapping ``state`` (``st.session_state`` in the app, a plain ``dict`` in
tests), so everything here is testable without Streamlit. No physics: the dashboard calls the same
library functions as the command line (:mod:`calib.ingest`, :mod:`calib.fit.driver`,
:mod:`optimize.casestudy`, :mod:`iptm.pipeline`).

Per session
    ``state[LOGS]``: ``{name: LoadedLog}``, the session's logs, and ``state[TMP]``: a temporary folder
    created for the session, where uploads are written (original file name kept, so the format is
    detected from the extension) before being read. Two sessions never share either.
Shared between sessions (content-keyed, so a session only ever hits entries of content it has itself)
    the one content-keyed cache (:class:`calib.store.Store` under :func:`cache_dir`, shared with ``iptm run``,
    ``iptm optimize`` and ``iptm sweep``): ingested logs (keyed by the file's SHA-256 and the DBC),
    calibrations, optimisations and sweep cases.

Configuration (environment)
    ``IPTM_MAX_UPLOAD_MB`` (default 200): larger uploads are refused with a message.
    ``IPTM_CACHE_DIR`` (default ``.iptm-cache``): the shared content-keyed cache; ``IPTM_CACHE_MAX_MB``
    (default 4096): its size cap, the least recently used entries removed past it.
    ``IPTM_SESSION_ROOT`` (default: the system temporary folder): where session folders are made.
"""
from __future__ import annotations

import os
import re
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import pandas as pd

from calib import IptmError

LOGS = "iptm_logs"
TMP = "iptm_tmpdir"
SEEN = "iptm_seen_uploads"
DBC = "iptm_dbc"
CALIB = "iptm_calibration"
OPT = "iptm_optimisation"
SCENARIO = "iptm_scenario"
UPLOADS = "iptm_upload_history"
UPLOAD_IDS = "iptm_upload_ids"  # upload file id -> the name of the session log it became
TMP_OWNER = "iptm_tmpdir_owner"  # its finaliser removes the folder when the session state is dropped

DEFAULT_MAX_UPLOAD_MB = 200.0
#: Extensions the readers understand (calib.ingest); anything else is refused up front with a message.
LOG_EXTENSIONS = (".csv", ".txt", ".mcap", ".log", ".candump", ".asc", ".blf", ".trc", ".mf4", ".mdf")


@dataclass
class LoadedLog:
    """One log of the session: where its bytes are, the canonical log and its channel report."""

    name: str
    path: Path
    log: object  # calib.drivelog.DriveLog
    report: pd.DataFrame
    sha256: str  # of the canonical table (DriveLog.content_digest): the key of what is computed from it

    @property
    def synthetic(self) -> bool:
        return bool(self.log.meta.synthetic)

    @property
    def label(self) -> str:
        return self.log.label()


# ---------------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------------
def max_upload_bytes() -> int:
    """The upload size limit in bytes (``IPTM_MAX_UPLOAD_MB``, default 200 MB)."""
    raw = os.environ.get("IPTM_MAX_UPLOAD_MB", "")
    try:
        mb = float(raw) if raw.strip() else DEFAULT_MAX_UPLOAD_MB
    except ValueError:
        mb = DEFAULT_MAX_UPLOAD_MB
    return int(mb * 1024 * 1024)


def cache_dir() -> Path:
    """The one content-keyed cache (:func:`calib.store.default_root`: ``IPTM_CACHE_DIR``, default
    ``.iptm-cache`` in the working folder, the same as ``iptm run``)."""
    from calib import default_root

    return default_root()


def _human(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GB"


# ---------------------------------------------------------------------------------------------------
# the session's folder and logs
# ---------------------------------------------------------------------------------------------------
#: A session folder untouched for this long belongs to a session that has ended (Streamlit has no
#: end-of-session hook): it is removed when the app starts and whenever a new session begins.
SESSION_MAX_IDLE_S = 6 * 3600.0


def _session_root() -> Path:
    root = os.environ.get("IPTM_SESSION_ROOT")
    return Path(root) if root else Path(tempfile.gettempdir())


def remove_stale_sessions(max_idle_s: float = SESSION_MAX_IDLE_S, root=None) -> int:
    """Remove session folders (``iptm-session-*``) whose newest file is older than ``max_idle_s``.

    Returns how many were removed."""
    import shutil
    import time

    root = Path(root) if root is not None else _session_root()
    now, n = time.time(), 0
    for d in root.glob("iptm-session-*"):
        try:
            newest = max([d.stat().st_mtime] + [f.stat().st_mtime for f in d.rglob("*")])
        except OSError:
            continue
        if now - newest > max_idle_s:
            shutil.rmtree(d, ignore_errors=True)
            n += 1
    return n


def end_session(state) -> None:
    """Remove the session's folder and forget its logs (the page's "end session" and the tests)."""
    import shutil

    d = state.pop(TMP, None)
    owner = state.pop(TMP_OWNER, None)
    if owner is not None:
        owner.remove()
    if d:
        shutil.rmtree(d, ignore_errors=True)
    for k in (LOGS, SEEN, UPLOAD_IDS):
        state.pop(k, None)


def session_dir(state) -> Path:
    """The session's private temporary folder (created on first use; stale ones of ended sessions are removed
    then)."""
    d = state.get(TMP)
    if not d or not Path(d).is_dir():
        root = _session_root()
        root.mkdir(parents=True, exist_ok=True)
        remove_stale_sessions(root=root)
        sid = _streamlit_session_id()
        d = tempfile.mkdtemp(prefix=f"iptm-session-{sid}-" if sid else "iptm-session-", dir=root)
        state[TMP] = d
        state[TMP_OWNER] = _FolderOwner(d)
        if sid:
            _start_janitor(root)
    return Path(d)


_SESSION_ID = re.compile(r"iptm-session-([0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12})-")
JANITOR_S = 5.0  # how often the server looks for folders of sessions Streamlit has closed
_janitors: set = set()


def _streamlit_session_id() -> str | None:
    """The Streamlit session's id inside a running app; None elsewhere (tests, the CLI)."""
    try:
        from streamlit.runtime.scriptrunner import get_script_run_ctx

        ctx = get_script_run_ctx(suppress_warning=True)
    except Exception:  # noqa: BLE001 - no Streamlit runtime: no session to follow
        return None
    sid = getattr(ctx, "session_id", None)
    return sid if isinstance(sid, str) and _SESSION_ID.match(f"iptm-session-{sid}-") else None


def remove_closed_sessions(root, is_open) -> int:
    """Remove the folders of sessions for which ``is_open(session_id)`` is False; returns how many."""
    import shutil

    n = 0
    for d in Path(root).glob("iptm-session-*"):
        m = _SESSION_ID.match(d.name)
        if m and not is_open(m.group(1)):
            shutil.rmtree(d, ignore_errors=True)
            n += 1
    return n


def _start_janitor(root) -> None:
    """One daemon thread per folder root: removes a session's folder once Streamlit has closed the session
    (a tab closed and not reconnected within ``server.disconnectedSessionTTL``)."""
    import threading
    import time

    key = str(root)
    if key in _janitors:
        return
    _janitors.add(key)

    def is_open(sid: str) -> bool:
        from streamlit.runtime import Runtime

        return not Runtime.exists() or Runtime.instance().get_app_session(sid) is not None

    def sweep():
        while True:
            time.sleep(JANITOR_S)
            try:
                remove_closed_sessions(root, is_open)
            except Exception:  # noqa: BLE001, S112 - a failed sweep is retried; the start-up sweep remains
                continue

    threading.Thread(target=sweep, name="iptm-session-janitor", daemon=True).start()


class _FolderOwner:
    """Owns a session folder: when Streamlit drops an ended session, its state and this object are freed
    and the folder is removed (also at interpreter exit); the start-up sweep catches a killed server."""

    def __init__(self, folder):
        import shutil
        import weakref

        self._finalizer = weakref.finalize(self, shutil.rmtree, str(folder), True)

    def remove(self) -> None:
        self._finalizer()


def logs(state) -> dict:
    """The session's logs ``{name: LoadedLog}`` (created empty on first use)."""
    if LOGS not in state:
        state[LOGS] = {}
    return state[LOGS]


def log_trouble(log) -> list[str]:
    """:func:`calib.ingest.log_warnings`: damage, channels that lost samples, estimated channels."""
    from calib.ingest import log_warnings

    return log_warnings(log)


def any_synthetic(state) -> bool:
    return any(e.synthetic for e in logs(state).values())


def remove_log(state, name: str) -> None:
    entry = logs(state).pop(name, None)
    if entry is not None and session_dir(state) in Path(entry.path).parents:
        try:
            Path(entry.path).unlink()
        except OSError:
            pass


#: Longest file name kept for an upload (the extension is kept whole; file systems allow 255 bytes).
MAX_NAME_CHARS = 100


def safe_name(name: str) -> str:
    """The file name only (no folders), with characters other than ``[A-Za-z0-9._-]`` replaced and the stem
    shortened to fit :data:`MAX_NAME_CHARS`."""
    base = Path(str(name).replace("\\", "/")).name.strip()
    base = re.sub(r"[^A-Za-z0-9._-]", "_", base).lstrip(".")
    base = base or "upload"
    if len(base) > MAX_NAME_CHARS:
        stem, ext = Path(base).stem, Path(base).suffix[:16]
        base = stem[: MAX_NAME_CHARS - len(ext)] + ext
    return base


def unique_name(state, fname: str, subdir: str = "uploads") -> str:
    """``fname``, or ``stem-2.ext``, ``stem-3.ext``... so that no upload of the session replaces another that
    cleaned to the same name (``log.csv`` twice, ``../../x.csv`` and ``x.csv``)."""
    taken = set(logs(state)) | {p.name for p in (session_dir(state) / subdir).glob("*")}
    if fname not in taken:
        return fname
    stem, ext = Path(fname).stem, Path(fname).suffix
    k = 2
    while f"{stem}-{k}{ext}" in taken:
        k += 1
    return f"{stem}-{k}{ext}"


_MD_SPECIAL = re.compile(r"([\\`*_\[\]#!|<>~$])")


#: A word joiner (U+2060, invisible): placed inside ``://``, ``www.`` and ``@`` it stops Markdown from turning
#: a web address or an e-mail address in user text into a link.
_WJ = "\u2060"


def plain(text) -> str:
    """``text`` escaped so that Streamlit's Markdown shows it as written: a log's header comment, a file name
    or an error message is never rendered (no links, no images fetched from another host, no HTML)."""
    t = _MD_SPECIAL.sub(r"\\\1", str(text)).replace("\n", "  \n")
    t = re.sub(r"(?i)(www)\.", r"\1" + _WJ + ".", t.replace("://", ":" + _WJ + "//"))
    return t.replace("@", _WJ + "@")


def check_size(name: str, size: int, max_bytes: int | None = None) -> None:
    lim = max_upload_bytes() if max_bytes is None else int(max_bytes)
    if size > lim:
        raise IptmError(f"{name}: file is too large ({_human(size)}; the limit is {_human(lim)}) - "
                        "split the log, or raise IPTM_MAX_UPLOAD_MB")
    if size == 0:
        raise IptmError(f"{name}: the file is empty")


def check_log_extension(name: str) -> None:
    ext = Path(name).suffix.lower()
    if ext not in LOG_EXTENSIONS:
        raise IptmError(f"{name}: unsupported file type {ext or '(no extension)'!r} - upload a drive log: "
                        + ", ".join(LOG_EXTENSIONS))


def save_upload(state, name: str, data: bytes, *, subdir: str = "uploads", max_bytes: int | None = None) -> Path:
    """Write uploaded bytes into the session folder under their original (sanitised) name.

    The size is checked before anything is written; the file appears whole or not at all.
    """
    from calib import atomic_path

    fname = safe_name(name)
    check_size(fname, len(data), max_bytes)
    folder = session_dir(state) / subdir
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / fname
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def read_log_cached(path, *, dbc=None, store_root=None):
    """Read a log through the pipeline's content-keyed ingest cache; returns (DriveLog, channel report)."""
    from calib import Store
    from iptm.pipeline import ingest_all

    store = Store(store_root or cache_dir())
    (_, log, report), = ingest_all([Path(path)], store, dbc=str(dbc) if dbc else None, progress=False)
    # the cache may hold a copy read from another path: the session's log names its own file
    log = replace(log, meta=replace(log.meta, source=str(path)))
    return log, report


def add_log_file(state, path, *, dbc=None, name: str | None = None, store_root=None) -> LoadedLog:
    """Read a log file (already on disk) into the session."""
    path = Path(path)
    log, report = read_log_cached(path, dbc=dbc, store_root=store_root)
    entry = LoadedLog(name=name or path.name, path=path, log=log, report=report, sha256=log.content_digest())
    logs(state)[entry.name] = entry
    return entry


def add_upload(state, name: str, data: bytes, *, dbc=None, max_bytes: int | None = None,
               store_root=None) -> LoadedLog:
    """Check, save and read an uploaded log. Raises :class:`IptmError` with a one-line message."""
    fname = unique_name(state, safe_name(name))
    check_log_extension(fname)
    path = save_upload(state, fname, data, max_bytes=max_bytes)
    try:
        return add_log_file(state, path, dbc=dbc, name=fname, store_root=store_root)
    except IptmError as exc:
        path.unlink(missing_ok=True)
        # name the file as the user knows it, not by the session's temporary path
        raise IptmError(str(exc).replace(str(path), fname)) from None
    except Exception as exc:  # noqa: BLE001 - a reader bug must not take the page down
        path.unlink(missing_ok=True)
        raise IptmError(f"{fname}: cannot read this log ({type(exc).__name__}: {str(exc)[:200]})") from None


def set_dbc(state, name: str, data: bytes, *, max_bytes: int | None = None) -> Path:
    """Save an uploaded DBC for the session's CAN logs (checked by parsing it with cantools)."""
    fname = safe_name(name)
    if Path(fname).suffix.lower() != ".dbc":
        raise IptmError(f"{fname}: a CAN database must be a .dbc file")
    path = save_upload(state, fname, data, subdir="dbc", max_bytes=max_bytes)
    try:
        import cantools

        cantools.database.load_file(str(path))
    except Exception as exc:  # noqa: BLE001 - cantools raises many types
        path.unlink(missing_ok=True)
        raise IptmError(f"{fname}: not a readable DBC ({str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__})"
                        ) from None
    state[DBC] = str(path)
    return path


def bundled_logs(include_other_formats: bool = False, root: Path | None = None) -> list[Path]:
    """The bundled sample logs (all SYNTHETIC): the ``.blf`` drives, optionally the same drive as CSV/MCAP/candump."""
    from iptm.bundled import bundled_logs_dir

    root = Path(root or bundled_logs_dir())
    files = sorted(root.glob("*.blf"))
    if include_other_formats:
        files += sorted(p for p in root.iterdir() if p.suffix.lower() in (".csv", ".mcap", ".log"))
    return files


def load_bundled(state, include_other_formats: bool = False, store_root=None) -> list[LoadedLog]:
    return [add_log_file(state, p, store_root=store_root) for p in bundled_logs(include_other_formats)]


# ---------------------------------------------------------------------------------------------------
# calibration helpers
# ---------------------------------------------------------------------------------------------------
def calibratable_parameters() -> list[str]:
    from calib.fit import SUBSYSTEM_PARAMS

    return [n for names in SUBSYSTEM_PARAMS.values() for n in names]


def subsystem_of(name: str) -> str:
    from calib.fit import SUBSYSTEM_PARAMS

    return next((s for s, names in SUBSYSTEM_PARAMS.items() if name in names), "")


def truncate(log, seconds: float | None):
    """The first ``seconds`` of a log (``None``/0: the whole log). Same meta (provenance, SHA-256)."""
    from calib import DriveLog

    if not seconds or seconds <= 0:
        return log
    t = log.data.index.to_numpy(float)
    return DriveLog(data=log.data.loc[t <= t[0] + float(seconds)], meta=log.meta)


def _fmt(v, digits=5):
    if v is None:
        return ""
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x, 4) for x in v) + "]"
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    return "nan" if f != f else f"{f:.{digits}g}"


def parameter_table(params, names=None) -> pd.DataFrame:
    """Parameter table for display: value, standard error, relative error, status and identifiability.

    ``identifiable`` is ``yes`` for an estimated parameter, ``weak`` for one the logs informed little (the
    posterior is mostly the prior; the note says how much), ``-`` for fixed / not attempted ones.
    """
    names = list(names or calibratable_parameters())
    rows = []
    for n in names:
        p = params.param(n)
        rel = ""
        if not p.is_table and isinstance(p.stderr, (int, float)) and p.value:
            rel = f"{100 * abs(float(p.stderr) / float(p.value)):.2g} %"
        status = p.status or "prior"
        flag = {"estimated": "yes", "weak": "weak"}.get(status, "-")
        n_est = p.n_entries_estimated()
        if n_est and status == "estimated" and n_est[0] < n_est[1]:
            flag = f"{n_est[0]} of {n_est[1]} entries"
        rows.append({"parameter": n, "subsystem": subsystem_of(n), "value": _fmt(p.value), "unit": p.unit,
                     "stderr": _fmt(p.stderr), "rel. stderr": rel, "status": p.status_text(), "identifiable": flag,
                     "note": p.note or ""})
    return pd.DataFrame(rows)


# ---------------------------------------------------------------------------------------------------
# optimisation helpers
# ---------------------------------------------------------------------------------------------------
def cycle_csv_from_log(state, entry: LoadedLog) -> Path:
    """Write a session log's speed trace as a cycle CSV (``time_s,speed_kph``) in the session folder."""
    from calib.model import load_cycle

    cyc = load_cycle(entry.log)
    out = session_dir(state) / "cycles" / f"{Path(entry.name).stem}_cycle.csv"
    out.parent.mkdir(parents=True, exist_ok=True)
    pd.DataFrame({"time_s": cyc.t, "speed_kph": cyc.v * 3.6}).to_csv(out, index=False, float_format="%.6g")
    return out


def scenario_key(scenario) -> dict:
    """The scenario as a dict whose ``cycle`` names the content (SHA-256) of a cycle file, not its path."""
    from calib import file_sha256

    d = scenario.to_dict()
    p = Path(str(d.get("cycle", "")))
    if p.suffix and p.is_file():
        d["cycle"] = "sha256:" + file_sha256(p)
    return d


def merge_case_studies(parts):
    """One :class:`optimize.casestudy.CaseStudy` from case studies of single strategies (same scenario)."""
    from optimize import CaseStudy

    sims, outs, timings, rule = {}, {}, {}, None
    for cs in parts:
        sims.update(cs.sims)
        outs.update(cs.outcomes)
        timings.update(cs.timings)
        rule = cs.rule if cs.rule is not None else rule
    order = [k for k in ("rule", "baseline", "thermal", "thermal_cabin", "baseline_warm") if k in sims]
    order += [k for k in sims if k not in order]
    return CaseStudy({k: sims[k] for k in order}, outs, parts[0].scenario, parts[0].grids, rule, timings)


def render_sidebar(state=None) -> None:
    """The sidebar: what the workbench is, the session's logs, and a notice when any of them is SYNTHETIC.

    Called by every page after its content (so it reflects logs loaded in the same run).
    """
    import streamlit as st

    state = st.session_state if state is None else state
    with st.sidebar:
        st.markdown("**Prius winter workbench**  \ncalibrate a Prius model from winter drive logs; optimise power "
                    "split, engine thermal management and cabin heating by DP (after Gong et al., CCTA 2019)")
        session_logs = logs(state)
        if session_logs:
            st.caption(f"{len(session_logs)} log(s) loaded in this session")
        synth = [e.name for e in session_logs.values() if e.synthetic]
        if synth:
            st.warning(plain("SYNTHETIC data: " + ", ".join(synth) + (" was" if len(synth) == 1 else " were")
                       + " simulated by iptm, not measured on a vehicle. Results from synthetic logs demonstrate "
                       "the workbench; they say nothing about a real car."), icon=":material/science:")


_RAW_BYTES = re.compile(r"(\((?:\d{1,3}, ){3,}\d{1,3}\)|b'[^']{4,}'|b\"[^\"]{4,}\")")


def error_message(exc: BaseException) -> str:
    """One line for the page: the library's message for an IptmError, type and text for anything else.
    Raw file bytes that a reader quoted (a header as a tuple of byte values) are replaced by words."""
    if isinstance(exc, IptmError):
        text = str(exc)
    else:
        first = str(exc).splitlines()[0][:300] if str(exc) else ""
        text = f"unexpected error ({type(exc).__name__}{': ' + first if first else ''})"
    text = _RAW_BYTES.sub("(the file's first bytes are not this format's header)", text)
    return scrub_paths(text)


_ABS_PATH = re.compile(r"(?:[A-Za-z]:)?[\\/](?:[^\s'\"():,;]+[\\/])+([^\s'\"():,;/\\]+)")


def scrub_paths(text: str) -> str:
    """Server paths in a message replaced by the file's own name: a user sees ``log.csv``, never the session
    folder it was saved in."""
    return _ABS_PATH.sub(lambda m: m.group(1), str(text))


# ---------------------------------------------------------------------------------------------------
# the session's upload history
# ---------------------------------------------------------------------------------------------------
def record_upload(state, name: str, ok: bool, message: str) -> None:
    """Remember an upload attempt: every upload stays listed with its status and message."""
    state.setdefault(UPLOADS, []).append({"file": name, "status": "loaded" if ok else "FAILED",
                                          "message": message})


def upload_history(state) -> pd.DataFrame:
    """Every upload of the session, newest first: file, status (loaded / FAILED), message."""
    return pd.DataFrame(list(reversed(state.get(UPLOADS, []))), columns=["file", "status", "message"])


# ---------------------------------------------------------------------------------------------------
# which logs are one drive
# ---------------------------------------------------------------------------------------------------
def drive_groups(state, names) -> list[list[str]]:
    """The session's logs ``names`` grouped by drive (copies of one drive in several formats together)."""
    from calib.ingest import group_drives

    names = list(names)
    entries = logs(state)
    return [[names[i] for i in g] for g in group_drives([entries[n].log for n in names])]


def same_drive_as(state, name: str, others) -> str | None:
    """The first of ``others`` that records the same drive as ``name`` (None if none)."""
    from calib.ingest import same_drive

    entries = logs(state)
    return next((o for o in others if o != name and same_drive(entries[o].log, entries[name].log)), None)
