"""What a reader of the HTML report sees: a labelled row per strategy, economy units, channel reports in
reader units, copies of a drive flagged and never used for validation, figures on the fitted logs, the
truth table for SYNTHETIC logs; and `iptm optimize` reusing what `iptm run` solved."""
import json
import re

import pytest

from calib.synth import Scenario, draw_truth, synthesise
from calib.ingest.writers import write_streams
from iptm import pipeline
from iptm.cli import main
from optimize.formulations import DPGrids, DPScenario

GRIDS = DPGrids(soc=0.02, tcl=2.0, tcab=1.0, pbat=1000.0, qheat=100.0)
SCEN = DPScenario(duration_s=120.0)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("logs")
    truth = draw_truth(11)
    truth.save(d / "truth_params.toml")
    logs = []
    for i, (name, cyc, T_cl0) in enumerate([("a_cold", "udds", -10.0), ("c_city", "nycc", 40.0)]):
        sc = Scenario(name, cyc, -10.0, 0.6, T_cl0, -10.0 if T_cl0 < 0 else 10.0, T_bat=0.0)
        _, streams, meta = synthesise(sc, truth, seed=i)
        logs.append(write_streams(streams, meta, d / f"{name}.csv", "csv"))
        if i == 0:  # the same drive again, in another format
            logs.append(write_streams(streams, meta, d / f"{name}.mcap", "mcap"))
    root = tmp_path_factory.mktemp("run")
    cfg = pipeline.RunConfig(logs=logs, scenario=SCEN, grids=GRIDS, reports_dir=root / "reports",
                             cache_dir=root / "cache", progress=False)
    return cfg, pipeline.run(cfg)


def _rows(html, caption_start):
    """The body rows (lists of cell texts) of the first table after the caption that starts so."""
    i = html.index(caption_start)
    table = html[html.index("<table", i):html.index("</table>", i)]
    body = table[table.index("<tbody>"):]
    return [re.findall(r"<td>(.*?)</td>", r, re.S) for r in re.findall(r"<tr>(.*?)</tr>", body, re.S)]


def test_comparison_table_has_a_labelled_row_per_strategy(run):
    _, out = run
    html = (out.report_dir / "index.html").read_text()
    rows = _rows(html, "one row per strategy")
    names = [r[0] for r in rows]
    assert names == ["Rule-based (tuned)", "Baseline-DP on thermal model", "Thermal-DP", "Thermal-Cabin-DP",
                     "Baseline-DP (own optimum, f_cl = 1)"]
    assert "own optimum" in html.split("one row per strategy")[1].split("<h2")[0].split("</table>")[1]
    head = html[html.index("one row per strategy"):]
    head = head[:head.index("</thead>")]
    assert "L/100 km" in head and "mpg" in head and "fuel [g]" in head
    assert "class='tablewrap'" in html
    # the summary gives the same per strategy, in the units engineers read
    summ = _rows(html, "fuel over the scenario, per strategy")
    assert [r[0] for r in summ][:4] == names[:4]
    assert all(re.fullmatch(r"\d+\.\d\d", r[2]) and re.fullmatch(r"\d+\.\d", r[3]) for r in summ)


def test_copies_flagged_and_never_validated(run):
    _, out = run
    rep = json.loads((out.report_dir / "report.json").read_text())
    roles = {lg["name"]: lg["role"] for lg in rep["provenance"]["logs"]}
    assert roles["a_cold.csv"] == "calibration"
    assert roles["a_cold.mcap"].startswith("not used: same drive as")
    assert roles["c_city.csv"].startswith("validation")
    html = (out.report_dir / "index.html").read_text()
    assert "are the same drive" in html and "class='warn'" in html


def test_channel_report_in_reader_units_and_fit_figures(run):
    _, out = run
    html = (out.report_dir / "index.html").read_text()
    chan = html[html.index("channel report: a_cold.csv"):]
    chan = chan[:chan.index("</table>")]
    assert "m/s (km/h)" in chan and "<td>%</td>" in chan and "dimensionless" not in chan
    figs = json.loads((out.report_dir / "report.json").read_text())["figures"]
    assert any(f.startswith("fit_0_a_cold") for f in figs) and any(f.startswith("validation_") for f in figs)
    assert "residuals.png" in figs
    assert "measured vs simulated on a fitted log" in html
    # SYNTHETIC logs with their truth file: estimates next to the truth
    rows = _rows(html, "SYNTHETIC logs: estimates next to the truth")
    assert rows and all(len(r) == 8 for r in rows)


def test_optimize_reuses_the_run_cache(run, capsys):
    cfg, out = run
    capsys.readouterr()
    rc = main(["optimize", "--params", str(out.report_dir / "calibration.toml"), "--duration", "120",
               "--grid", "soc=0.02,tcl=2,tcab=1,pbat=1000,qheat=100", "--formulation", "baseline,thermal",
               "--cache", str(cfg.cache_dir)])
    assert rc == 0
    cap = capsys.readouterr()
    assert "baseline:" in cap.out and cap.out.count("(from the cache)") == 2
    assert "fuel economy, corrected (raw): baseline" in cap.out and "L/100 km" in cap.out and "mpg" in cap.out
    assert "Baseline-DP on thermal model" in cap.err and "from the cache" in cap.err


