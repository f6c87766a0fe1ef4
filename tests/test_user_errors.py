"""A user's mistakes: each is one line naming the field, the file or option and the fix, exit status 2, given
before any work starts; and a benchmark whose cases failed fails."""
from __future__ import annotations

import types

import pytest

from iptm.cli import build_parser, main


def _one_error(capsys, argv) -> str:
    assert main([str(a) for a in argv]) == 2
    cap = capsys.readouterr()
    err = cap.err.strip().splitlines()
    assert len(err) == 1, cap.err  # one message, no progress bar or traceback before it
    assert "Traceback" not in cap.err + cap.out
    return err[0]


def test_calibrate_a_picture_suggests_an_option_calibrate_has(tmp_path, capsys):
    pic = tmp_path / "picture.png"
    pic.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    err = _one_error(capsys, ["calibrate", pic, "--out", tmp_path / "c.toml", "--quiet"])
    assert "picture.png" in err and "--format" in err and "mf4" in err
    cal = next(a for a in build_parser()._subparsers._group_actions[0].choices["calibrate"]._actions
               if "--format" in a.option_strings)
    assert "csv" in cal.choices
    assert not (tmp_path / "c.toml").exists()


def test_run_a_picture_suggests_no_option_run_lacks(tmp_path, capsys):
    pic = tmp_path / "picture.png"
    pic.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    err = _one_error(capsys, ["run", pic, "--quiet", "--reports", tmp_path / "r", "--cache", tmp_path / "c"])
    assert "picture.png" in err and "--format" not in err and ".blf" in err
    assert not (tmp_path / "r").exists()


def test_heater_limits_the_wrong_way_round_name_both_fields_and_the_file(tmp_path, capsys):
    f = tmp_path / "heater.toml"
    f.write_text("Q_heat_min = 2000\nQ_heat_max = 1000\n")
    err = _one_error(capsys, ["optimize", "--scenario", f, "--formulation", "thermal_cabin", "--duration", "30"])
    assert str(f) in err and "Q_heat_min = 2000" in err and "Q_heat_max = 1000" in err and "below" in err
    assert "fewer than two points" not in err


@pytest.mark.parametrize("argv, where", [
    (["--soc0", "0.95"], "--soc0 = 0.95"),
    (["--tcl0", "150", "--formulation", "thermal"], "--tcl0 = 150"),
])
def test_initial_state_off_the_grid_refused_before_solving(tmp_path, capsys, argv, where):
    err = _one_error(capsys, ["optimize", "--duration", "30", "--no-cache", *argv])
    assert err.startswith(f"iptm optimize: error: {where} lies outside the grid")
    assert "between" in err  # the fix: the range it must lie in


def test_initial_state_from_a_scenario_file_names_the_file(tmp_path, capsys):
    f = tmp_path / "s.toml"
    f.write_text("[scenario]\nsoc0 = 0.9\n")
    err = _one_error(capsys, ["run", "--scenario", f, "--quiet", "--reports", tmp_path / "r", "--cache", tmp_path / "c"])
    assert f"{f}: soc0 = 0.9" in err and f"set soc0 in {f} between 0.4 and 0.8" in err


def test_rule_based_alone_may_start_above_the_dp_grid(capsys):
    assert main(["optimize", "--soc0", "0.85", "--formulation", "rule", "--duration", "30", "--no-cache"]) == 0


def test_unknown_parameter_suggests_the_closest_names(tmp_path, capsys):
    f = tmp_path / "p.toml"
    f.write_text("[parameters.k_radd]\nvalue = 100.0\n")
    err = _one_error(capsys, ["simulate", "--params", f])
    assert str(f) in err and "'k_radd'" in err and "did you mean k_rad_W_per_K?" in err
    assert "m_kg" not in err  # not the list of all


def test_unknown_parameter_in_code_suggests_the_closest_names():
    from calib.errors import ParameterError
    from calib.model.params import default_parameters

    with pytest.raises(ParameterError, match=r"'m_kgg' \(did you mean m_kg\?\)$"):
        default_parameters().param("m_kgg")
    with pytest.raises(ParameterError) as exc:
        default_parameters().param("zzzz")
    assert "m_kg" not in str(exc.value) and "iptm params" in str(exc.value)


