"""The command line against hostile input, as a user would run it: unit bombs, decompression bombs, deep
nesting, parameter files that try to widen physics, non-finite scenario fields, grids that ask for millions of
states, and their kin.

Each case runs ``python -m iptm.cli ...`` in a fresh folder holding only its inputs and an empty ``out/``
folder, and must answer within 10 s and 500 MB above the baseline of the same command (the same process
answering a plain error of the same command, so start-up and imports are not counted), with exactly one
clear message on stderr, exit status 2, no traceback and nothing written: no output file, no temporary file,
nothing new in the folder. A log that still holds good data next to a bomb may be read with its damage
named instead (exit 0, each warning a single ``iptm: warning:`` line naming the chunk, message or container,
the output complete): that is what the issue asks of a chunk over the budget ("refused by name").
"""
import os
import resource
import struct
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from testcars.fabricate import fabricate_streams
from calib.ingest.writers import write_streams
from iptm.benchmarks.fuzz import _blf_container, _blf_objects, _mcap_records, _zlib_zeros, _zstd_zeros

ROOT = Path(__file__).resolve().parents[1]
LIMIT_S = 10.0
LIMIT_MB = 500.0
GiB = 1 << 30
#: Address space a case may take before it gets a MemoryError (keeps a runaway case off the machine).
AS_LIMIT = 8 * GiB


@dataclass
class Run:
    rc: int | None
    stdout: str
    stderr: str
    wall_s: float
    maxrss_mb: float
    killed: bool


def _cli(args, cwd: Path, timeout: float) -> Run:
    """``python -m iptm.cli ARGS`` in ``cwd``; wall time and peak resident memory of that child alone."""
    import subprocess

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (AS_LIMIT, AS_LIMIT))

    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    env.pop("IPTM_MAX_INFLATE_MB", None)
    out_f, err_f = cwd.parent / f".{cwd.name}.stdout", cwd.parent / f".{cwd.name}.stderr"
    with open(out_f, "wb") as fo, open(err_f, "wb") as fe:
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "iptm.cli", *map(str, args)], cwd=cwd, stdout=fo, stderr=fe,
                                env=env, preexec_fn=limit)
        killed = False
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() - t0 > timeout:
                proc.kill()
                killed = True
                pid, status, usage = os.wait4(proc.pid, 0)
                break
            time.sleep(0.02)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait for it again
    rc = None if killed else proc.returncode
    return Run(rc, out_f.read_text(errors="replace"), err_f.read_text(errors="replace"), wall,
               usage.ru_maxrss / 1024, killed)


def _messages(stderr: str) -> list[str]:
    """What stderr says, one entry per line (a progress bar's redraws, split at carriage returns, count too)."""
    return [p.strip() for line in stderr.splitlines() for p in line.split("\r") if p.strip()]