@pytest.fixture(scope="module")
def rule_baseline_cs():
    """A short case study of rule-based and Baseline-DP only (no strategy that decides the heat)."""
    from calib.model.params import default_parameters
    from optimize.casestudy import run_case_study

    return run_case_study(default_parameters(), DPScenario(duration_s=60.0), strategies=("rule", "baseline"),
                          progress=False, grids=GRIDS)


def test_fuel_chart_labels_every_bar(rule_baseline_cs, tmp_path, monkeypatch):
    """The fuel chart draws savings against rule-based (differences of a few % stay visible) and writes a
    value on every bar; its legend sits outside the axes."""
    import calib.fileio as fio

    cs = rule_baseline_cs
    figs = {}
    real = fio.save_figure
    monkeypatch.setattr(fio, "save_figure", lambda fig, path, **kw: (figs.__setitem__(path.stem, fig),
                                                                       real(fig, path, **kw)))
    cs.plot(tmp_path)
    ax = figs["fuel_bars"].axes[0]
    bars = list(ax.patches)
    texts = [t.get_text() for t in ax.texts]
    assert len(bars) == 2 * len(cs.table().query("key != 'baseline_warm'")) == len(texts)
    assert sum("(reference)" in t for t in texts) == 2 and all(" g" in t for t in texts)
    assert "saving vs Rule-based (tuned) [%]" == ax.get_xlabel()
    leg = ax.get_legend()
    assert leg is not None and leg.get_bbox_to_anchor().y0 < ax.bbox.y0  # below the axes, covering no bar
    # corrected fuel is the headline: the solid bar above each pair, first in the legend; raw is lighter
    n = len(bars) // 2
    corrected, raw = bars[:n], bars[n:]
    assert all(b.get_alpha() in (None, 1.0) for b in corrected) and all(b.get_alpha() < 0.5 for b in raw)
    assert all(c.get_y() > r.get_y() for c, r in zip(corrected, raw))
    names = [t.get_text() for t in leg.get_texts()]
    assert names[0].startswith("corrected fuel") and any(t.startswith("raw fuel") for t in names)
    assert sum(t.startswith("corrected") for t in texts) == sum(t.startswith("raw") for t in texts) == n


def test_paper_figures_are_labelled_raw_with_a_free_terminal_state(rule_baseline_cs):
    from iptm.report import comparison_table
    from optimize.labels import PAPER_CONDITION

    head = list(comparison_table(rule_baseline_cs.table().reset_index()).columns)
    assert head[1:4] == ["corrected fuel [g]", "corrected L/100 km", "corrected mpg"]
    assert head[4:7] == ["raw fuel [g]", "raw L/100 km", "raw mpg"]
    assert any("paper" in h and PAPER_CONDITION in h for h in head)
    assert "raw" in PAPER_CONDITION and "free" in PAPER_CONDITION


def test_corrected_economy_is_the_corrected_fuel_over_the_distance(rule_baseline_cs):
    from calib import economy

    for key, sim in rule_baseline_cs.sims.items():
        s = sim.summary()
        row = rule_baseline_cs.table().set_index("key").loc[key]
        assert row["L_per_100km_corrected"] == pytest.approx(economy.l_per_100km(s["fuel_corrected_g"],
                                                                                 s["distance_km"]), rel=1e-12)
        assert row["mpg_corrected"] == pytest.approx(economy.mpg(s["fuel_corrected_g"], s["distance_km"]), rel=1e-12)
        assert row["L_per_100km"] == pytest.approx(s["L_per_100km"], rel=1e-12)
    txt = rule_baseline_cs.format_table()
    head = txt.splitlines()[1]
    assert head.index("corr g") < head.index("raw g") and "corr L/100" in head


def test_one_count_and_the_priors_banner_in_the_report(run):
    from calib.model.params import ParameterSet
    from iptm.present import counts_text, parameter_counts, prior_banner

    _, out = run
    rep = json.loads((out.report_dir / "report.json").read_text())
    counts = parameter_counts(ParameterSet.load(out.report_dir / "calibration.toml"))
    assert rep["summary"]["n_estimated"] == counts["estimated"] and rep["summary"]["n_weak"] == counts["weak"]
    html = (out.report_dir / "index.html").read_text()
    assert counts_text(counts) in html
    assert rep["summary"]["at_prior"] == prior_banner(rep["calibration"])
    for w in rep["summary"]["at_prior"]:
        assert f"Not fitted: {w}" in html


def test_case_study_draws_no_empty_cabin_figures(rule_baseline_cs, tmp_path):
    """Without Thermal-DP or Thermal-Cabin-DP no strategy decides the heat: the cabin and heater figures are
    not drawn (an empty axes with a legend of nothing), and the others are."""
    import warnings
    from pathlib import Path

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # matplotlib warns when a legend has no labelled artist
        names = {Path(p).stem for p in rule_baseline_cs.plot(tmp_path)}
    assert "cabin" not in names and "heater_power" not in names
    assert {"soc", "coolant", "fuel_bars"} <= names
