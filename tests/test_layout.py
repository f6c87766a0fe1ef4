"""The compiled form and the DP kernels' flat vector are generated from one table (calib.model.params.COMPILED)."""
import numpy as np
import pytest

from calib.errors import ParameterError
from calib.model.params import COMPILED, SCALAR_FIELDS, ModelParams, compiled_with, default_parameters
from optimize.formulations import layout


def test_every_compiled_field_reads_a_parameter_of_the_set():
    ps = default_parameters()
    assert ModelParams._fields == tuple(f.name for f in COMPILED)
    for f in COMPILED:
        assert f.param in ps, f
        assert f.array == isinstance(getattr(ps.model_params(), f.name), np.ndarray), f


def test_model_params_reads_each_parameter_by_its_name():
    ps = default_parameters().with_values(C_eng_J_per_K=91e3, UA_cab_W_per_K=37.5, C_bat_Ah=7.0, n_idle_rpm=1100.0,
                                          m_kg=1600.0, m_eq_factor=1.05)
    mp = ps.model_params()
    assert mp.C_eng == 91e3 and mp.UA_cab == 37.5
    assert mp.C_bat_As == 7.0 * 3600.0  # the unit conversions of the table
    assert mp.w_idle == pytest.approx(1100.0 * 2 * np.pi / 60)
    assert mp.m_eq == 1600.0 * 1.05
    assert np.array_equal(mp.soc_bp, ps.param("U_oc_V").x) and np.array_equal(mp.U_oc, ps["U_oc_V"])


def test_slots_are_numbered_by_code_and_cover_every_scalar():
    assert layout._MS == SCALAR_FIELDS
    slots = list(layout.SLOT.values())
    names_in_header = len(layout.CFG) + len(layout.ARRAYS) + len(SCALAR_FIELDS) + len(layout.HEATER)
    assert len(set(slots)) == names_in_header  # no two names share a slot
    used = set(slots) | {layout.SLOT["array:" + a] + 1 for a in layout.ARRAYS}  # a descriptor's length
    assert used == set(range(layout._HEADER))  # every header slot has one name, none is left over


def test_the_packed_vector_holds_every_model_scalar_under_its_name():
    """What the kernels read at ``P[_MS0 + _CENG]`` is the parameter set's C_eng_J_per_K, and so for every
    slot the kernels name."""
    ps = default_parameters().with_values(C_eng_J_per_K=91e3, UA_cab_W_per_K=37.5, C_cab_J_per_K=55e3,
                                          gamma_exh=0.35, Q_sun_W=120.0, U_hyst_V=2.0)
    mp = ps.model_params()
    ms = np.array([float(getattr(mp, n)) for n in layout._MS])
    arrays = [np.arange(3.0), np.arange(2.0), np.arange(4.0)] + [np.asarray(getattr(mp, n)) for n in
                                                                 layout.ARRAYS[3:9]] + [np.arange(5.0)]
    P = layout.pack_params(np.arange(len(layout.CFG), dtype=float), ms, arrays)
    for f in COMPILED:
        if not f.array:
            assert P[layout.SLOT[f.name]] == getattr(mp, f.name), f
    kernel_names = {"_R_TC": "R_int_tc_per_K", "_TBREF": "T_bat_ref_degC", "_KAPPA": "kappa", "_HA": "hA_eng_W_per_K",
                    "_TOPEN": "T_open_degC", "_KRAD": "k_rad_W_per_K", "_QRADMAX": "Q_rad_max_W", "_EPS": "eps_hc",
                    "_CP": "cp_air_J_per_kgK", "_RECIRC": "recirc_frac", "_LHV": "LHV_J_per_g",
                    "_GAMMA": "gamma_exh", "_CENG": "C_eng_J_per_K", "_UACAB": "UA_cab_W_per_K",
                    "_CCAB": "C_cab_J_per_K", "_QSUN": "Q_sun_W", "_UHYST": "U_hyst_V"}
    for alias, name in kernel_names.items():
        assert P[layout._MS0 + getattr(layout, alias)] == ps[name], alias
    assert P[layout._MS0 + layout._CBAT] == ps["C_bat_Ah"] * 3600.0
    for j, name in enumerate(layout.ARRAYS):
        assert np.array_equal(layout._arr(P, layout.SLOT["array:" + name]), arrays[j].ravel()), name
    for i, name in enumerate(layout.CFG):
        assert P[layout.SLOT["cfg:" + name]] == i


def test_pack_params_refuses_a_vector_of_another_layout():
    mp = default_parameters().model_params()
    ms = np.array([float(getattr(mp, n)) for n in layout._MS])
    with pytest.raises(ValueError, match="model scalars"):
        layout.pack_params(np.zeros(len(layout.CFG)), ms[:-1], [np.zeros(1)] * len(layout.ARRAYS))


def test_compiled_with_replaces_by_parameter_name():
    ps = default_parameters()
    mp0 = ps.model_params()
    mp = compiled_with(mp0, {"UA_cab_W_per_K": 42.0, "C_bat_Ah": 5.0, "soc0_log1": 0.5},
                       ("UA_cab_W_per_K", "C_bat_Ah", "Q_sun_W"))
    want = ps.with_values(UA_cab_W_per_K=42.0, C_bat_Ah=5.0).model_params()
    for f in ModelParams._fields:
        assert np.array_equal(np.asarray(getattr(mp, f)), np.asarray(getattr(want, f))), f
    with pytest.raises(ParameterError, match="not read by the compiled model"):
        compiled_with(mp0, {"soc0_log1": 0.5})
    with pytest.raises(ParameterError, match="derived from m_eq_factor"):
        compiled_with(mp0, {"m_eq_factor": 1.1})
