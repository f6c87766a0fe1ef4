"""What the command line prints and draws for a reader: no misleading zero lines, whole titles."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import pytest  # noqa: E402

from calib.model.params import default_parameters  # noqa: E402
from calib.model.simulate import simulate  # noqa: E402
from iptm.cli import main  # noqa: E402


def test_simulate_prints_heater_shortfall_only_when_there_is_one(capsys):
    assert main(["simulate", "--cycle", "nycc"]) == 0  # warm start: the heater gets all it asks for
    assert "shortfall" not in capsys.readouterr().out
    assert main(["simulate", "--cycle", "nycc", "--tcl0", "-10", "--tcab0", "-10"]) == 0
    assert "heater shortfall" in capsys.readouterr().out


def test_simulate_plot_title_is_whole():
    res = simulate(default_parameters(), "nycc")
    fig = res.plot()
    fig.canvas.draw()
    title = fig._suptitle
    assert res.info["controller"].split(",")[-1].strip() in title.get_text().replace("\n", " ")
    box = title.get_window_extent(fig.canvas.get_renderer())
    W, H = fig.canvas.get_width_height()
    assert box.x0 >= 0 and box.x1 <= W and box.y1 <= H


def test_fuel_economy_units():
    from calib import economy

    e = economy.economy(152.1, 4.87)
    # 152.1 g = 0.2055 L over 4.87 km
    assert e["L_per_100km"] == pytest.approx(152.1 / 740 / 4.87 * 100)
    assert e["mpg"] == pytest.approx(4.87 / (152.1 / 740) / 0.4251)
    assert economy.format_economy(152.1, 4.87) == f"{e['L_per_100km']:.2f} L/100 km, {e['mpg']:.1f} mpg"
    assert economy.format_economy(1.0, 0.0) == "-"
    s = simulate(default_parameters(), "nycc").summary()
    assert s["L_per_100km"] == economy.l_per_100km(s["fuel_g"], s["distance_km"])
