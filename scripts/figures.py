"""Figures in the README and the docs that cannot drift: the blocks between ``<!-- figures:NAME -->`` and
``<!-- /figures:NAME -->`` in the files of ``FILES`` are rendered from the benchmarks' JSON (``iptm bench SUITE
--json``, committed under reports/figures/), from the main job's summary (``iptm run --json
reports/figures/run.json``), from the mutation report reports/mutation.json (written by scripts/mutation.py,
which ``run`` does not re-run: it takes hours), from the causal comparisons' reports/causal-SET-VALUATION.json
(``iptm bench causal``; not re-run either) and from the FASTSim drive selections'
reports/figures/calib-selections.json (``python -m iptm.benchmarks.calib --selections``; not re-run).

    python scripts/figures.py run      # re-run the benchmarks and the main job, write their JSON, rewrite the blocks
    python scripts/figures.py render   # rewrite the blocks from the committed JSON (nothing re-run)
    python scripts/figures.py check    # exit 1 when a block differs from what the JSON renders

Deterministic figures (the EPA table, the main job's table) are printed to the page's precision and must
match exactly; a timing is quoted as the median and the range of its repetitions with the machine's load at
the time, so the page says how noisy it is. ``check`` never re-runs anything (it is part of the test suite).
A block belongs to one file: moving it to another page means moving its renderer in ``FILES`` too.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
JSON_DIR = ROOT / "reports" / "figures"
#: ``iptm run --json reports/figures/run.json`` on the bundled logs (``run`` re-runs it: minutes)
RUN_JSON = JSON_DIR / "run.json"
#: ``python -m iptm.benchmarks.calib --selections --json reports/figures/calib-selections.json`` (not re-run)
SELECTIONS_JSON = JSON_DIR / "calib-selections.json"
SUITES = ("sim", "epa")
MUTATION_JSON = ROOT / "reports" / "mutation.json"
#: The 10,000-input runs of every fuzz generator and mutated reader (``python -m iptm.benchmarks.fuzz --n 10000
#: ...``: hours on 2 cores, so ``run`` does not re-run them; each run names its commit and command)
FUZZ_JSON = JSON_DIR / "fuzz-10k.json"
#: ``iptm bench causal --drives SET --valuation V --json reports/causal-SET-V.json`` (each run takes minutes:
#: ``run`` does not re-run them)
CAUSAL_SETS = ("test-cycles", "cmap-trip1", "cmap-trip2", "cmap-trip3", "wltc-high-cmap-trip4")
CAUSAL_VALUATIONS = ("corrected", "continuation")


def causal_json(drives: str, valuation: str) -> Path:
    return ROOT / "reports" / f"causal-{drives}-{valuation}.json"


def hindsight_json(valuation: str) -> Path:
    """``python studies/ecms_hindsight/ecms_hindsight.py --valuation V --out reports/ecms-hindsight-V.json`` (not re-run)."""
    return ROOT / "reports" / f"ecms-hindsight-{valuation}.json"


def bench_json(suite: str) -> Path:
    return JSON_DIR / f"bench-{suite}.json"


# --------------------------------------------------------------------------------------------------- renderers
def _epa(d: dict) -> str:
    rows = ["| cycle | EPA mpg | model mpg | model mpg, SOC-corrected | final SOC | error |",
            "|---|---|---|---|---|---|"]
    for r in d["sim"]["epa"]:
        rows.append(f"| {r['cycle']} | {r['epa_mpg']:.1f} | {r['model_mpg']:.1f} | "
                    f"{r['model_mpg_soc_corrected']:.1f} | {r['soc_final']:.3f} | {r['error_pct']:+.1f} % |")
    return "\n".join(rows)


def _sim_speed(d: dict) -> str:
    s, m = d["sim"], d.get("machine", {})
    ms = [t * 1e3 for t in s.get("sim_artemis_times_s", [s["sim_artemis_best_s"], s["sim_artemis_median_s"]])]
    load = f", load average {m['load_1min']:.1f} on {m['cpus']} cores" if m else ""
    return (f"the {s['steps']}-s ARTEMIS Urban cycle under the rule-based controller takes a median "
            f"{s['sim_artemis_median_s'] * 1e3:.0f} ms after compilation (range {min(ms):.0f}-{max(ms):.0f} ms over "
            f"{len(ms)} runs{load})")


def _mutation(d: dict) -> str:
    m = d["mutation"]
    what = (f"a seeded sample of at most {m['sample']} mutants per module (seed {m['seed']})" if m.get("sample")
            else "every mutant of the configured modules")
    return (f"score {100 * m['score']:.1f} %: {m['killed']} killed, {m['survived']} survived, {m['equivalent']} "
            f"equivalent (excluded, each with its reason in `pyproject.toml`) of {m['run']} mutants, {what}")


def _fuzz10k(d: dict) -> str:
    """Every reader and generated file kind at 10,000 inputs: the outcomes, memory and the slowest case."""
    rows = ["| reader / file kind | inputs | read | recovered | clean error | unclear | escape | hang | printed | "
            "peak MB | rise MB | slowest s | run |", "|---|" + "---:|" * 11 + "---|"]
    for i, run in enumerate(d["fuzz10k"]["runs"]):
        for kind, t in run["kinds"].items():
            rows.append(f"| {kind} | {t['n']} | {t['read']} | {t['recovered']} | {t['error']} | {t['unclear']} | "
                        f"{t['escape']} | {t['hang']} | {t['printed']} | {t['peak_mb']:.0f} | {t['added_mb']:.0f} | "
                        f"{t['slowest_s']:.2f} | {i + 1} |")
    rows.append("")
    for i, run in enumerate(d["fuzz10k"]["runs"]):
        rows.append(f"{i + 1}. `{run['command']}` at {run['commit']}, load average {run['load']:.1f} at the start")
    missing = d["fuzz10k"].get("not_run_at_10000") or []
    if missing:
        rows += ["", "Not run at 10,000 inputs: " + ", ".join(missing) + "."]
    return "\n".join(rows)


#: the command that writes reports/figures/plan-bench.json and the block (not re-run by ``run``: minutes)
PLAN_COMMAND = "python -m iptm.benchmarks.plan --json reports/figures/plan-bench.json --doc docs/drive_plans.md"


def _plan_bench(d: dict) -> str:
    """The drive plans' closed loop on the foreign cars, as ``python -m iptm.benchmarks.plan`` prints it."""
    from iptm.benchmarks.plan import table

    return "```text\n" + f"$ {PLAN_COMMAND}\n" + "\n\n".join(table(f) for f in d["plan_bench"]) + "\n```"


