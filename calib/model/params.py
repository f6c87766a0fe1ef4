"""Parameter sets: values with units, bounds and provenance, read and written as TOML or JSON.

A :class:`ParameterSet` is what the simulator, the fitters and the optimiser all take. Every
:class:`Parameter` has a name that carries its unit where helpful (``C_eng_J_per_K``), a unit string
(pint syntax), bounds, a source, and after a calibration its standard error and flags. Tables (U_oc over
SOC, the cold-fuel factor over coolant temperature, engine efficiency along the optimal operating line)
are parameters whose value is a list with breakpoints ``x``.

The file format is TOML (or JSON with the same structure)::

    [meta]
    name = "2017 Toyota Prius, default"

    [parameters.C_eng_J_per_K]
    value = 80000.0
    unit = "J/K"
    bounds = [20000.0, 400000.0]
    source = "docs/model.md section 5 (prior)"

A value given in another but compatible unit (``unit = "kJ/K"``) is converted on load; bounds are always
in the parameter's canonical unit (unless ``bounds_unit`` says otherwise), so changing ``unit`` changes only
how ``value`` is read. An incompatible
unit, an unknown name, a value outside its bounds or a non-monotonic table breakpoint is an error.
"""
from __future__ import annotations

import copy
import math
from collections import namedtuple
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from calib.errors import ParameterError
from calib.units import RPM

DATA = resources.files("calib") / "data"


@dataclass
class Parameter:
    """One model parameter (scalar or table).

    Attributes
    ----------
    name, unit : str
        Name (unit-bearing where helpful) and pint unit string of ``value``.
    value : float or list of float
        Scalar value, or table values at breakpoints ``x``.
    bounds : (float, float)
        Physical bounds, applied to every table entry.
    source : str
        Where the value comes from (a data file, the spec, a calibration).
    description : str
    x, x_name, x_unit : list, str, str
        Table breakpoints (strictly increasing), their meaning and unit.
    vary : bool
        Whether calibration may estimate it (False for physical constants).
    stderr : float or list, optional
        Standard error after a calibration.
    status : str
        ``prior`` (not estimated), ``estimated`` (maximum a posteriori, the data narrowed the prior),
        ``weak`` (posterior, but the data narrowed the prior little: mostly the prior), ``fixed``.
    note : str
        Why (for example which channels were missing).
    entry_status : list of str, optional
        For a table after a calibration: the status of each entry (a table is ``estimated`` when any entry
        is; :meth:`status_text` says how many).
    prior_sd : float or list, optional
        Prior uncertainty (1 sd, unit of ``value``; per entry for tables) used by the maximum-a-posteriori
        calibration. ``None``: :func:`prior_sd_of` gives the default (25 % of the value).
    prior_value : float or list, optional
        After a calibration: the prior value the posterior ``value`` was estimated from.
    informed : float or list, optional
        After a calibration: ``1 - posterior sd / prior sd`` (0: the data said nothing, 1: the data
        alone determine it).
    """

    name: str
    value: float | list
    unit: str
    bounds: tuple
    source: str
    description: str = ""
    x: list | None = None
    x_name: str = ""
    x_unit: str = ""
    vary: bool = True
    stderr: float | list | None = None
    status: str = "prior"
    note: str = ""
    logs: list = field(default_factory=list)
    entry_status: list | None = None
    prior_sd: float | list | None = None
    prior_value: float | list | None = None
    informed: float | list | None = None

    @property
    def is_table(self) -> bool:
        """Whether the value is a table over breakpoints ``x``."""
        return self.x is not None

    def n_entries_estimated(self) -> tuple[int, int] | None:
        """For a table with per-entry statuses: (entries estimated, entries); else None."""
        if not self.is_table or not self.entry_status:
            return None
        return sum(st == "estimated" for st in self.entry_status), len(self.entry_status)

    def status_text(self) -> str:
        """The status as a reader should see it: a table says how many of its entries the data determined
        (``estimated: 2 of 15 entries``)."""
        n = self.n_entries_estimated()
        if n is None or self.status != "estimated" or n[0] == n[1]:
            return self.status
        return f"estimated: {n[0]} of {n[1]} entries ({n[1] - n[0]} weak or at the prior)"

    def to_dict(self) -> dict:
        """The parameter as a TOML/JSON-able dict."""
        d = {"value": self.value, "unit": self.unit, "bounds": list(self.bounds), "source": self.source}
        if self.description:
            d["description"] = self.description
        if self.is_table:
            d.update(x=list(self.x), x_name=self.x_name, x_unit=self.x_unit)
        if not self.vary:
            d["vary"] = False
        if self.stderr is not None:
            d["stderr"] = self.stderr
        d["status"] = self.status
        if self.note:
            d["note"] = self.note
        if self.logs:
            d["logs"] = list(self.logs)
        if self.entry_status:
            d["entry_status"] = list(self.entry_status)
        for key in ("prior_sd", "prior_value", "informed"):
            if getattr(self, key) is not None:
                d[key] = getattr(self, key)
        return d


