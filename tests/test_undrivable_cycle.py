"""A cycle the car cannot follow is one message naming the cycle and the time, exit status 2."""
from iptm.cli import main


def test_an_undrivable_cycle_names_the_cycle_and_the_time(tmp_path, capsys):
    f = tmp_path / "rocket.csv"  # 0 -> 250 km/h in 10 s, then 250 km/h
    f.write_text("time_s,speed_kph\n" + "".join(f"{t},{min(250, 25 * t)}\n" for t in range(31)))
    assert main(["optimize", "--cycle", str(f), "--formulation", "baseline", "--grid", "soc=0.04,pbat=2000",
                 "--no-cache"]) == 2
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err
    err = cap.err.strip().splitlines()[-1]
    assert err.startswith("iptm optimize: error: baseline: the cycle rocket cannot be driven") and "t = " in err
    assert "P_e_max_W" in err