def _causal(d: dict) -> str:
    rows = ["| drives | valuation | controller | within 3 % of Thermal-DP | better than the rule tuned on the drive | "
            "better than the rule tuned on the training cycles | ends within 0.01 of SOC_0 | largest gap to DP | "
            "final SOC - SOC_0 |", "|---|---|---|---|---|---|---|---|---|"]
    for (drives, valuation), c in d["causal"].items():
        for s in ("sdp", "ecms", "sdp_own", "rule_train"):
            g = c["goals"].get(s)
            if g is None:
                continue
            name = {"sdp": "SDP", "ecms": "ECMS", "rule_train": "rule tuned on the training cycles"}.get(s) or (
                f"SDP, chain also learnt {len(c['learn_from'])} earlier trips"
                + (", settings chosen again" if c.get("own_settings") else ""))
            n = g["runs"]
            bt = "(itself)" if s == "rule_train" else (f"{g['better_than_rule_train']}/{n}" if "better_than_rule_train" in g
                                               else "not run")
            rows.append(f"| {drives} | {valuation} | {name} | {g['within_3pct']}/{n} | {g['better_than_rule']}/{n} | "
                        f"{bt} | {g['charge_sustaining']}/{n} | {g['max_gap_to_dp_pct']:+.2f} % | "
                        f"{g['dsoc_range'][0]:+.4f} to {g['dsoc_range'][1]:+.4f} |")
    return "\n".join(rows)


