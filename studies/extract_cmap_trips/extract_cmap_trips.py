"""Cut the causal controllers' CMAP test trips out of FASTSim's CMAP subset (run once; its output is bundled).

The CMAP Travel Tracker subset in NREL FASTSim's resources (``python/fastsim/resources/cycles/cmap_subset``,
Apache-2.0) holds GPS speed logs per vehicle and day and a ``trips.csv`` per vehicle with each trip's start
and end. The rule, fixed before any of these trips was simulated: trips of 5 to 30 minutes whose samples
are never more than 2 s apart, of vehicles other than the one whose commute is already bundled
(``cmap_chicago_commute``), the first such trip of each vehicle (``--nth 2`` / ``3`` / ``4``: the second,
third or fourth, for the vehicles that have one: the drive sets cmap-trip2 and cmap-trip3 and the CMAP trip of
wltc-high-cmap-trip4).
Each is resampled to 1 Hz (linear across the 2-s gaps), speed converted from mph to km/h, time counted
from the trip's start.

Usage: ``python studies/extract_cmap_trips/extract_cmap_trips.py FASTSIM_GIT_DIR [--nth 1|2|3|4] [--out calib/data/cycles]``;
FASTSIM_GIT_DIR is a clone (or bare repository) of https://github.com/NREL/fastsim. Prints the trips it wrote.
"""
from __future__ import annotations

import argparse
import io
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd

SUBSET = "python/fastsim/resources/cycles/cmap_subset"
BUNDLED_VEHICLE = "4033363_3"  # the commute already bundled; its household's vehicles are excluded
MIN_S, MAX_S, MAX_GAP_S = 300.0, 1800.0, 2.0
MPH_TO_KPH = 1.609344


def _show(repo: Path, path: str) -> str:
    return subprocess.run(["git", "--git-dir", str(repo), "show", f"HEAD:{path}"], check=True,
                          capture_output=True, text=True).stdout


def select(repo: Path, nth: int = 1) -> list[dict]:
    """The ``nth`` qualifying trip (by start time) of every vehicle outside the bundled household that has one."""
    files = subprocess.run(["git", "--git-dir", str(repo), "ls-tree", "-r", "--name-only", "HEAD", SUBSET],
                           check=True, capture_output=True, text=True).stdout.split()
    household = BUNDLED_VEHICLE.split("_")[0]
    chosen = []
    for f in sorted(p for p in files if p.endswith("/trips.csv")):
        veh = f.split("/")[-2]
        if veh.split("_")[0] == household:
            continue
        t = pd.read_csv(io.StringIO(_show(repo, f)))
        dur = 3600.0 * t["absolute_time_duration_hrs"]
        ok = t[(dur >= MIN_S) & (dur <= MAX_S) & (t["max_gap_between_samples_s"] <= MAX_GAP_S)]
        if len(ok) >= nth:
            r = ok.sort_values("start_ts").iloc[nth - 1]
            chosen.append({"vehicle": veh, "start": r["start_ts"], "end": r["end_ts"]})
    return chosen


def cut(repo: Path, trip: dict) -> pd.DataFrame:
    day = trip["start"][:10]
    d = pd.read_csv(io.StringIO(_show(repo, f"{SUBSET}/{trip['vehicle']}/{day}.csv")), parse_dates=["timestamp"])
    a, b = pd.Timestamp(trip["start"]), pd.Timestamp(trip["end"])
    d = d[(d.timestamp >= a) & (d.timestamp <= b)]
    ts = (d.timestamp - a).dt.total_seconds().to_numpy(float)
    if ts.size < 2 or np.diff(ts).max() > MAX_GAP_S:
        raise SystemExit(f"{trip}: samples more than {MAX_GAP_S} s apart")
    t = np.arange(0.0, np.floor(ts[-1]) + 1.0)
    v = np.interp(t, ts, d.speed_mph.to_numpy(float)) * MPH_TO_KPH
    return pd.DataFrame({"time_s": t, "speed_kph": np.round(v, 3)})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("repo", type=Path)
    ap.add_argument("--out", type=Path, default=Path("calib/data/cycles"))
    ap.add_argument("--nth", type=int, default=1, choices=(1, 2, 3, 4), help="which qualifying trip of each vehicle")
    a = ap.parse_args(argv)
    for trip in select(a.repo, a.nth):
        df = cut(a.repo, trip)
        name = f"cmap_{trip['vehicle']}_{trip['start'][:10].replace('-', '')}"
        if a.nth > 1:  # a vehicle's second trip may start on its first one's day
            name += f"_{trip['start'][11:16].replace(':', '')}"
        path = a.out / f"{name}.csv"
        tmp = path.with_suffix(".tmp")
        df.to_csv(tmp, index=False, float_format="%.3f")
        tmp.replace(path)
        v = df.speed_kph.to_numpy()
        print(f"{name}: {trip['start']} to {trip['end'][11:]}, {df.time_s.iloc[-1]:.0f} s, "
              f"{v.sum() / 3600.0:.2f} km, mean {v.mean():.1f} km/h, standstill {100.0 * (v < 0.5).mean():.0f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