def test_unknown_fit_parameter_named_before_the_logs_are_read(tmp_path, capsys):
    err = _one_error(capsys, ["calibrate", tmp_path / "not_read.csv", "--out", tmp_path / "c.toml", "--fit", "m_kgg"])
    assert err == "iptm calibrate: error: --fit: unknown parameter 'm_kgg' (did you mean m_kg?)"


def test_misspelt_field_of_a_parameter_is_named(tmp_path, capsys):
    f = tmp_path / "p.toml"
    f.write_text("[parameters.m_kg]\nvaleu = 1400\n")
    err = _one_error(capsys, ["simulate", "--params", f])
    assert err.endswith(f"{f}: parameter m_kg: unknown field 'valeu' (did you mean 'value'?)")
    assert "has no value" not in err


# --------------------------------------------------------------------------------------------------------------
# benchmarks fail honestly
# --------------------------------------------------------------------------------------------------------------
def _fake_suites(monkeypatch, **suites):
    import sys

    from iptm.commands import bench

    for name, fn in suites.items():
        mod = types.ModuleType(f"fake_bench_{name}")
        mod.run = fn
        monkeypatch.setitem(sys.modules, mod.__name__, mod)
        monkeypatch.setitem(bench.SUITES, name, mod.__name__)


def test_a_benchmark_with_failed_cases_exits_non_zero(monkeypatch, capsys):
    def failing(quick=False):
        return {"t_s": 1.0, "cases": [{"failures": ["case 3: RuntimeError: boom"]}]}

    def crashing(quick=False):
        raise RuntimeError("kernel exploded\nsecond line")

    ran = []
    _fake_suites(monkeypatch, failing=failing, crashing=crashing, fine=lambda quick=False: ran.append(1) or {})
    assert main(["bench", "failing", "crashing", "fine"]) == 1
    cap = capsys.readouterr()
    assert ran == [1]  # a failed suite does not stop the others
    assert "FAILED: crashing: RuntimeError: kernel exploded" in cap.out and "second line" not in cap.out
    assert "failing: 1 failure(s), first: case 3: RuntimeError: boom" in cap.err
    assert main(["bench", "fine"]) == 0


@pytest.mark.parametrize("failing", ["warm", "bench_sweep"])
def test_the_sweep_benchmark_reports_failures_first_and_no_speed_up(monkeypatch, capsys, failing):
    import optimize
    import optimize.sweep as sweep
    from iptm.benchmarks import sweep as bench_sweep

    def broken(case):  # the cases of one study fail (the warm-up's, or the timed study's)
        err = "thermal: RuntimeError: Cannot set NUMBA_NUM_THREADS" if case["study"] == failing else None
        return {"key": case["key"], "results": {}, "error": err}

    monkeypatch.setattr(sweep, "run_case", broken)  # what run_study calls
    monkeypatch.setattr(optimize, "run_case", broken)  # the benchmark's own warm-up, through the front door
    out = bench_sweep.run(quick=True)
    text = capsys.readouterr().out
    assert out["failures"] and "Cannot set NUMBA_NUM_THREADS" in out["failures"][0]
    assert len(out["failures"]) == (1 if failing == "warm" else 16)
    assert "speedup" not in out and "t_sequential_s" not in out
    assert " s (process CPU" not in text and "x over sequential" not in text  # no time of a failed run
    assert text.splitlines()[1].startswith("FAILED: ")  # right after the description of the study


def test_unknown_scenario_field_suggests_the_closest():
    from calib.errors import ScenarioError
    from optimize.formulations.scenario import DPScenario

    with pytest.raises(ScenarioError) as err:
        DPScenario.from_dict({"T_ambb": -5.0})
    msg = str(err.value)
    assert "did you mean 'T_amb'?" in msg and "known:" not in msg


@pytest.mark.parametrize("field,value", [("T_cl0", 18446744073709551616.0), ("Q_heat", -1.09465e70), ("T_amb", 90.0),
                                         ("soc0", 1.5), ("duration_s", 1e12)])
def test_scenario_numbers_outside_their_physical_range_are_refused(field, value):
    """A finite but absurd number (a fuzzed scenario with these values built a 1-GB problem) is refused by name."""
    from calib.errors import ScenarioError
    from optimize.formulations.scenario import DPScenario

    with pytest.raises(ScenarioError) as err:
        DPScenario.from_dict({field: value})
    assert field in str(err.value) and "physical range" in str(err.value)