def _causal_rule_train(d: dict) -> str:
    """Per drive, the rule tuned on the training cycles against Thermal-DP and the rule tuned on the drive,
    and the causal controllers' savings against it (docs/studies/causal_controllers.md, per drive)."""
    out = []
    for valuation in CAUSAL_VALUATIONS:
        out += ["", f"{valuation.capitalize()} valuation:", "",
                "| drives | drive | ambient | Thermal-DP g | rule tuned on the drive g | rule tuned on the training "
                "cycles g (gap to DP, vs the drive's rule) | its SOC_N | SDP vs it | ECMS vs it |",
                "|---|---|---|---|---|---|---|---|---|"]
        for (drives, v), c in d["causal"].items():
            if v != valuation:
                continue
            rows = c.get("table") or []
            by = {(r["cycle"], r["T_amb"], r["strategy"]): r for r in rows}
            for (cyc, T, strat), r in by.items():
                if strat != "rule_train":
                    continue
                dp, rule = by[(cyc, T, "dp_thermal")], by[(cyc, T, "rule_tuned")]
                sdp, ecms = by.get((cyc, T, "sdp")), by.get((cyc, T, "ecms"))
                out.append(f"| {drives} | {cyc} | {T:g} | {dp['fuel_corrected_g']:.2f} | {rule['fuel_corrected_g']:.2f} | "
                           f"{r['fuel_corrected_g']:.2f} ({r['gap_to_dp_pct']:+.2f} %, {r['vs_rule_pct']:+.2f} %) | "
                           f"{r['soc_final']:.4f} | {sdp['vs_rule_train_pct']:+.2f} % | {ecms['vs_rule_train_pct']:+.2f} % |")
    return "\n".join(out[1:])


def _causal_per_drive(d: dict, drives: str = "wltc-high-cmap-trip4") -> str:
    """Per drive of one set, both valuations: Thermal-DP, the rule tuned on the drive, the SDP and the ECMS
    (docs/studies/causal_controllers.md, per drive)."""
    out = []
    for valuation in CAUSAL_VALUATIONS:
        c = d.get("causal", {}).get((drives, valuation))
        if c is None:
            continue
        cont = valuation == "continuation"
        out += ["", f"{valuation.capitalize()} valuation (`reports/causal-{drives}-{valuation}.json`):", "",
                "| drive | ambient | Thermal-DP g" + (" (credit; SOC_N)" if cont else "") + " | tuned rule g | "
                "SDP g (gap to DP, vs rule) | SDP SOC_N | ECMS g (gap to DP, vs rule) | ECMS SOC_N |",
                "|---|---|---|---|---|---|---|---|"]
        by = {(r["cycle"], r["T_amb"], r["strategy"]): r for r in c["table"]}
        for (cyc, T, strat), dp in by.items():
            if strat != "dp_thermal":
                continue
            rule, sdp, ecms = by[(cyc, T, "rule_tuned")], by[(cyc, T, "sdp")], by[(cyc, T, "ecms")]
            dp_cell = f"{dp['fuel_corrected_g']:.2f}" + (f" ({dp['credit_g']:+.2f}; {dp['soc_final']:.3f})" if cont else "")
            out.append(f"| {cyc} | {T:g} | {dp_cell} | {rule['fuel_corrected_g']:.2f} | "
                       + " | ".join(f"{r['fuel_corrected_g']:.2f} ({r['gap_to_dp_pct']:+.2f} %, {r['vs_rule_pct']:+.2f} %) | "
                                    f"{r['soc_final']:.4f}" for r in (sdp, ecms)) + " |")
    return "\n".join(out[1:])


