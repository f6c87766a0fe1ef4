"""A study file's bad [vary] value is refused on loading, by one message naming the study file."""
import pytest

from calib.errors import ScenarioError
from optimize.sweep import load_study


@pytest.mark.parametrize("bad", ["inf", "-inf", "nan", "1e400"])
def test_bad_vary_value_names_the_study_file(tmp_path, bad):
    path = tmp_path / "cold.toml"
    path.write_text('[study]\nstrategies = ["rule"]\n[scenario]\ncycle = "nycc"\n'
                    f"[vary]\nT_amb = [-7.0, {bad}]\n")
    with pytest.raises(ScenarioError) as err:
        load_study(path)
    msg = str(err.value)
    assert str(path) in msg and "T_amb" in msg and "finite" in msg
    assert "\n" not in msg


def test_good_vary_values_load(tmp_path):
    path = tmp_path / "ok.toml"
    path.write_text('[study]\nstrategies = ["rule"]\n[scenario]\ncycle = "nycc"\n[vary]\nT_amb = [-7.0, 0.0, 5.0]\n')
    assert len(load_study(path).expand()) == 3


def test_unreadable_cycle_csv_is_one_line_naming_the_file(tmp_path):
    from calib.errors import IptmError
    from calib.model.cycles import load_cycle

    bad = tmp_path / "passwd"
    bad.write_text("root:x:0:0\n" + "a,b,c,d\n" * 30)
    with pytest.raises(IptmError) as err:
        load_cycle(str(bad))
    msg = str(err.value)
    assert str(bad) in msg and "\n" not in msg and "time_s" in msg


@pytest.mark.parametrize("unit", ["degC*dB %", "dB ** 1e308", "degC*dB"])
def test_units_pint_parses_but_cannot_convert_are_one_unit_error(unit):
    """Fuzzed units that pint parses (a logarithmic unit inside a product, an exponent written 1e308) but then
    fails on with its own errors when converting: refused where the unit is parsed."""
    from calib.units import UnitError, parse_unit

    with pytest.raises(UnitError) as err:
        parse_unit(unit)
    assert repr(unit) in str(err.value)


def test_a_csv_header_with_such_a_unit_is_a_clean_error(tmp_path):
    from calib.errors import IptmError
    from calib.ingest import read_log

    p = tmp_path / "units.csv"
    p.write_text("time (degC*dB %),speed (km/h),coolant_temp (degC)\n" + "".join(f"{i},{10 + i},20\n" for i in range(8)))
    with pytest.raises(IptmError) as err:
        read_log(p)
    assert str(p) in str(err.value) and "\n" not in str(err.value)


def test_a_dbc_with_a_megabyte_line_is_refused_before_cantools_parses_it(tmp_path):
    """cantools needs ~200 bytes per byte of a line: a fuzzed 4-MB unit string cost 800 MB before."""
    import resource

    from calib.errors import LogFormatError
    from calib.ingest.dbc import PRIUS_DBC, load_dbc

    text = PRIUS_DBC.read_text().splitlines()
    i = next(k for k, ln in enumerate(text) if ln.strip().startswith("SG_"))
    head, _, rest = text[i].partition('"')
    text[i] = head + '"' + "kilo" * 1_000_000 + '"' + rest.split('"', 1)[1]
    bad = tmp_path / "bomb.dbc"
    bad.write_text("\n".join(text) + "\n")
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(LogFormatError) as err:
        load_dbc(bad)
    assert "characters long" in str(err.value) and str(bad) in str(err.value)
    assert (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024 < 100
    assert load_dbc(PRIUS_DBC).messages  # the shipped DBC passes the check


def test_a_cause_the_epa_bench_could_not_compute_fails_the_bench():
    from iptm.benchmarks.epa import cause_failures
    from iptm.commands.bench import suite_failures

    rows = [{"case": "default", "warm_err_pct": -4.5, "infeasible": float("nan")},
            {"case": "steeper f_cl", "infeasible": "step 407 (t=407 s): the controller's choice is infeasible"}]
    fails = cause_failures(rows)
    assert fails == ["cause 'steeper f_cl' not run: step 407 (t=407 s): the controller's choice is infeasible"]
    assert suite_failures({"causes": rows, "failures": fails}) == fails
