"""The command line: help, simulate with --json, one-line errors."""
import json

from iptm.cli import main


def test_help_lists_commands(capsys):
    assert main([]) == 0
    out = capsys.readouterr().out
    for cmd in ("simulate", "synth", "bench"):
        assert cmd in out


def test_simulate_json(tmp_path, capsys):
    j = tmp_path / "s.json"
    assert main(["simulate", "--cycle", "nycc", "--ambient", "-5", "--json", str(j)]) == 0
    d = json.loads(j.read_text())
    assert d["fuel_g"] > 0 and d["energy_balance_residual_rel"] < 1e-9
    assert "fuel" in capsys.readouterr().out


def test_bad_params_file_one_line_error(tmp_path, capsys):
    f = tmp_path / "p.toml"
    f.write_text("[parameters.nope]\nvalue = 1\n")
    assert main(["simulate", "--params", str(f)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "unknown parameter 'nope'" in err


def test_unknown_cycle(capsys):
    assert main(["simulate", "--cycle", "nope"]) == 2
    assert "not found" in capsys.readouterr().err


def test_bench_causal_refuses_to_learn_from_its_test_set(capsys):
    assert main(["bench", "causal", "--drives", "cmap-trip1", "--learn-from", "cmap-trip1"]) == 2
    assert "learn from another set than --drives" in capsys.readouterr().err