def _ecms_hindsight(d: dict) -> str:
    """Per valuation, the causal ECMS against the ECMS tuned on each drive (studies/ecms_hindsight/ecms_hindsight.py)."""
    from optimize.causal.hindsight import summarize

    rows = ["| valuation | runs | within 3 % of Thermal-DP: causal ECMS | ECMS tuned on the drive | constant co-states "
            "tuned on the drive | rule tuned on the drive | better than the rule tuned on the drive: causal ECMS | "
            "ECMS tuned on the drive | constant co-states tuned on the drive | largest gap to DP: causal, tuned, "
            "constant |", "|---|---|---|---|---|---|---|---|---|---|"]
    for v, h in d.get("ecms_hindsight", {}).items():
        s = summarize(h["runs"])
        n = s["runs"]
        cells = [f"{s[f'{k}_within']}/{n}" for k in ("causal", "adaptive", "constant", "rule")]
        cells += [f"{s[f'{k}_better_than_rule']}/{n}" for k in ("causal", "adaptive", "constant")]
        worst = ", ".join(f"{s[f'{k}_max_gap_pct']:+.2f} %" for k in ("causal", "adaptive", "constant"))
        rows.append(f"| {v} | {n} | " + " | ".join(cells) + f" | {worst} |")
    return "\n".join(rows)


def _headline(d: dict) -> str:
    """The main job's comparison, corrected fuel first (the fair figure), raw fuel beside it."""
    from optimize.labels import LABELS

    r = d["run"]

    def pct(v):
        return "-" if v is None or v != v else f"{v:.2f} %"

    rows = ["| strategy | corrected fuel g | saving vs rule-based, corrected | L/100 km, corrected | fuel g (raw) | "
            "saving vs rule-based, raw | L/100 km, raw | SOC_N | final coolant degC |", "|---|---|---|---|---|---|---|---|---|"]
    for key, v in r["strategies"].items():
        if key == "baseline_warm":  # its own model's optimum, not a row of the comparison
            continue
        ref = key == "rule"  # the reference: no saving against itself
        rows.append(f"| {LABELS.get(key, key)} | **{v['fuel_corrected_g']:.2f}** | "
                    f"{'-' if ref else '**' + pct(v['saving_vs_rule_pct']) + '**'} | {v['L_per_100km_corrected']:.2f} | "
                    f"{v['fuel_g']:.2f} | {'-' if ref else pct(v['raw_saving_vs_rule_pct'])} | {v['L_per_100km']:.2f} | "
                    f"{v['soc_final']:.3f} | "
                    f"{v['T_cl_final_degC']:.1f} |")
    rows += ["", f"Calibration: {r['n_estimated']} parameters estimated, {r['n_weak']} weakly informed. "
                 f"Terminal condition `{r['terminal']}`. Printed by the run: \"{r['ordering']}\"."]
    return "\n".join(rows)


def _calib_selections(d: dict) -> str:
    """The FASTSim drive selections (``python -m iptm.benchmarks.calib --selections --json
    reports/figures/calib-selections.json``; ``run`` does not re-run them), rendered by the benchmark's own table."""
    from iptm.benchmarks.calib import selections_table

    return selections_table(d["calib_selections"])


def _epa_bags(d: dict) -> str:
    """Every EPA bag, raw against raw (``iptm bench epa``), then the two FTP composites."""
    rows = ["| test | bag | EPA mpg (raw) | model mpg (raw) | error | model mpg, SOC-corrected | SOC at start / end |",
            "|---|---|---|---|---|---|---|"]
    for r in d["epa"]["bags"]:
        rows.append(f"| {r['test']} | {r['bag']} | {r['epa_mpg']:.2f} | {r['model_mpg_raw']:.1f} | "
                    f"{r['error_raw_pct']:+.1f} % | {r['model_mpg_soc_corrected']:.1f} | "
                    f"{r['soc_start']:.3f} / {r['soc_end']:.3f} |")
    rows += ["", "| test | EPA composite mpg | model, bags SOC-corrected | error | model, raw bags |", "|---|---|---|---|---|"]
    for r in d["epa"]["ftp"]:
        rows.append(f"| {r['test']} | {r['epa_mpg']:.1f} | {r['model_mpg']:.1f} | {r['error_pct']:+.1f} % | "
                    f"{r['model_mpg_raw']:.1f} |")
    return "\n".join(rows)


