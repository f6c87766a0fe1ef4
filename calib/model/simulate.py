"""Forward simulation of the model over a drive cycle under a controller, with energy bookkeeping.

:func:`simulate` returns a :class:`SimResult` (in the style of python-control's ``TimeResponseData``):
every state, control and power/heat flow as arrays, ``.to_pandas()``, ``.plot()``, ``.summary()`` and
``.energy_balance()``. The balances close to rounding error because every flow is the one the explicit
Euler step used.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from calib.model.cycles import Cycle, load_cycle
from calib.errors import ScenarioError
from calib.model.equations import INFEASIBLE_REASONS, OFF, ON, OUTPUTS, IDLE, battery_ocv_r, step, traction_power

from calib import economy
from calib.economy import GASOLINE_KG_PER_L, KM_PER_L_PER_MPG  # noqa: F401 - re-exported


def fuel_equivalents_g(p, soc0, soc_final, T_cl0, T_cl_final, T_cab0, T_cab_final) -> dict:
    """Fuel (g) equivalent to the change of stored electric and thermal energy from the initial to the
    final states (each final state may be an array: the DP values whole grids with it).

    Conversion (stated once, used everywhere: corrected fuel and the DP's ``valued`` terminal cost):
    electric energy ``C_bat U_oc(SOC) dSOC`` (``U_oc`` at the mean SOC) is valued at the fuel the engine
    would burn to put it there at its best efficiency through the generator
    (``max eta_ool * eta_mech * eta_em``); coolant heat ``C_eng dT_cl`` and cabin heat ``C_cab dT_cab``
    at the fuel an idling engine would burn to supply it (``LHV (1 - gamma_exh)`` per gram).
    """
    mid = 0.5 * (np.asarray(soc0, dtype=float) + np.asarray(soc_final, dtype=float))
    U0 = np.reshape([battery_ocv_r(p, float(m), p.T_bat_ref)[0] for m in np.ravel(mid)], np.shape(mid))
    eta_chain = float(np.max(p.eta_ool)) * p.eta_mech * p.eta_em
    d_el = p.C_bat_As * U0 * (np.asarray(soc_final, dtype=float) - soc0)
    heat = p.LHV * (1.0 - p.gamma_exh)
    out = {"electric_g": d_el / (p.LHV * eta_chain),
           "coolant_g": p.C_eng * (np.asarray(T_cl_final, dtype=float) - T_cl0) / heat,
           "cabin_g": p.C_cab * (np.asarray(T_cab_final, dtype=float) - T_cab0) / heat}
    return {k: (float(v) if np.ndim(v) == 0 else v) for k, v in out.items()}


def credit_per_gram(p, P_e: float, T_cl: float = 90.0) -> float:
    """Fuel-equivalent credit (g) that :func:`fuel_equivalents_g` gives for the charge and coolant heat one
    gram of fuel makes with the engine at power ``P_e`` (W, on), charging the battery through the
    generator, before battery and coolant losses.

    The work is credited as charge at the best-efficiency valuation and the rest of the non-exhaust fuel
    energy as coolant heat at the idling-engine valuation, so the credit is ``1 + eta (1/eta_max - 1)``
    with ``eta = P_e / (LHV W_f)``: above 1 whenever the engine does work. A strategy that ends a drive
    with charge and heat made just before the end is credited more than the fuel it burnt for them.
    """
    from calib.model.equations import ON, coolant_heat_rate, fuel_rate

    W_f = fuel_rate(p, ON, P_e, T_cl)  # one second of running: W_f grams
    net, _ = coolant_heat_rate(p.gamma_exh, p.LHV * W_f, P_e, 0.0, 0.0)
    U, _ = battery_ocv_r(p, 0.6, p.T_bat_ref)
    dsoc = P_e * p.eta_mech * p.eta_em / (p.C_bat_As * U)  # the generator's output stored without loss
    eq = fuel_equivalents_g(p, 0.6 - dsoc / 2, 0.6 + dsoc / 2, 0.0, net / p.C_eng, 0.0, 0.0)
    return float((eq["electric_g"] + eq["coolant_g"]) / W_f)


@dataclass
class SimResult:
    """Time series of one simulated (or DP-optimised) drive.

    Attributes
    ----------
    t : ndarray (N+1,)
        Time (s).
    soc, T_cl, T_cab : ndarray (N+1,)
        States at every time.
    e_mode, P_bat_mg_cmd, Q_heat_cmd : ndarray (N,)
        Controls applied during each step.
    flows : dict of ndarray (N,)
        Every output of :func:`calib.model.equations.step` during each step.
    info : dict
        Scenario and controller description.
    """

    t: np.ndarray
    soc: np.ndarray
    T_cl: np.ndarray
    T_cab: np.ndarray
    e_mode: np.ndarray
    P_bat_mg_cmd: np.ndarray
    Q_heat_cmd: np.ndarray
    flows: dict
    v: np.ndarray
    mp: object = None
    info: dict = field(default_factory=dict)

    @property
    def Ts(self) -> float:
        """Time step of the simulation, in s."""
        return float(self.t[1] - self.t[0])

    @property
    def fuel_g(self) -> float:
        """Total fuel burnt, in g."""
        return float(np.sum(self.flows["W_f"]) * self.Ts)

    @property
    def distance_km(self) -> float:
        """Distance driven, in km."""
        return float(np.sum(0.5 * (self.v[1:] + self.v[:-1])) * self.Ts / 1e3)

    def to_pandas(self) -> pd.DataFrame:
        """One row per step k (states at the start of the step, flows during it) plus the final state."""
        n = len(self.e_mode)
        df = pd.DataFrame({"time_s": self.t, "speed_mps": self.v, "soc": self.soc, "T_cl_degC": self.T_cl,
                           "T_cab_degC": self.T_cab})
        cols = {"e_mode": self.e_mode, "P_bat_mg_cmd_W": self.P_bat_mg_cmd, "Q_heat_cmd_W": self.Q_heat_cmd}
        cols.update({k: v for k, v in self.flows.items() if k not in ("soc_next", "T_cl_next", "T_cab_next")})
        for k, v in cols.items():
            df[k] = np.append(np.asarray(v, dtype=float), np.nan)[: n + 1]
        df["fuel_cum_g"] = np.concatenate([[0.0], np.cumsum(self.flows["W_f"]) * self.Ts])
        return df.set_index("time_s")

    # --- bookkeeping ------------------------------------------------------------------------------
    def energy_balance(self) -> dict:
        """Energy balances over the drive (J) and their residuals.

        - coolant: fuel energy = engine work + exhaust + engine-bay loss + radiator + heater + stored heat;
        - wheels: eta_mech * engine work + electric wheel power + friction brakes = traction energy;
        - battery: electrochemical energy U_oc I = terminal energy + resistive and hysteresis loss
          (``R_int I^2 + U_hyst |I|``);
        - cabin: heater + load + sun = stored heat.
        """
        f, Ts, p = self.flows, self.Ts, self.mp
        E = lambda a: float(np.sum(a) * Ts)  # noqa: E731
        fuel = E(f["Q_fuel"])
        stored_cl = p.C_eng * (self.T_cl[-1] - self.T_cl[0])
        out_cl = E(f["P_e"]) + E(f["Q_exh"]) + E(f["Q_air"]) + E(f["Q_rad"]) + E(f["Q_heat"])
        wheel_in = E(p.eta_mech * f["P_e"] + f["P_em"] + f["P_brake"])
        wheel = E(f["P_trac"])
        chem = E(f["U_oc"] * f["I_bat"])
        term = E(f["P_bat"])
        loss = E(f["R_int"] * f["I_bat"] ** 2 + p.U_hyst * np.abs(f["I_bat"]))
        stored_cab = p.C_cab * (self.T_cab[-1] - self.T_cab[0])
        cab_in = E(f["Q_heat"] + f["Q_cab_load"]) + p.Q_sun * Ts * len(self.e_mode)
        return {
            "fuel_energy_J": fuel, "engine_work_J": E(f["P_e"]), "exhaust_J": E(f["Q_exh"]),
            "engine_bay_loss_J": E(f["Q_air"]), "radiator_J": E(f["Q_rad"]), "heater_J": E(f["Q_heat"]),
            "coolant_stored_J": stored_cl, "traction_J": wheel, "friction_brake_J": E(f["P_brake"]),
            "battery_chemical_J": chem, "battery_terminal_J": term, "battery_loss_J": loss,
            "cabin_stored_J": stored_cab,
            "residual_coolant_rel": (fuel - out_cl - stored_cl) / max(fuel, 1.0),
            "residual_wheel_rel": (wheel_in - wheel) / max(abs(wheel), 1.0),
            "residual_battery_rel": (chem - term - loss) / max(abs(chem), 1.0),
            "residual_cabin_rel": (cab_in - stored_cab) / max(abs(cab_in), 1.0),
        }

    def fuel_equivalents(self) -> dict:
        """Fuel (g) equivalent to the change of stored electric and thermal energy over the drive
        (:func:`fuel_equivalents_g`)."""
        return fuel_equivalents_g(self.mp, self.soc[0], self.soc[-1], self.T_cl[0], self.T_cl[-1],
                                  self.T_cab[0], self.T_cab[-1])

    def summary(self) -> dict:
        """Headline figures: fuel, economy, final states, starts, idle time, heater shortfall, balances."""
        f, Ts = self.flows, self.Ts
        fuel = self.fuel_g
        eq = self.fuel_equivalents()
        corr = fuel - eq["electric_g"] - eq["coolant_g"] - eq["cabin_g"]
        fuel_el = fuel - eq["electric_g"]
        dist = self.distance_km
        running = self.e_mode != OFF
        starts = int(np.sum(running[1:] & ~running[:-1]) + (1 if running[0] else 0))
        short = np.clip(self.Q_heat_cmd - f["Q_heat"], 0.0, None)
        bal = self.energy_balance()
        return {
            **self.info,
            "duration_s": float(self.t[-1] - self.t[0]), "distance_km": dist, "fuel_g": fuel,
            "fuel_L": economy.litres(fuel), "L_per_100km": economy.l_per_100km(fuel, dist),
            "mpg": economy.mpg(fuel, dist), "mpg_soc_corrected": economy.mpg(fuel_el, dist),
            "fuel_soc_corrected_g": fuel_el, "fuel_corrected_g": corr, "fuel_equivalents_g": eq,
            "soc_initial": float(self.soc[0]), "soc_final": float(self.soc[-1]),
            "T_cl_initial_degC": float(self.T_cl[0]), "T_cl_final_degC": float(self.T_cl[-1]),
            "T_cl_mean_degC": float(np.mean(self.T_cl)), "T_cab_final_degC": float(self.T_cab[-1]),
            "T_cab_mean_degC": float(np.mean(self.T_cab)), "engine_starts": starts,
            "engine_on_s": float(np.sum(self.e_mode == ON) * Ts), "idle_s": float(np.sum(self.e_mode == IDLE) * Ts),
            "heater_delivered_J": float(np.sum(f["Q_heat"]) * Ts), "heater_shortfall_J": float(np.sum(short) * Ts),
            "energy_balance_residual_rel": max(abs(bal[k]) for k in bal if k.startswith("residual")),
        }

    def plot(self, path=None, title=None):
        """States, powers and fuel over time (:func:`calib.plotting.plot_simulation`); saves to ``path`` when
        given. Returns the Figure."""
        from calib.plotting import plot_simulation

        return plot_simulation(self, path, title)

    # --- saving -----------------------------------------------------------------------------------
    def save(self, path):
        """Save as a result folder of kind ``simulation`` (docs/results.md), atomically; returns its path."""
        from calib.results import save_result

        return save_result(path, self.write_into)

    def write_into(self, folder) -> None:
        """The folder's contents (also a part of a DP outcome's folder)."""
        import json

        from calib.results import write_parts

        arrays = sim_to_arrays(self)
        arrays.pop("info_json")
        info = json.loads(json.dumps(self.info, default=str))
        write_parts(folder, "simulation", {"info": info, "fuel_g": self.fuel_g, "n_steps": int(len(self.e_mode)),
                                           "flows": list(self.flows)}, arrays)

    @classmethod
    def load(cls, path) -> "SimResult":
        """Read a folder written by :meth:`save` (a ResultFileError where it is not one)."""
        import json

        from calib.errors import ResultFileError
        from calib.results import need, read_parts

        doc, arrays, path = read_parts(path, "simulation")
        arrays["info_json"] = np.array(json.dumps(need(doc, "info", path)))
        try:
            return sim_from_arrays(arrays)
        except KeyError as exc:
            raise ResultFileError(f"{path}: array {exc.args[0]!r} is missing") from None


def simulate(params, cycle, controller=None, *, T_amb=-10.0, soc0=0.6, T_cl0=70.0, T_cab0=20.0,
             Q_heat=1500.0, T_bat=None, W_bl=None, rule_params=None, engine_start=True) -> SimResult:
    """Run the model over a cycle.

    Parameters
    ----------
    params : ParameterSet
    cycle : str, path, Cycle or DriveLog
    controller : callable, optional
        ``controller(k, soc, T_cl, T_cab, P_trac, Ts) -> (e_mode, P_bat_mg, Q_heat_cmd)``; default the
        rule-based controller with ``rule_params`` (its heater demand set to ``Q_heat``).
    T_amb, soc0, T_cl0, T_cab0 : float
        Ambient temperature and initial states.
    T_bat : float or array, optional
        Battery temperature (default: the resistance table's reference temperature).
    engine_start : bool
        The drive starts the car (default): below the catalyst threshold the plant first heats the catalyst
        (:mod:`calib.model.catalyst`) whatever the controller commands; the controller is still called in
        those steps and only its heater command is applied. False: the drive continues a trip whose engine
        already started (no catalyst heating, and the rule-based controller's warm-up charge does not begin).
    """
    from calib.model.catalyst import prelude_steps, run_prelude
    from calib.model.rulebased import RuleBasedController, RuleParams

    cyc: Cycle = load_cycle(cycle)
    mp = params.model_params() if hasattr(params, "model_params") else params
    if controller is None:
        rp = rule_params or RuleParams(Q_heat_W=Q_heat)
        controller = RuleBasedController(mp, rp)
    if hasattr(controller, "reset"):
        controller.reset()
    if not engine_start and hasattr(controller, "warming_up"):
        controller.warming_up = False  # a continued trip is past its start: no warm-up charge begins mid-trip
    N, Ts = cyc.n_steps, cyc.Ts
    v = cyc.v
    grade = cyc.grade if cyc.grade is not None else np.zeros(N + 1)
    T_amb_a = np.broadcast_to(np.asarray(T_amb, float), (N + 1,))
    T_bat_a = np.broadcast_to(np.asarray(mp.T_bat_ref if T_bat is None else T_bat, float), (N + 1,))
    W_bl = mp.W_bl if W_bl is None else W_bl
    x = np.empty((N + 1, 3))
    x[0] = soc0, T_cl0, T_cab0
    u = np.empty((N, 3))
    out = np.empty((N, len(OUTPUTS)))
    n_pre = prelude_steps(mp, T_cl0, N, Ts) if engine_start else 0
    if n_pre:
        def heat(k, soc, T_cl, T_cab, P_trac):
            return controller(k, soc, T_cl, T_cab, P_trac, Ts)[2]

        pre = run_prelude(mp, v, grade, T_amb_a, T_bat_a, W_bl, x[0], Ts, n_pre, heat, t=cyc.t)
        x[: n_pre + 1], u[:n_pre], out[:n_pre] = pre.x, pre.u, pre.out
    tell_T_bat = hasattr(controller, "T_bat")  # a controller that limits a cold battery learns its temperature
    for k in range(n_pre, N):
        P_trac = traction_power(mp, v[k], v[k + 1], grade[k], Ts)
        if tell_T_bat:
            controller.T_bat = float(T_bat_a[k])
        e, pb, qh = controller(k, x[k, 0], x[k, 1], x[k, 2], P_trac, Ts)
        r = step(mp, x[k, 0], x[k, 1], x[k, 2], int(e), float(pb), float(qh), v[k], v[k + 1], grade[k],
                 T_amb_a[k], T_bat_a[k], W_bl, Ts)
        if r[3] != 0:
            raise ScenarioError(
                f"step {k} (t={cyc.t[k]:.0f} s, v={v[k] * 3.6:.1f} km/h): the controller's choice is infeasible: "
                f"{INFEASIBLE_REASONS[int(r[3])]} (mode {int(e)}, P_trac {P_trac / 1e3:.1f} kW) - the cycle may "
                "ask more than the vehicle can deliver; check the cycle and P_bat / P_e limits")
        u[k] = e, pb, qh
        out[k] = r
        x[k + 1] = r[0], r[1], r[2]
    flows = {name: out[:, j] for j, name in enumerate(OUTPUTS)}
    desc = controller.describe() if hasattr(controller, "describe") else getattr(controller, "__name__", "custom")
    info = {"cycle": cyc.name, "T_amb_degC": float(np.mean(T_amb_a)), "controller": desc,
            "params": (params.meta.get("name", "") if hasattr(params, "meta") else "")}
    return SimResult(cyc.t.copy(), x[:, 0].copy(), x[:, 1].copy(), x[:, 2].copy(), u[:, 0].astype(int),
                     u[:, 1].copy(), u[:, 2].copy(), flows, v.copy(), mp, info)


def sim_to_arrays(res: SimResult) -> dict:
    """Flatten a :class:`SimResult` into named numpy arrays (for ``.npz`` storage without pickle)."""
    import json

    d = {"t": res.t, "soc": res.soc, "T_cl": res.T_cl, "T_cab": res.T_cab, "e_mode": res.e_mode,
         "P_bat_mg_cmd": res.P_bat_mg_cmd, "Q_heat_cmd": res.Q_heat_cmd, "v": res.v,
         "info_json": np.array(json.dumps(res.info, default=str))}
    d.update({f"flow__{k}": v for k, v in res.flows.items()})
    for k, v in (res.mp._asdict().items() if res.mp is not None else ()):
        d[f"mp__{k}"] = np.asarray(v, dtype=np.float64)
    return d


def sim_from_arrays(d: dict) -> SimResult:
    """Inverse of :func:`sim_to_arrays`."""
    import json

    from calib.model.params import ModelParams, default_parameters

    has_mp = any(k.startswith("mp__") for k in d)  # a result made without a model (SimResult(mp=None))
    # files written before the hysteresis term existed: that model had none, so 0 V is exact there
    d = {"mp__U_hyst": np.asarray(0.0), **d}
    # files written before catalyst heating was modelled never used that mode: any value reads them exactly
    dmp = default_parameters().model_params()
    d = {"mp__W_cat": np.asarray(dmp.W_cat), "mp__w_cat": np.asarray(dmp.w_cat), "mp__t_cat": np.asarray(dmp.t_cat),
         "mp__T_cat": np.asarray(dmp.T_cat), **d}
    mp = ModelParams(**{f: (d[f"mp__{f}"] if d[f"mp__{f}"].ndim else float(d[f"mp__{f}"]))
                        for f in ModelParams._fields}) if has_mp else None
    flows = {k[6:]: d[k] for k in d if k.startswith("flow__")}
    return SimResult(d["t"], d["soc"], d["T_cl"], d["T_cab"], d["e_mode"].astype(int), d["P_bat_mg_cmd"],
                     d["Q_heat_cmd"], flows, d["v"], mp, json.loads(str(d["info_json"])))