def _p(name, value, unit, lo, hi, source, description="", **kw) -> Parameter:
    return Parameter(name, value, unit, (lo, hi), source, description, **kw)


def _battery_tables(T_C: int = 26, n_modules: int = 28):
    import csv

    with (DATA / "battery" / "nimh_module_ocv_resistance.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    rows = [r for r in rows if int(float(r["temperature_C"])) == T_C]
    soc = [float(r["soc"]) for r in rows]
    ocv = [round(n_modules * float(r["ocv_V"]), 4) for r in rows]
    res = [round(n_modules * float(r["r_total_ohm"]), 5) for r in rows]
    return soc, ocv, res


# FASTSim 2016 Prius engine efficiency vs fraction of 71 kW (docs/model.md section 4), extended to
# 72 kW. The optimal-operating-line speed is our choice: it passes through 142 N m at 3600 rpm and
# 72 kW at 5200 rpm (2ZR-FXE data) and through 1000 rpm (idle) at zero power.
_ENG_FRAC = [0.0, 0.005, 0.015, 0.04, 0.06, 0.10, 0.14, 0.20, 0.40, 0.60, 0.80, 1.00]
_ENG_ETA = [0.08, 0.10, 0.26, 0.33, 0.355, 0.37, 0.38, 0.38, 0.35, 0.34, 0.33, 0.32]


def default_parameters() -> "ParameterSet":
    """The default 2017 Prius, built from the bundled reference data (sources given per parameter)."""
    soc, ocv, res = _battery_tables(26)
    _, _, res1 = _battery_tables(1)
    # Temperature coefficient of R_int from the pack tables at 1 and 26 degC around SOC 0.5.
    i5 = soc.index(0.5)
    tc = math.log(res1[i5] / res[i5]) / 25.0
    P_ool = [round(f * 71e3, 1) for f in _ENG_FRAC] + [72e3]
    eta_ool = _ENG_ETA + [0.32]
    n_ool = [1000, 1020, 1060, 1150, 1200, 1300, 1400, 1550, 2300, 3000, 3900, 5100, 5200]
    epa = "EPA Test Car List 2022 (data/prius_facts.md)"
    bat = "NREL ADVISOR NiMH module pulse tests x 28 modules (data/battery)"
    plist = [
        # road load and vehicle
        _p("m_kg", 1531.0, "kg", 1000, 2500, f"{epa}: equivalent test weight 3375 lb", "test mass"),
        _p("m_eq_factor", 1.03, "dimensionless", 1.0, 1.15, "docs/model.md s.1", "rotating-inertia factor"),
        _p("A_N", 81.28, "N", 0, 400, f"{epa}: A = 18.272 lbf", "road-load constant term"),
        _p("B_N_per_mps", 2.940, "N*s/m", 0, 30, f"{epa}: B = 0.29545 lbf/mph", "road-load linear term"),
        _p("C_N_per_mps2", 0.3070, "N*s^2/m^2", 0.05, 1.5, f"{epa}: C = 0.013793 lbf/mph^2",
           "road-load quadratic term"),
        # power split
        _p("eta_em", 0.88, "dimensionless", 0.6, 1.0, "docs/model.md s.2", "motor+inverter+gearing, lumped"),
        _p("eta_mech", 0.96, "dimensionless", 0.8, 1.0, "docs/model.md s.2", "engine-path mechanical"),
        _p("P_e_max_W", 72e3, "W", 30e3, 120e3, "Toyota: 2ZR-FXE 72 kW at 5200 rpm", "engine maximum"),
        _p("P_regen_max_W", 25e3, "W", 0, 80e3, "docs/model.md s.2", "regenerative braking limit at wheels"),
        _p("n_idle_rpm", 1000.0, "rpm", 600, 1500, "docs/model.md s.2", "idle speed"),
        _p("P_aux_W", 400.0, "W", 0, 5000, "docs/model.md s.2", "12 V loads and blower from the HV bus"),
        _p("P_bat_min_W", -25e3, "W", -60e3, 0, "docs/model.md s.2", "battery charge power limit"),
        _p("P_bat_max_W", 25e3, "W", 0, 60e3, "docs/model.md s.2", "battery discharge power limit"),
        # battery
        _p("U_oc_V", ocv, "V", 150, 300, bat + " at 26 degC", "pack open-circuit voltage",
           x=soc, x_name="soc", x_unit="dimensionless"),
        _p("R_int_ohm", res, "ohm", 0.02, 2.0, bat + " at 26 degC", "pack internal resistance at T_ref",
           x=soc, x_name="soc", x_unit="dimensionless"),
        _p("R_int_tc_per_K", round(tc, 5), "1/K", 0.0, 0.1, bat + ": ratio of 1 and 26 degC tables at SOC 0.5",
           "R_int(T) = R_int(T_ref) exp(-tc (T - T_ref))"),
        # instantaneous hysteresis (Plett 2004, J. Power Sources 134:262, the "M0 sgn(i)" term of the enhanced
        # self-correcting cell model): a loss proportional to |I| that resistance alone cannot represent
        _p("U_hyst_V", 0.0, "V", 0.0, 40.0,
           "iptm prior: 0 (the ADVISOR pulse tests give discharge resistance only); sd 5 V, about 30 mV per cell "
           "over the pack's 168 cells (judgement)",
           "half the gap between charge and discharge open-circuit voltage: V = U_oc - U_hyst sgn(I) - R_int I"),
        _p("T_bat_ref_degC", 26.0, "degC", -40, 60, bat, "reference temperature of R_int_ohm", vary=False),
        _p("C_bat_Ah", 6.5, "A*h", 2.0, 20.0, "Toyota: NiMH 6.5 Ah (data/prius_facts.md)", "capacity"),
        # fuel
        # upper bound above any engine's efficiency: a calibrated table also carries the level (fuel_scale
        # stays at its base value), so it is an effective efficiency eta / fuel_scale
        _p("eta_ool", eta_ool, "dimensionless", 0.02, 0.6,
           "NREL FASTSim 2016 Prius engine efficiency vs fraction of 71 kW", "engine efficiency on the OOL",
           x=P_ool, x_name="P_e", x_unit="W"),
        _p("n_ool_rpm", n_ool, "rpm", 600, 6000, "iptm choice through 142 N m @ 3600 rpm and 72 kW @ 5200 rpm",
           "engine speed on the optimal operating line", x=P_ool, x_name="P_e", x_unit="W", vary=False),
        _p("fuel_scale", 1.065, "dimensionless", 0.5, 2.0,
           "tuned to EPA warm UDDS/HWFET/US06 with the rule-based controller (calib.model.epa.tune_fuel_scale)",
           "warm fuel-map scale"),
        _p("W_idle_g_per_s", 0.10, "g/s", 0.02, 0.5, "docs/model.md s.4", "idle fuel rate, warm"),
        # catalyst heating after a cold start (docs/cold_start.md): a fixed fuel rate at a set engine speed
        _p("W_cat_g_per_s", round(0.60 * 3.785411784 * 0.74 / 3.6, 3), "g/s", 0.05, 2.0,
           "owner's ScanGauge readings of a 2003 and a 2010 Prius: 0.60 gal/h held regardless of pedal and speed "
           "until the catalyst is warm (fuelzilla.com/prius, 'motor assist obscure warm-up EV mode', 2011)",
           "fuel rate while heating the catalyst", vary=False),
        _p("n_cat_rpm", 1350.0, "rpm", 900, 2000,
           "owners' observation of the third-generation Prius: 1300-1400 rpm while heating the catalyst "
           "(priuschat.com/posts/2320984)", "engine speed while heating the catalyst", vary=False),
        _p("t_cat_s", 50.0, "s", 0, 120,
           "owners' scan-tool warm-up stages of the third-generation Prius: about 50 s "
           "(priuschat.com/goto/post?id=1067278; '45-55 seconds', priuschat.com/posts/2320984)",
           "duration of catalyst heating after a cold start (0: none)", vary=False),
        _p("T_cat_degC", 60.0, "degC", -40, 100,
           "the same warm-up stages: catalyst heating after a start below about 60 degC coolant "
           "(priuschat.com/goto/post?id=1067278)", "coolant at the start below which the catalyst is heated",
           vary=False),
        # above the warm reference (80 degC) the factor may fall below 1: oil and coolant hotter than the
        # thermostat's lower friction and wall-heat loss by a few % (docs/model.md s.4); prior 1 there
        _p("f_cl", [1.5, 1.2, 1.05, 1.0, 1.0, 1.0, 1.0], "dimensionless", 0.5, 6.0,
           "docs/model.md s.4 (prior shape below 80 degC); above it 1 +- 1.5 % per 10 K (Brace et al. 2008, "
           "Proc. IMechE D 222(4) 579-591: about 3 % lower bsfc at low load from hotter coolant and oil)",
           "coolant fuel factor (1 at the warm reference)",
           x=[-10.0, 20.0, 60.0, F_CL_REF_DEGC, 90.0, 100.0, 120.0], x_name="T_cl", x_unit="degC"),
        _p("LHV_J_per_g", 42.6e3, "J/g", 40e3, 45e3, "gasoline, 42.6 MJ/kg", "lower heating value", vary=False),
        # engine coolant
        _p("C_eng_J_per_K", 80e3, "J/K", 20e3, 400e3, "docs/model.md s.5 (prior)", "engine+coolant heat capacity"),
        _p("gamma_exh", 0.4, "dimensionless", 0.2, 0.8,
           "NREL ADVISOR FC_SI95.m fc_ex_pwr_frac (waste heat to exhaust) 0.40 at low engine speed (0.30 at high); "
           "checked against the EPA warm and cold FTP (docs/cold_start.md)",
           "fraction of fuel heat (not work) leaving with the exhaust"),
        _p("hA_eng_W_per_K", 25.0, "W/K", 1.0, 300.0, "docs/model.md s.5 (prior)", "engine-to-compartment"),
        _p("kappa", 0.3, "dimensionless", 0.0, 0.9, "docs/model.md s.5 (prior)",
           "compartment temperature: T_com = T_amb + kappa (T_cl - T_amb)"),
        _p("T_open_degC", 88.0, "degC", 70.0, 105.0, "docs/model.md s.5 (prior)", "thermostat opening"),
        _p("k_rad_W_per_K", 1500.0, "W/K", 100.0, 20000.0, "docs/model.md s.5 (prior)", "radiator gain"),
        _p("Q_rad_max_W", 50e3, "W", 1e3, 100e3,
           "iptm prior: sustained 30 kW engine power with gamma_exh 0.4 must not saturate the radiator "
           "(docs/model.md s.5 prior 30 kW assumed gamma_exh 0.5)", "radiator capacity"),
        # heater core and cabin
        _p("eps_hc", 0.7, "dimensionless", 0.2, 1.0, "NREL ADVISOR heater effectiveness", "heater-core effectiveness"),
        _p("W_bl_kg_per_s", 0.06, "kg/s", 0.01, 0.3, "iptm prior (mid blower)", "blower air mass flow"),
        _p("recirc_frac", 0.0, "dimensionless", 0.0, 1.0, "iptm prior: fresh air in winter (anti-fog)",
           "heater inlet air = recirc T_cab + (1 - recirc) T_amb"),
        _p("cp_air_J_per_kgK", 1005.0, "J/(kg*K)", 1000, 1010, "air", "air heat capacity", vary=False),
        _p("C_cab_J_per_K", 60e3, "J/K", 10e3, 400e3, "docs/model.md s.6 (prior)", "cabin heat capacity"),
        _p("UA_cab_W_per_K", 50.0, "W/K", 5.0, 300.0, "docs/model.md s.6 (prior)", "cabin loss conductance"),
        _p("Q_sun_W", 0.0, "W", -500.0, 2000.0, "docs/model.md s.6 (prior)", "solar and occupant gains"),
    ]
    for p in plist:
        if p.name in PRIOR_SD or p.name in TABLE_PRIOR_SD:
            p.prior_sd = prior_sd_of(p)
    return ParameterSet({p.name: p for p in plist}, meta={"name": "2017 Toyota Prius, default",
                                                         "origin": "calib.model.params.default_parameters"})


#: Prior uncertainty (1 sd) of every parameter the calibration estimates, as a function of the prior
#: value (per entry for tables). Judgement, stated so it can be argued with: the spec's priors are
#: round engineering numbers (25-50 %), the pack tables and the efficiency curve are measured on
#: similar hardware (a few %), the cold-fuel excess is uncertain in proportion to its size.
PRIOR_SD = {
    "U_oc_V": lambda v: 4.0,  # V: +-2 % between packs of the same type
    "R_int_ohm": lambda v: 0.25 * v,
    "R_int_tc_per_K": lambda v: 0.01,
    "U_hyst_V": lambda v: 5.0,
    "C_bat_Ah": lambda v: 1.5,
    "eta_ool": lambda v: 0.20 * v,  # another engine, or this one with a biased fuel meter
    "fuel_scale": lambda v: 0.15,
    "W_idle_g_per_s": lambda v: 0.04,
    "C_eng_J_per_K": lambda v: 0.3 * v,
    "gamma_exh": lambda v: 0.1,
    "hA_eng_W_per_K": lambda v: 0.5 * v,
    "kappa": lambda v: 0.1,
    "T_open_degC": lambda v: 4.0,
    "k_rad_W_per_K": lambda v: 0.5 * v,
    "eps_hc": lambda v: 0.15,
    "C_cab_J_per_K": lambda v: 0.4 * v,
    "UA_cab_W_per_K": lambda v: 0.4 * v,
    "Q_sun_W": lambda v: 150.0,
}


#: Warm reference of the coolant fuel factor ``f_cl`` (degC): the table is 1 at its last breakpoint at or
#: below this temperature, so the warm fuel map is the fuel rate of an engine at 80 degC.
F_CL_REF_DEGC = 80.0
#: Prior sd of ``f_cl`` above the warm reference, per K above it: 1.5 % per 10 K (3 % at 100 degC, 6 % at
#: 120 degC), the size of the measured bsfc gain of an engine run hotter than its thermostat (source above).
F_CL_HOT_SD_PER_K = 0.0015


def f_cl_ref_index(x) -> int:
    """Index of the warm reference breakpoint of an ``f_cl`` table: the last one at or below
    :data:`F_CL_REF_DEGC` (the first one when every breakpoint is above it)."""
    x = np.asarray(x, float)
    return max(int(np.searchsorted(x, F_CL_REF_DEGC, side="right")) - 1, 0)


def _f_cl_prior_sd(p: "Parameter") -> list:
    r = f_cl_ref_index(p.x)
    # below the reference engines differ most when cold (x2-x5 at -7 degC seen); above it a few %
    return [0.05 + 1.0 * (v - 1.0) if j <= r else F_CL_HOT_SD_PER_K * (x - p.x[r])
            for j, (x, v) in enumerate(zip(p.x, p.value))]


#: Prior sd of table parameters that depends on the breakpoints, not only on the values.
TABLE_PRIOR_SD = {"f_cl": _f_cl_prior_sd}


def prior_sd_of(p: "Parameter"):
    """Prior sd of a parameter: its own ``prior_sd``, else :data:`TABLE_PRIOR_SD` or :data:`PRIOR_SD` of its
    value, else 25 %."""
    if p.prior_sd is not None:
        return p.prior_sd
    if p.name in TABLE_PRIOR_SD and p.is_table:
        return [float(v) for v in TABLE_PRIOR_SD[p.name](p)]
    f = PRIOR_SD.get(p.name, lambda v: 0.25 * abs(v) if v else 1.0)
    return [float(f(v)) for v in p.value] if p.is_table else float(f(p.value))


#: One field of the compiled form: its ``name`` (the kernels' attribute), the ``param`` it is read from, how it
#: is read (``read``: "value", "x" the table's breakpoints, a number the value is multiplied by (a unit
#: conversion), or a function of the set for a quantity derived from several), whether it is an ``array``, and
#: the other parameters whose values a derived field reads (``also``).
CompiledField = namedtuple("CompiledField", ["name", "param", "read", "array", "also"], defaults=[()])


def _val(name, param, scale=None):
    return CompiledField(name, param, "value" if scale is None else scale, False)


def _tab(name, param, read="value"):
    return CompiledField(name, param, read, True)


#: The compact form the compiled model reads, one row per field in :class:`ModelParams` order: the one place
#: where a compiled name is tied to its parameter. :meth:`ParameterSet.model_params`, :func:`compiled_with`
#: (the fitters) and the DP kernels' flat vector (``optimize.formulations.layout``) are generated from it.
COMPILED = (
    _val("m", "m_kg"), CompiledField("m_eq", "m_kg", lambda ps: float(ps["m_kg"]) * float(ps["m_eq_factor"]), False,
                                      ("m_eq_factor",)),
    _val("A", "A_N"), _val("B", "B_N_per_mps"), _val("C", "C_N_per_mps2"), _val("eta_em", "eta_em"),
    _val("eta_mech", "eta_mech"), _val("P_e_max", "P_e_max_W"), _val("P_regen_max", "P_regen_max_W"),
    _val("w_idle", "n_idle_rpm", RPM), _val("P_aux", "P_aux_W"), _val("P_bat_min", "P_bat_min_W"),
    _val("P_bat_max", "P_bat_max_W"), _tab("soc_bp", "U_oc_V", "x"), _tab("U_oc", "U_oc_V"),
    _tab("soc_bp_R", "R_int_ohm", "x"), _tab("R_int", "R_int_ohm"), _val("R_tc", "R_int_tc_per_K"),
    _val("T_bat_ref", "T_bat_ref_degC"), _val("C_bat_As", "C_bat_Ah", 3600.0), _tab("P_ool", "eta_ool", "x"),
    _tab("eta_ool", "eta_ool"),
    # the engine speed on the optimal operating line at the efficiency table's breakpoints (rad/s)
    CompiledField("w_ool", "n_ool_rpm", lambda ps: np.interp(_x(ps, "eta_ool"), _x(ps, "n_ool_rpm"),
                                                             _a(ps, "n_ool_rpm")) * RPM, True),
    _val("fuel_scale", "fuel_scale"), _val("W_idle", "W_idle_g_per_s"), _tab("T_fcl", "f_cl", "x"),
    _tab("f_cl", "f_cl"), _val("LHV", "LHV_J_per_g"), _val("C_eng", "C_eng_J_per_K"), _val("gamma_exh", "gamma_exh"),
    _val("hA_eng", "hA_eng_W_per_K"), _val("kappa", "kappa"), _val("T_open", "T_open_degC"),
    _val("k_rad", "k_rad_W_per_K"), _val("Q_rad_max", "Q_rad_max_W"), _val("eps_hc", "eps_hc"),
    _val("W_bl", "W_bl_kg_per_s"), _val("recirc", "recirc_frac"), _val("cp_air", "cp_air_J_per_kgK"),
    _val("C_cab", "C_cab_J_per_K"), _val("UA_cab", "UA_cab_W_per_K"), _val("Q_sun", "Q_sun_W"),
    _val("U_hyst", "U_hyst_V"), _val("W_cat", "W_cat_g_per_s"), _val("w_cat", "n_cat_rpm", RPM),
    _val("t_cat", "t_cat_s"), _val("T_cat", "T_cat_degC"),
)

# The compact form the compiled model reads (numba accepts namedtuples of floats and arrays).
ModelParams = namedtuple("ModelParams", [f.name for f in COMPILED])
#: The compiled fields that are numbers (the rest are arrays), in :class:`ModelParams` order.
SCALAR_FIELDS = tuple(f.name for f in COMPILED if not f.array)
#: The compiled fields read from each parameter.
FIELDS_OF = {p: tuple(f for f in COMPILED if p == f.param or p in f.also)
             for p in dict.fromkeys(n for f in COMPILED for n in (f.param, *f.also))}


def _a(ps, n):
    return np.ascontiguousarray(ps[n], dtype=np.float64)


def _x(ps, n):
    return np.ascontiguousarray(ps.param(n).x, dtype=np.float64)


def _read(ps, f: CompiledField):
    if callable(f.read):
        return f.read(ps)
    if f.read == "x":
        return _x(ps, f.param)
    if f.array:
        return _a(ps, f.param)
    return float(ps[f.param]) if f.read == "value" else float(ps[f.param]) * f.read


def compiled_with(mp: ModelParams, values: dict, names=None) -> ModelParams:
    """``mp`` with the fields read from some parameters replaced: ``values`` maps parameter names (of
    ``names`` where given; other keys, such as a fit's nuisance parameters, are then ignored) to new values.

    The fitters' objective functions change a few parameters thousands of times; this rebuilds only their
    fields, through :data:`COMPILED`; a table's breakpoints stay. A parameter a derived field reads cannot be
    replaced this way (a ParameterError): build it with :meth:`ParameterSet.with_values`."""
    new = {}
    for n in (values if names is None else [n for n in names if n in values]):
        if n not in FIELDS_OF:
            raise ParameterError(f"parameter {n!r} is not read by the compiled model")
        for f in FIELDS_OF[n]:
            if f.read == "x":
                continue  # a table's breakpoints are not its values
            if callable(f.read):
                raise ParameterError(f"{f.name} is derived from {n}: replace {n} with ParameterSet.with_values")
            v = values[n]
            if f.array:
                new[f.name] = np.ascontiguousarray(v, dtype=np.float64)
            else:
                new[f.name] = float(v) if f.read == "value" else float(v) * f.read
    return mp._replace(**new)


class ParameterSet:
    """An ordered collection of :class:`Parameter` with file I/O and validation.

    ``pset["C_eng_J_per_K"]`` returns the value; ``pset.param(name)`` the :class:`Parameter`.
    """

    def __init__(self, params: dict, meta: dict | None = None):
        self._p = dict(params)
        self.meta = dict(meta or {})

    # --- access -----------------------------------------------------------------------------------
    def __getitem__(self, name):
        return self.param(name).value

    def __contains__(self, name):
        return name in self._p

    def __iter__(self):
        return iter(self._p)

    def names(self) -> list[str]:
        """Parameter names in definition order."""
        return list(self._p)

    def param(self, name) -> Parameter:
        """The :class:`Parameter` called ``name`` (ParameterError suggesting the closest names if absent)."""
        try:
            return self._p[name]
        except KeyError:
            raise ParameterError(f"unknown parameter {name!r} ({self.closest_hint(name)})") from None

    def closest_hint(self, name) -> str:
        """"did you mean ...?" with the closest parameter names, or where the list of all names is."""
        import difflib

        g = str(name)
        close = difflib.get_close_matches(g, self.names(), n=3, cutoff=0.6)
        if not close:  # a name without its unit suffix (k_rad for k_rad_W_per_K): compare with as many characters
            by_start = {n[:len(g)]: n for n in reversed(self.names())}
            close = [by_start[k] for k in difflib.get_close_matches(g, list(by_start), n=3, cutoff=0.75)]
        return f"did you mean {' or '.join(close)}?" if close else "`iptm params --out FILE` writes every parameter"

    def copy(self) -> "ParameterSet":
        """A deep copy (parameters are mutable)."""
        return ParameterSet(copy.deepcopy(self._p), copy.deepcopy(self.meta))

    def with_values(self, **values) -> "ParameterSet":
        """A copy with some values replaced (validated)."""
        new = self.copy()
        for k, v in values.items():
            p = new.param(k)
            p.value = list(map(float, v)) if p.is_table else float(v)
        new.validate()
        return new

    # --- validation -------------------------------------------------------------------------------
    def validate(self) -> None:
        """Check every value against its bounds and table shapes; raise ParameterError saying which."""
        for p in self._p.values():
            lo, hi = p.bounds
            vals = p.value if p.is_table else [p.value]
            for v in vals:
                if not isinstance(v, (int, float)) or not math.isfinite(v):
                    raise ParameterError(f"{p.name}: value {v!r} is not a finite number")
                if not lo <= v <= hi:
                    raise ParameterError(f"{p.name} = {v:g} {p.unit} is outside its bounds [{lo:g}, {hi:g}] {p.unit}")
            if p.is_table:
                if len(p.x) != len(p.value):
                    raise ParameterError(f"{p.name}: {len(p.x)} breakpoints but {len(p.value)} values")
                if len(p.x) < 2 or any(b <= a for a, b in zip(p.x, p.x[1:])):
                    raise ParameterError(f"{p.name}: breakpoints {p.x_name} must be strictly increasing: {p.x}")
        f = self.param("f_cl").value
        if any(b > a + 1e-12 for a, b in zip(f, f[1:])):
            raise ParameterError(f"f_cl must not increase with coolant temperature: {f}")
        u = self.param("U_oc_V").value
        if any(b < a for a, b in zip(u, u[1:])):
            raise ParameterError(f"U_oc_V must not decrease with SOC: {u}")
        if self["P_bat_min_W"] >= self["P_bat_max_W"]:
            raise ParameterError("P_bat_min_W must be below P_bat_max_W")

    # --- compiled form ----------------------------------------------------------------------------
    def model_params(self) -> ModelParams:
        """The namedtuple of floats and float64 arrays that the compiled model functions take (:data:`COMPILED`)."""
        return ModelParams(*(_read(self, f) for f in COMPILED))

    # --- I/O --------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The set as a TOML/JSON-able dict (what :meth:`save` writes)."""
        return {"meta": dict(self.meta), "parameters": {k: p.to_dict() for k, p in self._p.items()}}

    def save(self, path) -> None:
        """Write as TOML (``.toml``) or JSON (``.json``), atomically."""
        from calib.fileio import write_json, write_text

        path = Path(path)
        d = self.to_dict()
        if path.suffix.lower() == ".json":
            write_json(path, d)
        elif path.suffix.lower() == ".toml":
            import tomli_w

            write_text(path, tomli_w.dumps(_strip_none(d)))
        else:
            raise ParameterError(f"{path}: parameter files are .toml or .json")

    @classmethod
    def load(cls, path, base: "ParameterSet | None" = None) -> "ParameterSet":
        """Read a TOML or JSON parameter file.

        Parameters missing from the file keep the values of ``base`` (default: the default Prius), so a
        file may hold only what it changes. Units are converted to each parameter's canonical unit.
        """
        from calib.fileio import read_config

        path = Path(path)
        d = read_config(path, ParameterError, "parameter file")
        return cls.from_dict(d, base=base, origin=str(path))

    @classmethod
    def from_dict(cls, d: dict, base: "ParameterSet | None" = None, origin: str = "<dict>") -> "ParameterSet":
        new = (base or default_parameters()).copy()
        if not isinstance(d, dict) or not isinstance(d.get("parameters", {}), dict):
            raise ParameterError(f"{origin}: expected a [parameters] table")
        if not isinstance(d.get("meta", {}), dict):
            raise ParameterError(f"{origin}: [meta] must be a table")
        new.meta.update(d.get("meta", {}))
        new.meta["file"] = origin
        for name, entry in d.get("parameters", {}).items():
            try:
                new._read_entry(name, entry, origin)
            except (TypeError, ValueError, AttributeError, OverflowError) as exc:
                # a field of the wrong kind that the checks below do not name (a table where text goes, ...)
                raise ParameterError(f"{origin}: parameter {name}: a field has the wrong type "
                                     f"({str(exc).splitlines()[0][:120]})") from None
        try:
            new.validate()
        except ParameterError as exc:
            raise ParameterError(f"{origin}: {exc}") from None
        return new

    def _read_entry(self, name, entry, origin: str) -> None:
        """Apply one ``[parameters.NAME]`` entry of a file (checked field by field)."""
        new = self
        limits = physical_limits()
        if name not in new:
            raise ParameterError(f"{origin}: unknown parameter {name!r} ({new.closest_hint(name)})")
        p = new.param(name)
        if not isinstance(entry, dict):
            entry = {"value": entry}
        unknown = [k for k in entry if k not in ENTRY_FIELDS]
        if unknown:
            import difflib

            k = unknown[0]
            close = difflib.get_close_matches(str(k), ENTRY_FIELDS, n=1, cutoff=0.6)
            raise ParameterError(f"{origin}: parameter {name}: unknown field {k!r}"
                                 + (f" (did you mean {close[0]!r}?)" if close else
                                    f" (fields: {', '.join(ENTRY_FIELDS)})"))
        if "value" not in entry:
            raise ParameterError(f"{origin}: parameter {name} has no value")
        val = entry["value"]
        if p.is_table != isinstance(val, list):
            kind = "a table (list)" if p.is_table else "a scalar"
            raise ParameterError(f"{origin}: parameter {name} must be {kind}")
        unit = entry.get("unit", p.unit)
        val = _convert(val, unit, p.unit, f"{origin}: parameter {name}")
        p.value = [float(v) for v in val] if p.is_table else float(val)
        if p.is_table and "x" in entry and not isinstance(entry["x"], list):
            raise ParameterError(f"{origin}: breakpoints x of {name} must be a list of numbers")
        if p.is_table and "x" in entry:
            xu = entry.get("x_unit", p.x_unit)
            p.x = [float(v) for v in _convert(entry["x"], xu, p.x_unit, f"{origin}: breakpoints of {name}")]
        if "prior_sd" not in entry and (p.name in PRIOR_SD or p.name in TABLE_PRIOR_SD):
            # the default uncertainty of the new value (and breakpoints)
            p.prior_sd = None
            if not p.is_table or len(p.x) == len(p.value):  # else validate() names the mismatch
                p.prior_sd = prior_sd_of(p)
        for key in ("source", "description", "status", "note"):
            if key in entry:
                setattr(p, key, str(entry[key]))
        if "stderr" in entry:
            p.stderr = _numbers(entry["stderr"], f"{origin}: stderr of {name}")
        if "logs" in entry:
            p.logs = list(entry["logs"])
        if "entry_status" in entry and p.is_table:
            st = entry["entry_status"]
            if not (isinstance(st, list) and len(st) == len(p.value)):
                raise ParameterError(f"{origin}: entry_status of {name} must list one status per table entry")
            p.entry_status = [str(v) for v in st]
        for key in ("prior_sd", "prior_value", "informed"):
            if key in entry:
                setattr(p, key, _numbers(entry[key], f"{origin}: {key} of {name}")
                        if key != "prior_sd" else entry[key])
        if "prior_sd" in entry:
            _check_prior_sd(entry["prior_sd"], p, origin)
        if "bounds" in entry:
            b = entry["bounds"]
            if not (isinstance(b, list) and len(b) == 2):
                raise ParameterError(f"{origin}: bounds of {name} must be [low, high]")
            # Bounds belong to the parameter and are in its canonical unit (what save() writes), whatever
            # unit the value is given in; ``bounds_unit`` states another unit explicitly.
            bu = entry.get("bounds_unit", p.unit)
            lo, hi = (float(v) for v in _convert(b, bu, p.unit, f"{origin}: bounds of {name}"))
            llo, lhi = limits[name]
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ParameterError(f"{origin}: bounds of {name} must be two finite numbers, low < high; got {b}")
            if lo < llo or hi > lhi:
                raise ParameterError(f"{origin}: bounds of {name} [{lo:g}, {hi:g}] {p.unit} go beyond its physical "
                                     f"limits [{llo:g}, {lhi:g}] {p.unit}: a parameter file may narrow the "
                                     "bounds, never widen them")
            p.bounds = (lo, hi)

    def table(self):
        """A pandas DataFrame, one row per parameter (for reports)."""
        import pandas as pd

        rows = []
        for p in self._p.values():
            rows.append({"name": p.name, "value": p.value, "unit": p.unit, "stderr": p.stderr,
                         "status": p.status, "source": p.source, "note": p.note})
        return pd.DataFrame(rows)


#: The fields a parameter entry of a file may have (anything else is a typo, named with the closest field).
ENTRY_FIELDS = ("value", "unit", "bounds", "bounds_unit", "vary", "x", "x_unit", "x_name", "source", "description",
                "status", "note", "stderr", "logs", "entry_status", "prior_sd", "prior_value", "informed")

_LIMITS: dict | None = None


def physical_limits() -> dict:
    """``{name: (low, high)}``: the bounds of the default parameter set, which are physical limits owned by the
    code (no zero capacity, no efficiency above 1, no negative mass). A file may narrow a parameter's bounds
    within them, never widen them."""
    global _LIMITS
    if _LIMITS is None:
        ps = default_parameters()
        _LIMITS = {n: tuple(ps.param(n).bounds) for n in ps.names()}
    return _LIMITS


def _check_prior_sd(sd, p, origin) -> None:
    """A prior sd is a positive finite number (one per entry for a table)."""
    vals = sd if isinstance(sd, list) else [sd]
    if p.is_table and isinstance(sd, list) and len(sd) != len(p.value):
        raise ParameterError(f"{origin}: prior_sd of {p.name} must give one value per table entry ({len(p.value)})")
    for v in vals:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise ParameterError(f"{origin}: prior_sd of {p.name} must be a positive finite number, got {v!r}")


def _strip_none(o):
    if isinstance(o, dict):
        return {k: _strip_none(v) for k, v in o.items() if v is not None}
    if isinstance(o, list):
        return [_strip_none(v) for v in o]
    return o


def _numbers(val, what: str):
    """``val`` (a number or a list of numbers) as floats, or one ParameterError naming ``what``: text, a
    table, a boolean or an integer too large for a float is not a value."""
    items = val if isinstance(val, list) else [val]
    out = []
    for v in items:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ParameterError(f"{what}: {str(v)[:40]!r} is not a number")
        try:
            out.append(float(v))
        except OverflowError:
            raise ParameterError(f"{what}: {str(v)[:20]}... is too large for a number") from None
    return out if isinstance(val, list) else out[0]


def _convert(val, unit: str, target: str, what: str):
    val = _numbers(val, what)
    if not isinstance(unit, str):
        raise ParameterError(f"{what}: unit {str(unit)[:40]!r} is not a unit string")
    if unit == target:
        return val
    import pint

    from calib.units import UnitError, parse_unit, ureg  # shared registry with aliases (ingestion)

    try:
        u = parse_unit(unit)  # garbage text is a UnitError here, whatever pint's tokenizer raises
    except UnitError as exc:
        raise ParameterError(f"{what}: {exc}; give a unit convertible to {target!r}") from None
    try:
        arr = np.asarray(val, dtype=float)
        q = ureg.Quantity(arr, u).to(target).magnitude
    except (pint.errors.DimensionalityError, ValueError, TypeError) as exc:
        raise ParameterError(f"{what}: unit {unit!r} cannot be converted to {target!r} ({exc})") from None
    return q.tolist() if isinstance(val, list) else float(q)