def _epa_causes(d: dict) -> str:
    """The warm and cold FTP and US06 with one cause at a time switched off or varied (``iptm bench epa``)."""
    rows = ["| case | warm FTP bags, raw error % | warm composite | cold FTP bags, raw error % | cold composite | "
            "US06 bags, raw error % | cold-test idle s | coolant / SOC at end of cold bag 1 |",
            "|---|---|---|---|---|---|---|---|"]
    for r in d["epa"]["causes"]:
        if isinstance(r.get("infeasible"), str):  # the controller left the cold battery a demand it cannot meet
            rows.append(f"| {r['case']} | not run: {r['infeasible']} (cold FTP) | | | | | | |")
            continue
        rows.append(f"| {r['case']} | {r['warm_bags_raw_err_pct']} | {r['warm_err_pct']:+.1f} % | "
                    f"{r['cold_bags_raw_err_pct']} | {r['cold_err_pct']:+.1f} % | {r['us06_bags_raw_err_pct']} | "
                    f"{r['cold_idle_s']:.0f} | {r['T_cl_end_bag1']:.1f} degC / {r['soc_end_cold_bag1']:.3f} |")
    return "\n".join(rows)


#: Strategy names of the case-study tables.
_STRATEGY = {"rule": "Rule-based (tuned)", "baseline": "Baseline-DP on thermal model", "thermal": "Thermal-DP",
             "thermal_cabin": "Thermal-Cabin-DP"}


def _case_study(name: str):
    """The case study ``name`` before and after the cold-start change (``iptm bench epa``, ``case_study``)."""

    def render(d: dict) -> str:
        c = d["epa"]["case_study"][name]
        rows = [f"{c['description']}; before / after:", "",
                "| strategy | fuel g | corrected g | saving over rule-based, corrected | final SOC | mean coolant degC | "
                "idle s | catalyst heating s | catalyst heating g |", "|---|---|---|---|---|---|---|---|---|"]
        for r in c["rows"]:
            b, a = r["before"], r["after"]
            sav = "-" if r["strategy"] == "rule" else f"{b['saving_pct']:.1f} / {a['saving_pct']:.1f} %"
            rows.append(f"| {_STRATEGY[r['strategy']]} | {b['fuel_g']:.1f} / {a['fuel_g']:.1f} | "
                        f"{b['fuel_corrected_g']:.1f} / {a['fuel_corrected_g']:.1f} | {sav} | "
                        f"{b['soc_final']:.3f} / {a['soc_final']:.3f} | {b['T_cl_mean_degC']:.1f} / "
                        f"{a['T_cl_mean_degC']:.1f} | {b['idle_s']:.0f} / {a['idle_s']:.0f} | "
                        f"{b['catalyst_s']:.0f} / {a['catalyst_s']:.0f} | {b['catalyst_g']:.1f} / {a['catalyst_g']:.1f} |")
        th = c["rule_thresholds"]
        keys = ("P_on_W", "P_off_W", "P_e_min_W", "k_soc_W", "soc_target")
        rows += ["", "Tuned rule-based thresholds, before / after: " + ", ".join(
            f"{k} {th['before'][k]:g} / {th['after'][k]:g}" for k in keys)]
        return "\n".join(rows)
    return render


#: Every file with generated blocks, and the renderer of each of its blocks.
FILES = {
    "README.md": {"headline": _headline, "epa-bags": _epa_bags},
    "docs/main_job.md": {"headline": _headline},
    "docs/cold_start.md": {"epa": _epa, "sim-speed": _sim_speed, "epa-bags": _epa_bags, "epa-causes": _epa_causes,
                           "case-study-paper": _case_study("paper"), "case-study-cold-soak": _case_study("cold_soak")},
    "docs/calibration_robustness.md": {"calib-selections": _calib_selections},
    "docs/testing.md": {"mutation": _mutation, "fuzz-10k": _fuzz10k},
    "docs/drive_plans.md": {"plan-bench": _plan_bench},
    "docs/studies/causal.md": {"causal": _causal, "ecms-hindsight": _ecms_hindsight},
    "docs/studies/causal_controllers.md": {"causal-rule-train": _causal_rule_train, "ecms-hindsight": _ecms_hindsight,
                                           "causal-wltc-high-cmap-trip4": _causal_per_drive},
}
RENDER = FILES["README.md"]