def _files(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


# --- inputs -------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A known 300-s drive: MCAP (two zstd chunks), BLF and CSV."""
    d = tmp_path_factory.mktemp("drive")
    streams, meta = fabricate_streams(300, seed=7)
    mcap = write_streams(streams, meta, d / "drive.mcap", "mcap")
    blf = write_streams(streams, meta, d / "drive.blf", "blf")
    csv = write_streams(streams, meta, d / "drive.csv", "csv")
    assert sum(op == 6 for op, _, _ in _mcap_records(mcap.read_bytes())) == 2
    return {"mcap": mcap.read_bytes(), "blf": blf.read_bytes(), "csv": csv.read_bytes()}


def _chunk(payload: bytes, declared: int, compression: str = "zstd") -> bytes:
    body = (struct.pack("<QQQI", 0, 0, declared, 0) + struct.pack("<I", len(compression)) + compression.encode()
            + struct.pack("<Q", len(payload)) + payload)
    return bytes([6]) + struct.pack("<Q", len(body)) + body


def _mcap_with(data: bytes, bomb: bytes) -> tuple[bytes, int]:
    """The drive with ``bomb`` before its second chunk, and the bomb's byte."""
    second = [a for op, a, _ in _mcap_records(data) if op == 6][1]
    return data[:second] + bomb + data[second:], second


def _mcap_only_bomb(data: bytes, bomb: bytes) -> tuple[bytes, int]:
    """The drive's records with its chunks replaced by ``bomb``: nothing readable but the bomb."""
    recs = _mcap_records(data)
    chunks = [(a, b) for op, a, b in recs if op == 6]
    at = chunks[0][0]
    return data[:at] + bomb + data[chunks[-1][1]:], at


def _deep_mcap(path: Path):
    """1,000 messages on two topics, one of them nested 100,000 levels deep."""
    from test_ingest_bombs import deep_mcap  # the tests folder is on the path (rootdir import mode)

    deep_mcap(path)


def _blf_with_bomb(data: bytes) -> tuple[bytes, int]:
    """The drive's BLF with a zlib container of 1 GiB of zeros (1 MB in the file) declaring 128 KiB."""
    out = bytearray(data)
    at = _blf_objects(data)[1]
    out[at:at] = _blf_container(_zlib_zeros(GiB), declared=128 * 1024)
    struct.pack_into("<Q", out, 16, len(out))
    return bytes(out), at


TOML = {
    # the parameter files
    "m_kg_negative_wide_bounds": "[parameters.m_kg]\nvalue = -1500\nbounds = [-1e9, 1e9]\n",
    "capacity_1e300_infinite_bounds": "[parameters.C_bat_Ah]\nvalue = 1e300\nbounds = [-inf, inf]\n",
    "capacity_zero": "[parameters.C_bat_Ah]\nvalue = 0\n",
    "capacity_zero_bounds_from_zero": "[parameters.C_bat_Ah]\nvalue = 0\nbounds = [0, 20]\n",
    "efficiency_zero_in_bounds": "[parameters.eta_em]\nvalue = 0\nbounds = [0, 1]\n",
    "prior_sd_negative": "[parameters.C_eng_J_per_K]\nvalue = 80000\nprior_sd = -5\n",
    "prior_sd_zero": "[parameters.C_eng_J_per_K]\nvalue = 80000\nprior_sd = 0\n",
    "prior_sd_nan": "[parameters.C_eng_J_per_K]\nvalue = 80000\nprior_sd = nan\n",
    "prior_sd_text": '[parameters.C_eng_J_per_K]\nvalue = 80000\nprior_sd = "abc"\n',
    "unit_bomb": '[parameters.m_kg]\nvalue = 1500\nunit = "kg**9**9**9"\n',
    # kin
    "value_text": '[parameters.m_kg]\nvalue = "abc"\n',
    "value_huge_integer": "[parameters.m_kg]\nvalue = 1" + "0" * 400 + "\n",
    "value_deep_array": "[parameters.m_kg]\nvalue = " + "[" * 100_000 + "1" + "]" * 100_000 + "\n",
    "table_of_text": '[parameters.U_oc_V]\nvalue = ["a", "b"]\n',
    # scenarios
    "duration_nan": '[scenario]\ncycle = "nycc"\nduration_s = nan\n',
    "ambient_nan": '[scenario]\ncycle = "nycc"\nduration_s = 20\nT_amb = nan\n',
    "heater_min_above_max": '[scenario]\ncycle = "nycc"\nduration_s = 20\nQ_heat_min = 2000\nQ_heat_max = 1000\n',
    "grids_soc_1e-7": '[scenario]\ncycle = "nycc"\nduration_s = 20\n[grids]\nsoc = 1e-7\n',
    "scenario_huge_integer": '[scenario]\ncycle = "nycc"\nduration_s = 1' + "0" * 5000 + "\n",
    "scenario_deep_array": '[scenario]\ncycle = "nycc"\nT_amb = ' + "[" * 100_000 + "]" * 100_000 + "\n",
    "scenario_cycle_table": '[scenario]\ncycle = {a = 1}\nduration_s = 20\n',
}


@dataclass
class Case:
    id: str
    cmd: str  # the subcommand (its baseline)
    args: list  # {name} is an input file, {out} the output target
    inputs: dict  # name -> bytes, or a builder (path, drive) -> None
    message: str  # a regular expression the message must match
    damage_ok: bool = False  # a bomb next to good data may be read with its damage named (exit 0)
    xfail: str = ""


def _csv(head: str, rows: str = "0,10\n1,11\n2,12\n") -> bytes:
    return (head + "\n" + rows).encode()


def _optimize(name, extra=(), message="", xfail=""):
    return Case(f"optimize-params-{name}", "optimize",
                ["optimize", "--params", "p.toml", "--cycle", "nycc", "--duration", "20", "--formulation", "rule",
                 "--no-cache", *extra], {"p.toml": TOML[name].encode()}, message, xfail=xfail)


def _calibrate(name, message, xfail=""):
    return Case(f"calibrate-params-{name}", "calibrate",
                ["calibrate", "log.csv", "--params", "p.toml", "--out", "{out}", "--quiet"],
                {"p.toml": TOML[name].encode(), "log.csv": "csv"}, message, xfail=xfail)


def _scenario(name, message, xfail=""):
    return Case(f"optimize-scenario-{name}", "optimize",
                ["optimize", "--scenario", "s.toml", "--formulation", "baseline", "--no-cache"],
                {"s.toml": TOML[name].encode()}, message, xfail=xfail)


def _bomb_zstd(path, drive):
    data, at = _mcap_with(drive["mcap"], _chunk(_zstd_zeros(GiB), declared=4096))
    assert len(data) - len(drive["mcap"]) < 34_000  # 33 kB -> 1 GiB
    path.write_bytes(data)
    return at


def _bomb_8gib(path, drive):
    data, at = _mcap_with(drive["mcap"], _chunk(_zstd_zeros(8 * GiB), declared=8 * GiB))
    path.write_bytes(data)
    return at


def _bomb_alone(path, drive):
    data, at = _mcap_only_bomb(drive["mcap"], _chunk(_zstd_zeros(GiB), declared=4096))
    path.write_bytes(data)
    return at


def _blf_bomb(path, drive):
    data, at = _blf_with_bomb(drive["blf"])
    path.write_bytes(data)
    return at


def _deep(path, drive):
    _deep_mcap(path)
    return None


def _candump_huge_time(path, drive):
    path.write_text("(1e308) can0 0B4#00000000000A6600\n(1e308) can0 0B4#00000000000A6700\n")


CASES = [
    # unit bombs
    Case("ingest-csv-unit-tower", "ingest", ["ingest", "b.csv", "--out", "{out}"],
         {"b.csv": _csv("time [s],speed [km/h**9**9**9]")}, r"b\.csv.*exponent 9 is larger than"),
    Case("ingest-csv-unit-nested", "ingest", ["ingest", "b.csv", "--out", "{out}"],
         {"b.csv": _csv("time [s],speed [" + "(" * 10_000 + "km/h" + ")" * 10_000 + "]")}, r"b\.csv"),
    Case("ingest-csv-unit-long", "ingest", ["ingest", "b.csv", "--out", "{out}"],
         {"b.csv": _csv("time [s],speed [" + "km*" * 100_000 + "h]")}, r"b\.csv"),
    Case("ingest-time-unit-tower", "ingest", ["ingest", "b.csv", "--out", "{out}"],
         {"b.csv": _csv("time [s**9**9**9],speed [km/h]")}, r"b\.csv.*s\*\*9\*\*9\*\*9"),
    Case("ingest-map-unit-bomb", "ingest", ["ingest", "log.csv", "--map", "m.toml", "--out", "{out}"],
         {"log.csv": _csv("time [s],spd"), "m.toml": b'[columns]\nspd = "speed_mps [m**9**9**9]"\n'},
         r"(m\.toml|log\.csv).*exponent"),
    Case("ingest-dbc-unit-bomb", "ingest", ["ingest", "log.log", "--dbc", "u.dbc", "--out", "{out}"],
         {"log.log": b"(0.0) can0 0B4#00000000000A6600\n(0.1) can0 0B4#00000000000A6700\n",
          "u.dbc": ('VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: X\n\nBO_ 180 SPEED: 8 X\n SG_ SPEED : 47|16@0+ (0.01,0) '
                    '[0|250] "km/h**9**9**9" X\n').encode()},
         r"(u\.dbc|log\.log).*exponent"),
    _optimize("unit_bomb", message=r"p\.toml.*m_kg.*exponent 9 is larger than"),
    # decompression bombs and deep nesting
    Case("ingest-mcap-zstd-1GiB-in-33kB", "ingest", ["ingest", "b.mcap", "--out", "{out}"], {"b.mcap": _bomb_zstd},
         r"b\.mcap.*chunk at byte {at}.*inflates beyond its declared 4096 bytes", damage_ok=True),
    Case("ingest-mcap-chunk-declaring-8GiB", "ingest", ["ingest", "b.mcap", "--out", "{out}"],
         {"b.mcap": _bomb_8gib}, r"b\.mcap.*chunk at byte {at}.*declares 8 GiB", damage_ok=True),
    Case("ingest-mcap-zstd-bomb-strict", "ingest", ["ingest", "b.mcap", "--strict", "--out", "{out}"],
         {"b.mcap": _bomb_zstd}, r"b\.mcap \(chunk at byte {at}\): inflates beyond its declared 4096 bytes"),
    Case("ingest-mcap-nothing-but-a-bomb", "ingest", ["ingest", "b.mcap", "--out", "{out}"], {"b.mcap": _bomb_alone},
         r"b\.mcap.*chunk at byte {at}"),
    Case("ingest-mcap-100000-deep-message", "ingest", ["ingest", "d.mcap", "--out", "{out}"], {"d.mcap": _deep},
         r"d\.mcap.*message 1001 on /vehicle/speed.*nested deeper than 64 levels", damage_ok=True),
    Case("ingest-blf-zlib-1GiB-container", "ingest", ["ingest", "b.blf", "--out", "{out}"], {"b.blf": _blf_bomb},
         r"b\.blf.*container at byte {at} inflates beyond its declared 131072 bytes", damage_ok=True),
    # parameter files that try to widen physics, non-finite and odd values
    _optimize("m_kg_negative_wide_bounds", message=r"p\.toml.*bounds of m_kg.*physical limits"),
    _optimize("capacity_1e300_infinite_bounds", message=r"p\.toml.*bounds of C_bat_Ah.*finite"),
    _optimize("capacity_zero", message=r"p\.toml.*C_bat_Ah = 0 .*outside its bounds"),
    _optimize("capacity_zero_bounds_from_zero", message=r"p\.toml.*bounds of C_bat_Ah.*physical limits"),
    _optimize("efficiency_zero_in_bounds", message=r"p\.toml.*bounds of eta_em.*physical limits"),
    _calibrate("prior_sd_negative", r"p\.toml.*prior_sd of C_eng_J_per_K must be a positive finite number, got -5"),
    _calibrate("prior_sd_zero", r"p\.toml.*prior_sd of C_eng_J_per_K must be a positive finite number, got 0"),
    _calibrate("prior_sd_nan", r"p\.toml.*prior_sd of C_eng_J_per_K must be a positive finite number, got nan"),
    _calibrate("prior_sd_text", r"p\.toml.*prior_sd of C_eng_J_per_K must be a positive finite number, got 'abc'"),
    _optimize("value_text", message=r"p\.toml.*m_kg"),
    _optimize("value_huge_integer", message=r"p\.toml.*m_kg"),
    _optimize("value_deep_array", message=r"p\.toml"),
    _optimize("table_of_text", message=r"p\.toml.*U_oc_V"),
    # scenarios and grids
    _scenario("duration_nan", r"s\.toml.*duration_s = nan: give a finite number"),
    _scenario("ambient_nan", r"s\.toml.*T_amb = nan: give a finite number"),
    _scenario("heater_min_above_max", r"s\.toml.*Q_heat_min = 2000 and Q_heat_max = 1000"),
    _scenario("grids_soc_1e-7", r"SOC grid.*1e-07.*would have"),
    _scenario("scenario_huge_integer", r"s\.toml.*(duration_s|4300 digits)"),
    _scenario("scenario_deep_array", r"s\.toml"),
    _scenario("scenario_cycle_table", r"s\.toml.*cycle"),
    Case("optimize-grid-soc-1e-7", "optimize",
         ["optimize", "--cycle", "nycc", "--duration", "20", "--grid", "soc=1e-7", "--formulation", "baseline",
          "--no-cache"], {}, r"SOC grid.*1e-07.*would have"),
    Case("optimize-grid-pbat-3W", "optimize",
         ["optimize", "--cycle", "nycc", "--duration", "590", "--grid", "pbat=3", "--formulation", "baseline",
          "--no-cache"], {}, r"transition tables .* MB \(budget"),
    Case("optimize-grid-tcab-1e-3", "optimize",
         ["optimize", "--cycle", "nycc", "--duration", "20", "--grid", "tcab=0.001", "--formulation", "thermal_cabin",
          "--no-cache"], {}, r"(states|grid)"),
    Case("optimize-duration-nan", "optimize",
         ["optimize", "--cycle", "nycc", "--duration", "nan", "--formulation", "rule", "--no-cache"], {},
         r"duration_s = nan: give a finite number"),
    Case("optimize-ambient-inf", "optimize",
         ["optimize", "--cycle", "nycc", "--duration", "20", "--ambient", "inf", "--formulation", "rule", "--no-cache"],
         {}, r"T_amb = inf: give a finite number"),
    # extreme numbers in logs
    Case("ingest-csv-time-1e308", "ingest", ["ingest", "n.csv", "--out", "{out}"],
         {"n.csv": _csv("time [s],speed [km/h]", "0,10\n1e308,11\n-1e308,12\n2,13\n")}, r"n\.csv", damage_ok=True),
    Case("ingest-candump-time-1e308", "ingest", ["ingest", "c.log", "--out", "{out}"], {"c.log": _candump_huge_time},
         r"c\.log.*not a date", damage_ok=True),
]


@pytest.fixture(scope="module")
def baselines(tmp_path_factory, drive):
    """Wall time and peak memory of each command answering a plain error (start-up and imports)."""
    d = tmp_path_factory.mktemp("baseline")
    (d / "p.toml").write_text("[parameters.no_such_parameter]\nvalue = 1\n")
    (d / "log.csv").write_bytes(drive["csv"])
    (d / "b.csv").write_bytes(_csv("time [s],speed [furlongs_per_fortnight_x]"))
    plain = {"ingest": ["ingest", "b.csv", "--out", "out/x.parquet"],
             "optimize": ["optimize", "--params", "p.toml", "--cycle", "nycc", "--duration", "20", "--no-cache"],
             "calibrate": ["calibrate", "log.csv", "--params", "p.toml", "--out", "out/a.toml", "--quiet"]}
    out = {}
    for cmd, args in plain.items():
        r = _cli(args, d, timeout=120)
        assert r.rc == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
        out[cmd] = r
    return out


@pytest.mark.parametrize("case", [pytest.param(c, id=c.id, marks=[pytest.mark.xfail(strict=True, reason=c.xfail)]
                                               if c.xfail else []) for c in CASES])
def test_hostile_input_is_answered_at_once(case, tmp_path, drive, baselines):
    import re

    work = tmp_path / "work"
    work.mkdir()
    (work / "out").mkdir()
    at = None
    for name, content in case.inputs.items():
        p = work / name
        if content == "csv":
            p.write_bytes(drive["csv"])
        elif callable(content):
            at = content(p, drive)
        else:
            p.write_bytes(content)
    before = _files(work)
    out = "out/" + ("artifact.toml" if case.cmd == "calibrate" else "result.parquet")
    args = [a.replace("{out}", out) for a in case.args]
    base = baselines[case.cmd]
    run = _cli(args, work, timeout=base.wall_s + 3 * LIMIT_S)
    assert not run.killed, f"no answer within {run.wall_s:.0f} s"
    assert run.wall_s - base.wall_s < LIMIT_S, (run.wall_s, base.wall_s)
    assert run.maxrss_mb - base.maxrss_mb < LIMIT_MB, (run.maxrss_mb, base.maxrss_mb)
    assert "Traceback" not in run.stderr and "Traceback" not in run.stdout, run.stderr[-3000:]
    msgs = _messages(run.stderr)
    pattern = case.message.replace("{at}", str(at))
    if case.damage_ok and run.rc == 0:
        # read with its damage named: warnings only, one line each, the bomb among them; the output complete
        assert msgs and all(re.match(r"iptm(?: \w+: [^:]+)?: warning: ", m) for m in msgs), msgs
        assert any(re.search(pattern, m) for m in msgs), (pattern, msgs)
        assert _files(work) - before == {out}, _files(work) - before
        return
    assert run.rc == 2, (run.rc, run.stderr[-3000:])
    assert len(msgs) == 1, msgs
    assert msgs[0].startswith(f"iptm {case.cmd}: error: "), msgs
    assert re.search(pattern, msgs[0]), (pattern, msgs[0])
    assert _files(work) == before, _files(work) - before  # nothing written, not even a temporary file


def test_a_drive_too_short_to_burn_fuel_is_not_an_error(tmp_path):
    """10 s of NYCC start no engine: the table has no saving to show (a dash), not a ZeroDivisionError."""
    run = _cli(["optimize", "--cycle", "nycc", "--duration", "10", "--formulation", "rule", "--no-cache"], tmp_path,
               timeout=120)
    assert run.rc == 0 and "Traceback" not in run.stderr, run.stderr[-2000:]
