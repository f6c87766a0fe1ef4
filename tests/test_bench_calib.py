"""``iptm bench calib``: the drive-selection rule, its table rendered from the JSON into the docs page, the
per-case timing table and its flag, and the section's command-line errors."""
import json
from itertools import combinations

import pytest

from calib.errors import IptmError
from iptm.benchmarks import calib as bench


def _figures():
    drives = [{"n": i, "key": f"d{i}", "name": f"d{i}", "cycle": "udds", "T_amb": -7.0, "T_eng0": -7.0,
               "minutes": 30.0} for i in (1, 2, 3)]
    rows = [{"selection": "1", "calibration": [1], "held_out": {"2": {"fuel_pct": 1.234, "soc_rmse": 0.0041},
                                                                "3": {"fuel_pct": -6.5, "soc_rmse": 0.0123}},
             "misses": ["3 fuel -6.5 %"], "meets": False, "s_per_hour": 3.21},
            {"selection": "2", "calibration": [2], "held_out": {"1": {"fuel_pct": 0.5, "soc_rmse": 0.001},
                                                                "3": {"refused": "no SOC"}},
             "misses": ["3 not validated"], "meets": False, "s_per_hour": 2.0}]
    return {"drives": drives, "selections": rows, "meet": 0,
            "targets": {"fastsim_fuel_pct": 5.0, "fastsim_soc_rmse": 0.02, "s_per_hour": 10.0},
            "load_average": 3.0, "cpus": 2}


def test_selection_rule_is_every_pair_of_six_drives_at_two_ambients_cold_and_warm():
    pool = bench.selection_pool()
    assert len(pool) == 6 and len({k for k, _ in pool}) == 6
    scs = [sc for _, sc in pool]
    assert {sc.T_amb for sc in scs} == {-7.0, 22.0}
    assert any(sc.T_eng0 == sc.T_amb for sc in scs) and any(sc.T_eng0 > sc.T_amb + 40 for sc in scs)
    cycles = "+".join(sc.cycle for sc in scs)
    for c in ("udds", "hwfet", "us06", "wltc"):
        assert c in cycles, c
    assert len(list(combinations(range(6), bench.SELECTION_CAL))) == 15


def test_table_shows_every_held_out_figure_and_names_the_misses():
    t = bench.selections_table(_figures())
    lines = t.splitlines()
    assert lines[0].count("held out") == 3
    row1 = next(ln for ln in lines if ln.startswith("| 1 |"))
    assert "(calibration)" in row1 and "+1.2 %, 0.0041" in row1 and "-6.5 %, 0.0123" in row1
    assert "misses: 3 fuel -6.5 %" in row1 and "3.2" in row1
    row2 = next(ln for ln in lines if ln.startswith("| 2 |"))
    assert "not validated" in row2
    assert "0 of 2 selections meet" in t


def test_render_doc_rewrites_only_its_block(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("intro\n<!-- figures:calib-selections -->\nold\n<!-- /figures:calib-selections -->\nend\n")
    bench.render_doc(page, _figures())
    text = page.read_text()
    assert text.startswith("intro\n") and text.endswith("end\n") and "old" not in text
    assert "+1.2 %, 0.0041" in text
    page.write_text("no block here\n")
    with pytest.raises(IptmError, match="calib-selections"):
        bench.render_doc(page, _figures())


def test_render_only_reads_the_bench_json(tmp_path, capsys):
    js, page = tmp_path / "b.json", tmp_path / "p.md"
    js.write_text(json.dumps({"calib": {"selections": _figures()}}))
    page.write_text("<!-- figures:calib-selections -->x<!-- /figures:calib-selections -->")
    assert bench.main(["--render-only", "--json", str(js), "--docs", str(page)]) == 0
    assert "-6.5 %" in page.read_text()
    assert bench.main(["--render-only", "--docs", str(page)]) == 2
    assert "needs --json" in capsys.readouterr().out
    js.write_text("{}")
    assert bench.main(["--render-only", "--json", str(js), "--docs", str(page)]) == 2
    assert "cannot read selection figures" in capsys.readouterr().out
    assert bench.main([]) == 2


def test_case_table_flags_a_case_over_the_target(capsys):
    bench.CASES.clear()
    bench.CASES.extend([{"case": "fast", "hours": 1.0, "wall_s": 2.0, "s_per_hour": 2.0, "steps_s": {"fuel": 1.0}},
                        {"case": "slow", "hours": 0.5, "wall_s": 6.0, "s_per_hour": 12.0,
                         "steps_s": {"thermal": 5.0, "fuel": 0.5}}])
    try:
        out = bench.cases_summary()
    finally:
        bench.CASES.clear()
    text = capsys.readouterr().out
    assert out["over_target"] == ["slow"] and out["max_s_per_hour"] == 12.0
    slow = next(ln for ln in text.splitlines() if ln.strip().startswith("slow"))
    assert "thermal 5.00 s" in slow and "OVER TARGET" in slow
    assert "MISSES" in text


def test_timed_calibrate_records_the_steps():
    from pathlib import Path

    from calib.ingest import read_log

    log = read_log(Path(__file__).parent / "data" / "fastsim" / "SYNTHETIC_fastsim_sonata_cold_udds_300s.csv")
    bench.CASES.clear()
    try:
        res = bench.timed_calibrate("sample", [log], diagnose=False)
        case = bench.CASES[-1]
    finally:
        bench.CASES.clear()
    assert case["case"] == "sample" and case["hours"] == pytest.approx(log.duration_s / 3600)
    assert set(case["steps_s"]) == {"battery", "fuel", "thermal", "cabin"} == set(res.timings)
    assert case["s_per_hour"] == pytest.approx(case["wall_s"] / case["hours"])