# --------------------------------------------------------------------------------------------------- README blocks
BLOCK = re.compile(r"(<!-- figures:(?P<name>[\w-]+) -->)(?P<body>.*?)(<!-- /figures:(?P=name) -->)", re.S)


def load() -> dict:
    d = {}
    for s in SUITES:
        p = bench_json(s)
        if p.exists():
            d.update(json.loads(p.read_text()))
    causal = {}
    for drives in CAUSAL_SETS:
        for v in CAUSAL_VALUATIONS:
            p = causal_json(drives, v)
            if p.exists():
                c = json.loads(p.read_text())["causal"]
                causal[(drives, v)] = {"goals": c["goals"], "learn_from": c.get("learn_from", []),
                                       "own_settings": c.get("own_settings"), "table": c.get("table", [])}
    if causal:
        d["causal"] = causal
    hind = {v: json.loads(p.read_text()) for v in CAUSAL_VALUATIONS if (p := hindsight_json(v)).exists()}
    if hind:
        d["ecms_hindsight"] = hind
    if RUN_JSON.exists():
        d["run"] = json.loads(RUN_JSON.read_text())
    if SELECTIONS_JSON.exists():
        d["calib_selections"] = json.loads(SELECTIONS_JSON.read_text())["selections"]
    if (JSON_DIR / "plan-bench.json").exists():
        d["plan_bench"] = json.loads((JSON_DIR / "plan-bench.json").read_text())
    if FUZZ_JSON.exists():
        d["fuzz10k"] = json.loads(FUZZ_JSON.read_text())
    if MUTATION_JSON.exists():
        m = json.loads(MUTATION_JSON.read_text())
        d["mutation"] = {k: m.get(k) for k in ("score", "killed", "survived", "equivalent", "run", "sample", "seed")}
    return d


#: Where each part of the data comes from, named when it is missing.
SOURCE_OF = {"sim": "reports/figures/bench-sim.json (`make figures`)",
             "run": "reports/figures/run.json (`make figures`)",
             "mutation": "reports/mutation.json (scripts/mutation.py)",
             "plan_bench": f"reports/figures/plan-bench.json ({PLAN_COMMAND})",
             "fuzz10k": "reports/figures/fuzz-10k.json (python -m iptm.benchmarks.fuzz --n 10000 ...)",
             "calib_selections": "reports/figures/calib-selections.json "
                                 "(`python -m iptm.benchmarks.calib --selections --json FILE`)",
             "causal": "reports/causal-SET-VALUATION.json (`iptm bench causal`)",
             "ecms_hindsight": "reports/ecms-hindsight-VALUATION.json (studies/ecms_hindsight/ecms_hindsight.py)"}


class MissingData(Exception):
    """A block's JSON is missing: the message names the file and the command that writes it."""


def blocks(text: str) -> dict:
    return {m["name"]: m["body"] for m in BLOCK.finditer(text)}


def rendered(data: dict, body: str, name: str, render: dict = RENDER) -> str:
    """A block's new body, keeping its inline/multi-line layout (a table starts on its own line)."""
    try:
        out = render[name](data)
    except KeyError as exc:
        key = exc.args[0] if exc.args else "?"
        raise MissingData(f"block {name!r} needs {SOURCE_OF.get(key, repr(key))}, which is missing") from None
    return f"\n{out}\n" if body.startswith("\n") else out


