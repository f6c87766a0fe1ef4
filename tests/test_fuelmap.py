"""Measured fuel maps: the derived optimal operating line recovers a known one; bad maps are clear errors."""
import numpy as np
import pytest

from calib.errors import IptmError
from calib.model.fuelmap import RPM, apply_fuel_map, optimal_operating_line, read_fuel_map
from calib.model.params import default_parameters
from calib.model.simulate import simulate
from iptm.cli import main


def _known_map(path, unit="g/s"):
    """A map whose least-fuel speed at each power is the default OOL by construction."""
    ps = default_parameters()
    P_bp, eta_bp = np.array(ps.param("eta_ool").x), np.array(ps["eta_ool"])
    n_bp = np.array(ps["n_ool_rpm"])
    rows = []
    for n in np.arange(1000, 5201, 100.0):
        for tau in np.arange(5, 146, 5.0):
            P = n * RPM * tau
            if P > 72e3:
                continue
            n_star = np.interp(P, P_bp, n_bp)
            w = P / (np.interp(P, P_bp, eta_bp) * 42.6e3) * (1 + 0.3 * ((n - n_star) / 1000) ** 2)
            rows.append((n, tau, w * (3.6 if unit == "kg/h" else 1.0)))
    path.write_text(f"speed [rpm],torque [N*m],fuel [{unit}]\n" + "\n".join(f"{a:g},{b:g},{c:.6f}" for a, b, c in rows))
    return ps, P_bp, eta_bp, n_bp


@pytest.mark.parametrize("unit", ["g/s", "kg/h"])
def test_ool_recovered_from_map(tmp_path, unit):
    f = tmp_path / "map.csv"
    ps, P_bp, eta_bp, n_bp = _known_map(f, unit)
    fm = read_fuel_map(f)
    assert fm.fuel_g_per_s.max() < 10  # converted to g/s
    P, n, eta = optimal_operating_line(fm, 42.6e3)
    sel = (P > 5e3) & (P < 60e3)
    assert np.max(np.abs(n[sel] - np.interp(P[sel], P_bp, n_bp))) < 150  # within the map's speed step
    assert np.max(np.abs(eta[sel] / np.interp(P[sel], P_bp, eta_bp) - 1)) < 0.01


def test_apply_map_gives_a_working_parameter_set(tmp_path):
    f = tmp_path / "map.csv"
    _known_map(f)
    new = apply_fuel_map(default_parameters(), f)
    assert "measured fuel map map.csv" in new.param("eta_ool").source and new["fuel_scale"] == 1.0
    r = simulate(new, "nycc", T_amb=0.0)
    assert r.summary()["energy_balance_residual_rel"] < 1e-9 and r.fuel_g > 0
    out = tmp_path / "p.toml"
    assert main(["params", "--fuel-map", str(f), "--out", str(out)]) == 0
    assert out.is_file()


@pytest.mark.parametrize("body, words", [
    ("", "empty"),
    ("speed [rpm],torque [N*m]\n1,2\n", "missing fuel"),
    ("speed,torque [N*m],fuel [g/s]\n" + "1000,10,0.1\n" * 6, "has no unit"),
    ("speed [rpm],torque [N*m],fuel [furlong]\n" + "1000,10,0.1\n" * 6, "furlong"),
    ("speed [rpm],torque [N*m],fuel [g/s]\n1000,10,x\n" + "1000,10,0.1\n" * 6, "line 2"),
])
def test_bad_maps(tmp_path, body, words):
    f = tmp_path / "bad.csv"
    f.write_text(body)
    with pytest.raises(IptmError, match=words):
        read_fuel_map(f)
