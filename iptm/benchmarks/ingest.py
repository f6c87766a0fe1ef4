"""Ingestion benchmark: a synthetic 30-minute CAN dump at realistic bus rates, about a million frames.

The dump carries our Prius DBC's messages at powertrain rates (battery 100 Hz, speed and engine speed
50 Hz, fuel/torque 20 Hz, battery state 10 Hz, thermal 1 Hz) plus traffic the DBC does not decode
(steering, wheel speeds, body...) at the rates seen on a Toyota bus, so the reader has to skip most
frames, as on a real car.

Memory is the peak resident set size (``VmHWM`` from ``/proc/self/status``; ``ru_maxrss`` where there is
no /proc) of a fresh Python process that only ingests the file, reported both as the whole peak and as the
rise above that process's peak after its imports; wall time is measured in the same process around
``read_log``.

Run: ``python -c "from iptm.benchmarks.ingest import run; run()"`` (``run(quick=True)``: 3 minutes).
"""
from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# Non-decoded traffic: CAN ID -> rate, Hz (typical of a Toyota powertrain/chassis bus).
FILLER = {0x025: 80.0, 0x0AA: 80.0, 0x0B0: 80.0, 0x260: 50.0, 0x2C1: 33.0, 0x224: 40.0, 0x3BC: 5.0,
          0x1D2: 33.0, 0x1D3: 33.0, 0x245: 20.0, 0x262: 10.0, 0x320: 5.0}
RATES = {"speed_mps": 50.0, "bat_current_A": 100.0, "bat_voltage_V": 100.0, "engine_speed_rpm": 50.0,
         "engine_torque_Nm": 20.0, "fuel_rate_g_per_s": 20.0, "soc": 10.0, "bat_temp_degC": 1.0}

_CHILD = r"""
import json, resource, sys, time

def hwm_kb():
    # VmHWM is per address space, so unlike ru_maxrss it does not inherit the parent's peak across exec.
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss

from calib.ingest import read_log
base = hwm_kb()
t = time.perf_counter()
log = read_log(sys.argv[1])
wall = time.perf_counter() - t
peak = hwm_kb()
print(json.dumps({"wall_s": wall, "peak_rss_mb": peak / 1024, "rise_mb": (peak - base) / 1024,
                  "rows": len(log.data), "channels": log.channels()}))
"""


def build_dump(path, duration_s: float = 1800.0, seed: int = 0) -> int:
    """Write the synthetic dump; returns the number of frames."""
    from calib import LogMeta
    from testcars.fabricate import fabricate_streams
    from calib.ingest import can_frames, write_can_frames

    streams, meta = fabricate_streams(duration_s, seed=seed, rates=RATES, dropout=None)
    fr = can_frames(streams, synthetic=True)
    rng = np.random.default_rng(seed)
    ts, ids, datas, dlcs = [fr["t"]], [fr["id"]], [fr["data"]], [fr["dlc"]]
    for cid, hz in FILLER.items():
        t = np.arange(rng.uniform(0, 1 / hz), duration_s, 1 / hz)
        ts.append(t)
        ids.append(np.full(len(t), cid, dtype=np.int64))
        datas.append(rng.integers(0, 256, (len(t), 8), dtype=np.uint8))
        dlcs.append(np.full(len(t), 8, dtype=np.uint8))
    t = np.concatenate(ts)
    order = np.argsort(t, kind="stable")
    frames = {"t": t[order], "id": np.concatenate(ids)[order], "data": np.concatenate(datas)[order],
              "dlc": np.concatenate(dlcs)[order]}
    assert isinstance(meta, LogMeta)
    write_can_frames(frames, path, "candump", start_epoch=1768462200.0,
                     header=["SYNTHETIC drive log: ingestion benchmark, not measured on a vehicle"])
    return int(len(t))


def run(quick: bool = False) -> dict:
    """Build the dump in a temporary folder, ingest it in a fresh process, print and return the figures.

    Returns
    -------
    dict
        ``frames``, ``file_mb``, ``build_s``, ``wall_s`` (ingest), ``peak_rss_mb``, ``rise_mb``,
        ``targets`` and ``ok``.
    """
    duration = 180.0 if quick else 1800.0
    with tempfile.TemporaryDirectory(prefix="iptm-bench-") as d:
        path = Path(d) / "bench_30min.log"
        t = time.perf_counter()
        n = build_dump(path, duration)
        build_s = time.perf_counter() - t
        size_mb = path.stat().st_size / 1e6
        root = Path(__file__).resolve().parents[2]
        proc = subprocess.run([sys.executable, "-c", _CHILD, str(path)], capture_output=True, text=True,
                              cwd=str(root), check=False)
        if proc.returncode != 0:
            raise RuntimeError(f"ingest benchmark child failed: {proc.stderr.strip().splitlines()[-1:]}")
        res = json.loads(proc.stdout.strip().splitlines()[-1])
    out = {"duration_s": duration, "frames": n, "file_mb": round(size_mb, 1), "build_s": round(build_s, 2),
           "wall_s": round(res["wall_s"], 2), "peak_rss_mb": round(res["peak_rss_mb"], 1),
           "rise_mb": round(res["rise_mb"], 1), "rows": res["rows"], "channels": res["channels"],
           "memory_measure": "VmHWM (peak RSS) of a fresh process that only ingests (peak, and rise after imports)",
           "targets": {"wall_s": 60.0, "peak_rss_mb": 1024.0}}
    out["ok"] = out["wall_s"] < 60.0 and out["peak_rss_mb"] < 1024.0
    print(f"ingest benchmark: {n:,} frames ({size_mb:.0f} MB candump, {duration / 60:.0f} min): "
          f"ingest {out['wall_s']:.1f} s, peak RSS {out['peak_rss_mb']:.0f} MB "
          f"(+{out['rise_mb']:.0f} MB over imports); targets < 60 s, < 1024 MB: {'OK' if out['ok'] else 'MISSED'}")
    return out


if __name__ == "__main__":
    run(quick="--quick" in sys.argv)