def render_text(text: str, data: dict, render: dict = RENDER) -> str:
    def sub(m):
        return m.group(1) + rendered(data, m["body"], m["name"], render) + m.group(4)

    return BLOCK.sub(sub, text)


def check(text: str, data: dict, render: dict = RENDER) -> list:
    """Differences between a file's blocks and the JSON (``render``: that file's renderers, ``FILES``): list of
    (block, in the file, from JSON)."""
    found = blocks(text)
    bad = [(n, "(no block)", "") for n in render if n not in found]
    for n, body in found.items():
        if n not in render:
            bad.append((n, body, "(unknown block)"))
            continue
        try:
            want = rendered(data, body, n, render)
        except MissingData as exc:
            bad.append((n, body.strip(), f"({exc})"))
            continue
        if body.strip() != want.strip():
            bad.append((n, body.strip(), want.strip()))
    return bad


def run_benchmarks():
    JSON_DIR.mkdir(parents=True, exist_ok=True)
    for s in SUITES:
        with tempfile.TemporaryDirectory() as td:
            tmp = Path(td) / "b.json"
            subprocess.run([sys.executable, "-m", "iptm.cli", "bench", s, "--json", str(tmp)], cwd=ROOT, check=True)
            d = json.loads(tmp.read_text())
        if s == "sim":  # its timings are quoted with the machine's load
            d["machine"] = {"load_1min": os.getloadavg()[0], "cpus": os.cpu_count()}
        out = bench_json(s)
        out.with_suffix(".tmp").write_text(json.dumps(d, indent=2) + "\n")
        out.with_suffix(".tmp").replace(out)
    with tempfile.TemporaryDirectory() as td:  # the report itself is not kept: only its summary
        tmp = Path(td) / "run.json"
        subprocess.run([sys.executable, "-m", "iptm.cli", "run", "--quiet", "--reports", str(Path(td) / "reports"),
                        "--json", str(tmp)], cwd=ROOT, check=True)
        d = json.loads(tmp.read_text())
    d.pop("report_dir", None)  # a temporary path
    RUN_JSON.with_suffix(".tmp").write_text(json.dumps(d, indent=2) + "\n")
    RUN_JSON.with_suffix(".tmp").replace(RUN_JSON)


def check_all(data: dict) -> list:
    """Differences in every file of ``FILES``: list of (file, block, in the file, from JSON)."""
    return [(f, *b) for f, render in FILES.items() for b in check((ROOT / f).read_text(), data, render)]


def main(argv=None) -> int:
    cmd = (argv or sys.argv[1:] or ["check"])[0]
    if cmd == "run":
        run_benchmarks()
        cmd = "render"
    data = load()
    if cmd == "render":
        missing = []
        for f, render in FILES.items():
            path = ROOT / f
            old = path.read_text()
            try:
                new = render_text(old, data, render)
            except MissingData as exc:  # that file is left as it is; the others are rendered
                missing.append(f"{f}: {exc}")
                continue
            if new != old:
                tmp = path.with_suffix(".tmp")
                tmp.write_text(new)
                tmp.replace(path)
        src = ([bench_json(s) for s in SUITES] + [RUN_JSON, SELECTIONS_JSON, MUTATION_JSON]
               + [causal_json(a, b) for a in CAUSAL_SETS for b in CAUSAL_VALUATIONS]
               + [hindsight_json(b) for b in CAUSAL_VALUATIONS])
        print(f"figures of {', '.join(FILES)} rendered from "
              f"{', '.join(str(p.relative_to(ROOT)) for p in src if p.exists())}")
        for m in missing:
            print(f"not rendered: {m}", file=sys.stderr)
        return 2 if missing else 0
    if cmd == "check":
        bad = check_all(data)
        for f, n, have, want in bad:
            print(f"{f}: block {n!r} differs from the JSON:\n  file: {have}\n  JSON: {want}")
        if not bad:
            print(f"the figures of {', '.join(FILES)} match the JSON")
        return 1 if bad else 0
    print(__doc__)
    return 2


if __name__ == "__main__":
    sys.exit(main())
