"""The drives the causal controllers are chosen on and tested on, the rule that chooses the SDP's settings, and
the study that cut the CMAP test trips out of FASTSim's CMAP subset."""
import importlib.util
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from calib.model.cycles import load_cycle
from calib.errors import IptmError
from optimize.causal.compare import (CMAP_TRIP1, CMAP_TRIP2, CMAP_TRIP3, DRIVE_SETS, TEST_CYCLES, TRAIN_CYCLES,
                                     WLTC_HIGH_CMAP_TRIP4, compare_causal)

ROOT = Path(__file__).resolve().parents[1]


def _script(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "studies" / name / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_training_and_test_drive_sets_are_disjoint_and_bundled():
    assert not set(TRAIN_CYCLES) & set(TEST_CYCLES)
    assert not set(CMAP_TRIP1) & (set(TRAIN_CYCLES) | set(TEST_CYCLES))
    assert not set(CMAP_TRIP2) & (set(TRAIN_CYCLES) | set(TEST_CYCLES) | set(CMAP_TRIP1))
    assert not set(CMAP_TRIP3) & (set(TRAIN_CYCLES) | set(TEST_CYCLES) | set(CMAP_TRIP1) | set(CMAP_TRIP2))
    assert not set(WLTC_HIGH_CMAP_TRIP4) & (set(TRAIN_CYCLES) | set(TEST_CYCLES) | set(CMAP_TRIP1) | set(CMAP_TRIP2)
                                   | set(CMAP_TRIP3))
    assert DRIVE_SETS == {"test-cycles": TEST_CYCLES, "cmap-trip1": CMAP_TRIP1, "cmap-trip2": CMAP_TRIP2,
                          "cmap-trip3": CMAP_TRIP3, "wltc-high-cmap-trip4": WLTC_HIGH_CMAP_TRIP4}
    from iptm.commands.bench import DRIVE_SET_NAMES

    assert DRIVE_SET_NAMES == tuple(DRIVE_SETS)  # the CLI's choices
    # each second trip is a later trip of a car of the first-trip set, each third trip later than its car's second
    first = {n.split("_")[1] + "_" + n.split("_")[2]: (n.split("_")[3], "") for n in CMAP_TRIP1}
    second = {n.split("_")[1] + "_" + n.split("_")[2]: tuple(n.split("_")[3:]) for n in CMAP_TRIP2}
    for later, earlier in ((CMAP_TRIP2, first), (CMAP_TRIP3, second)):
        for n in later:
            _, veh, no, day, hhmm = n.split("_")
            assert (day, hhmm) > earlier[f"{veh}_{no}"] and len(hhmm) == 4, n
    cmap = [n for n in WLTC_HIGH_CMAP_TRIP4 if n.startswith("cmap_")]
    assert cmap == ["cmap_4108468_1_20070625_1220"] and cmap[0] > CMAP_TRIP3[0]  # the fourth trip of that car
    for name in CMAP_TRIP1 + CMAP_TRIP2 + CMAP_TRIP3 + WLTC_HIGH_CMAP_TRIP4:
        c = load_cycle(name)
        if name.startswith("cmap_"):
            assert 300.0 <= c.t[-1] <= 1800.0, name  # the rule's 5-30 min
        assert c.v[0] == 0.0 and c.v[-1] == 0.0, name  # a trip starts and ends at rest
        assert np.all(np.diff(c.t) == 1.0)


def _row(gap, dsocs):
    return {"mean_gap_pct": gap, "max_abs_dsoc": max(abs(d) for d in dsocs)}


def test_selection_keeps_a_margin_inside_the_charge_band():
    sel = _script("causal_select")
    assert sel.SOC_TOL - sel.MARGIN == pytest.approx(0.0075)
    edge = _row(2.4, [0.009, 0.004])  # inside the band, but fills it: cheapest on corrected fuel
    inside = _row(2.8, [0.0054, -0.005])
    at_limit = _row(2.9, [0.0075, 0.0])
    out = _row(1.0, [0.012])
    assert sel.choose([edge, out, inside, at_limit]) is inside
    assert sel.choose([edge, out, at_limit]) is at_limit  # the limit itself is inside
    assert sel.choose([edge, out]) is None


def test_selection_rechooses_from_a_stored_report(tmp_path, capsys):
    import json

    sel = _script("causal_select")
    rows = [dict(_row(2.4, [0.009]), alpha=1.0, w_soc_g_per_s=100.0, soc_bias=0.01, regen="fit", regen_fraction=0.8,
                 regen_slope_per_mps=-0.012),
            dict(_row(2.8, [0.005]), alpha=0.1, w_soc_g_per_s=100.0, soc_bias=0.01, regen="fit", regen_fraction=0.8,
                 regen_slope_per_mps=-0.012)]
    src = tmp_path / "old.json"
    src.write_text(json.dumps({"rows": rows}))
    assert sel.main(["--rechoose", str(src), "--out", str(tmp_path / "new.json")]) == 0
    new = json.loads((tmp_path / "new.json").read_text())
    assert new["chosen"]["alpha"] == 0.1 and "0.0075" in new["rule"]
    assert "chosen: alpha 0.1" in capsys.readouterr().out
    # two reports judged together (a grid extended after the first chose nothing)
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps({"grid": {"alpha": [0.1]}, "drives": ["udds"], "rows": rows[:1]}))
    b.write_text(json.dumps({"grid": {"alpha": [1.0, 0.1]}, "drives": ["udds"], "rows": rows[1:]}))
    assert sel.main(["--rechoose", str(a), str(b), "--out", str(tmp_path / "ab.json")]) == 0
    ab = json.loads((tmp_path / "ab.json").read_text())
    assert ab["grid"] == {"alpha": [0.1, 1.0]} and ab["drives"] == ["udds"] and ab["chosen"]["alpha"] == 0.1
    assert sel.main(["--rechoose", str(a), "--out", str(tmp_path / "a2.json")]) == 0
    assert json.loads((tmp_path / "a2.json").read_text())["chosen"] is None  # 0.009 is outside the margin


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_cmap_trips_are_cut_by_the_fixed_rule(tmp_path):
    """A miniature of FASTSim's layout: the rule skips the bundled commute's household, trips outside 5-30 min
    and trips with a gap over 2 s, keeps each vehicle's first qualifying trip and resamples it to 1 Hz in km/h."""
    ex = _script("extract_cmap_trips")
    work = tmp_path / "w"
    sub = work / ex.SUBSET
    head = ("sampno,vehno,start_ts,end_ts,absolute_time_duration_hrs,max_gap_between_samples_s\n")

    def vehicle(veh, trips, day, samples):
        d = sub / veh
        d.mkdir(parents=True)
        (d / "trips.csv").write_text(head + "".join(f"1,1,{a},{b},{h},{g}\n" for a, b, h, g in trips))
        (d / f"{day}.csv").write_text("timestamp,cycle_sec,timestep,speed_mph,accel_meters_ps\n"
                                      + "".join(f"{t},0,1,{v},0\n" for t, v in samples))

    def stamp(s):
        return f"2007-05-01 10:{s // 60:02d}:{s % 60:02d}"

    ramp = [(stamp(s), 10.0 if 0 < s < 400 else 0.0) for s in range(0, 401, 2)]  # 2-s samples, 400 s
    vehicle("4033363_1", [(stamp(0), stamp(400), 400 / 3600, 1.0)], "2007-05-01", ramp)  # the commute's household
    vehicle("4100000_1", [(stamp(0), stamp(100), 100 / 3600, 1.0),  # too short
                          (stamp(0), stamp(400), 400 / 3600, 5.0),  # a 5-s gap
                          (stamp(2), stamp(400), 398 / 3600, 2.0),  # the second qualifying trip (by start)
                          (stamp(0), stamp(400), 400 / 3600, 2.0)], "2007-05-01", ramp)
    vehicle("4200000_2", [(stamp(0), stamp(400), 400 / 3600, 3.0)], "2007-05-01", ramp)
    subprocess.run(["git", "init", "-q", str(work)], check=True)
    subprocess.run(["git", "-C", str(work), "add", "."], check=True)
    subprocess.run(["git", "-C", str(work), "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "x"],
                   check=True)
    trips = ex.select(work / ".git")
    assert trips == [{"vehicle": "4100000_1", "start": stamp(0), "end": stamp(400)}]
    assert ex.select(work / ".git", nth=2) == [{"vehicle": "4100000_1", "start": stamp(2), "end": stamp(400)}]
    assert ex.select(work / ".git", nth=3) == []
    df = ex.cut(work / ".git", trips[0])
    assert df.time_s.tolist() == list(np.arange(401.0))
    assert df.speed_kph.iloc[0] == 0.0 and df.speed_kph.iloc[-1] == 0.0
    assert df.speed_kph.iloc[200] == pytest.approx(16.093)  # 10 mph
    assert df.speed_kph.iloc[1] == pytest.approx(8.047)  # half-way between 0 and 10 mph, a 2-s gap


def test_goals_count_the_runs_that_meet_each_goal():
    from optimize.causal.compare import CausalComparison

    def r(strategy, gap, vs_rule, dsoc, vs_train=1.0):
        return {"cycle": "x", "T_amb": 0.0, "strategy": strategy, "fuel_g": 1.0, "fuel_corrected_g": 1.0,
                "credit_g": 0.0, "soc_final": 0.6 + dsoc, "T_cl_final": 80.0, "gap_to_dp_pct": gap,
                "vs_rule_pct": vs_rule, "vs_rule_train_pct": vs_train, "dsoc": dsoc}

    rows = [r("dp_thermal", 0.0, 1.0, 0.0), r("sdp", 3.0, 0.5, 0.01), r("sdp", 3.01, 0.0, -0.0101, 0.0),
            r("ecms", 1.0, 2.0, 0.001), r("ecms", -1.0, 0.1, -0.002, -0.5), r("rule_tuned", 1.0, 0.0, 0.0),
            r("sdp_own", 4.0, -1.0, -0.02), r("rule_train", 5.0, -2.0, 0.003, 0.0)]
    cmp = CausalComparison(rows, markov=None, validation=[])
    g = cmp.goals()
    # the DP and the rule tuned on the drive are references, not judged; the rule tuned on the training
    # cycles does not know the drive, so it is judged as the causal controllers are
    assert set(g) == {"sdp", "ecms", "sdp_own", "rule_train"}
    assert (g["sdp"]["better_than_rule_train"], g["ecms"]["better_than_rule_train"]) == (1, 1)
    assert (g["rule_train"]["within_3pct"], g["rule_train"]["better_than_rule"]) == (0, 0)
    assert (g["sdp_own"]["within_3pct"], g["sdp_own"]["charge_sustaining"]) == (0, 0)
    assert (g["sdp"]["runs"], g["sdp"]["within_3pct"], g["sdp"]["better_than_rule"], g["sdp"]["charge_sustaining"]) \
        == (2, 1, 1, 1)  # 3 % and 0.01 themselves meet the goal; a saving of 0 % does not
    assert not (g["sdp"]["within_3pct_all"] or g["sdp"]["better_than_rule_all"] or g["sdp"]["charge_sustaining_all"])
    assert g["ecms"]["within_3pct_all"] and g["ecms"]["better_than_rule_all"] and g["ecms"]["charge_sustaining_all"]
    assert g["sdp"]["dsoc_range"] == (-0.0101, 0.01) and g["sdp"]["max_gap_to_dp_pct"] == 3.01
    txt = cmp.format()
    assert "sdp: within 3 % of DP on 1/2 runs" in txt and "better than tuned rule-based on 2/2 (met)" in txt
    assert "than the rule tuned on the training cycles on 1/2" in txt


def test_a_drive_the_chain_learns_from_cannot_also_test_it():
    with pytest.raises(IptmError, match="held-out drives must not be training drives"):
        compare_causal(None, held_out=CMAP_TRIP2[:1], learn_from=CMAP_TRIP2[:2], progress=False)


def test_own_chain_takes_the_chosen_settings():
    """``sdp_own``'s chain and settings: the selection report's alpha goes to the chain, the rest to SDPConfig."""
    from dataclasses import replace

    from calib.model.params import default_parameters
    from optimize.causal.compare import own_chain
    from optimize.causal.markov import DEFAULT_ALPHA
    from optimize.causal.sdp import SDPConfig

    ps = default_parameters()
    chosen = {"alpha": 3, "w_soc_g_per_s": 400, "soc_bias": 0.01, "regen_fraction": 0.5, "regen_slope_per_mps": 0.0,
              "mean_gap_pct": 3.23}
    mk, cfg = own_chain(ps, ["nycc"], chosen)
    assert mk.alpha == 3.0 and cfg == {"w_soc_g_per_s": 400.0, "soc_bias": 0.01, "regen_fraction": 0.5,
                                       "regen_slope_per_mps": 0.0}
    c = replace(SDPConfig(), **cfg)
    assert (c.w_soc_g_per_s, c.regen_fraction) == (400.0, 0.5)
    mk0, cfg0 = own_chain(ps, ["nycc"])
    assert mk0.alpha == DEFAULT_ALPHA and cfg0 == {}
    # the prior changes the chain: a rarely seen transition is likelier with the larger alpha
    assert mk.P.min() > mk0.P.min()


def test_own_settings_must_be_a_chosen_selection(tmp_path, capsys):
    import json

    from iptm.cli import main

    none = tmp_path / "none.json"
    none.write_text(json.dumps({"rows": [], "chosen": None}))
    cases = [(["--learn-from", "cmap-trip1", "--own-settings", str(none)], "no chosen setting"),
             (["--learn-from", "cmap-trip1", "--own-settings", str(tmp_path / "missing.json")], "cannot read it"),
             (["--own-settings", str(none)], "needs --learn-from"),
             (["--learn-from", "nope"], "choose among test-cycles, cmap-trip1, cmap-trip2, cmap-trip3")]
    for extra, why in cases:
        assert main(["bench", "causal", "--drives", "cmap-trip3"] + extra) == 2, extra
        assert why in capsys.readouterr().err, extra
