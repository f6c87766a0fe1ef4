"""Parameter sets: defaults from the bundled data, file round trips, validation errors."""
import pytest

from calib.errors import ParameterError
from calib.model.params import ParameterSet, default_parameters


def test_defaults_validate_and_carry_provenance(params):
    params.validate()
    for name in params:
        p = params.param(name)
        assert p.unit and p.source, name
        assert p.bounds[0] <= min(p.value if p.is_table else [p.value]) <= p.bounds[1]


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_round_trip(tmp_path, params, suffix):
    path = tmp_path / f"p{suffix}"
    params.save(path)
    back = ParameterSet.load(path)
    for n in params:
        assert back[n] == pytest.approx(params[n]), n
        assert back.param(n).unit == params.param(n).unit


def test_partial_file_with_unit_conversion(tmp_path):
    f = tmp_path / "p.toml"
    f.write_text('[parameters.C_eng_J_per_K]\nvalue = 120.0\nunit = "kJ/K"\n'
                 '[parameters.T_open_degC]\nvalue = 190.4\nunit = "degF"\n')
    ps = ParameterSet.load(f)
    assert ps["C_eng_J_per_K"] == pytest.approx(120e3)
    assert ps["T_open_degC"] == pytest.approx(88.0, abs=1e-6)
    assert ps["m_kg"] == default_parameters()["m_kg"]  # untouched values come from the defaults


@pytest.mark.parametrize("body, words", [
    ('[parameters.C_eng_J]\nvalue = 1.0\n', "unknown parameter 'C_eng_J'"),
    ('[parameters.C_eng_J_per_K]\nvalue = 80.0\nunit = "kg"\n', "cannot be converted"),
    ('[parameters.C_eng_J_per_K]\nvalue = 1.0\n', "outside its bounds"),
    ('[parameters.f_cl]\nvalue = [1.5, 1.2, 1.05, 1.0]\nx = [-10.0, 60.0, 20.0, 80.0]\n', "strictly increasing"),
    ('[parameters.f_cl]\nvalue = [1.0, 1.2, 1.05, 1.0]\nx = [-10.0, 20.0, 60.0, 80.0]\n', "must not increase"),
    ('[parameters.f_cl]\nvalue = [1.5, 1.2, 1.05, 1.0, 0.98, 0.99, 0.97]\n', "must not increase"),
    ('[parameters.f_cl]\nvalue = [1.5, 1.2, 1.05, 1.0]\n', "7 breakpoints but 4 values"),
    ('[parameters.f_cl]\nvalue = 1.2\n', "must be a table"),
    ('[parameters\n', "not a valid TOML"),
    # unit texts that pint's own parser fails on with a TokenError or a TypeError (found by the fuzz harness)
    ('[parameters.W_bl_kg_per_s]\nvalue = 0.05\nunit = "kg/swer)"\n', "unit 'kg/swer)': unmatched ')'"),
    ('[parameters.fuel_scale]\nvalue = 1.0\nunit = "di-ensionless"\n', "unknown unit 'di-ensionless'"),
])
def test_invalid_files_give_one_clear_error(tmp_path, body, words):
    f = tmp_path / "bad.toml"
    f.write_text(body)
    with pytest.raises(ParameterError) as ei:
        ParameterSet.load(f)
    msg = str(ei.value)
    assert words in msg and "bad.toml" in msg and "\n" not in msg


def test_with_values_validates(params):
    with pytest.raises(ParameterError):
        params.with_values(eta_em=1.5)
    assert params.with_values(eta_em=0.9)["eta_em"] == 0.9


def test_value_in_another_unit_keeps_canonical_bounds(tmp_path):
    """A file that states a value in another unit (with the bounds save() writes, in the canonical unit)."""
    ps = default_parameters()
    lo, hi = ps.param("m_kg").bounds
    f = tmp_path / "lb.toml"
    f.write_text(f'[parameters.m_kg]\nvalue = 3375\nunit = "lb"\nbounds = [{lo}, {hi}]\n')
    p = ParameterSet.load(f).param("m_kg")
    assert p.unit == "kg" and p.value == pytest.approx(3375 * 0.45359237)
    assert p.bounds == (lo, hi)
    # bounds in another unit only when the file says so
    f.write_text('[parameters.m_kg]\nvalue = 3375\nunit = "lb"\nbounds = [2300, 5000]\nbounds_unit = "lb"\n')
    assert ParameterSet.load(f).param("m_kg").bounds == pytest.approx((2300 * 0.45359237, 5000 * 0.45359237))
    f.write_text('[parameters.m_kg]\nvalue = 9000\nunit = "lb"\n')
    with pytest.raises(ParameterError, match=r"outside its bounds \[.*\] kg"):
        ParameterSet.load(f)


def test_table_status_is_per_entry(tmp_path):
    from types import SimpleNamespace

    from calib.fit.toolkit import ParamEstimate
    from calib.fit.driver import _merge

    ps = default_parameters()
    n = len(ps.param("U_oc_V").value)
    st = ["weak"] * n
    st[3] = st[4] = "estimated"
    val = list(ps.param("U_oc_V").value)
    est = ParamEstimate("U_oc_V", val, [None] * n, "estimated", "", prior=val, entry_status=st)
    _merge(ps, SimpleNamespace(estimates={"U_oc_V": est}, logs=["a.csv"]), {"U_oc_V"}, set())
    p = ps.param("U_oc_V")
    assert p.status == "estimated" and p.n_entries_estimated() == (2, n)
    assert p.status_text() == f"estimated: 2 of {n} entries ({n - 2} weak or at the prior)"
    ps.save(tmp_path / "c.toml")
    back = ParameterSet.load(tmp_path / "c.toml").param("U_oc_V")
    assert back.entry_status == st and back.status_text() == p.status_text()
    assert default_parameters().param("m_kg").status_text() == "prior"


@pytest.mark.parametrize("entry, msg", [
    ('value = -1500\nbounds = [-1e9, 1e9]', "never widen"),
    ('value = 1500\nbounds = [0, 1e300]', "never widen"),
    ('value = 1500\nbounds = [1600, 1200]', "low < high"),
    ('value = 1500\nbounds = [1000, inf]', "finite"),
    ('value = 1500\nprior_sd = -5', "positive finite"),
    ('value = 1500\nprior_sd = 0', "positive finite"),
    ('value = 1500\nprior_sd = nan', "positive finite"),
    ('value = 1500\nprior_sd = "abc"', "positive finite"),
    ('valeu = 1500', "did you mean 'value'"),
    ('value = nan', "not a finite number"),
    ('value = 1500\nunit = "kg**9**9**9"', "exponent 9"),
])
def test_a_file_cannot_widen_physics(tmp_path, entry, msg):
    f = tmp_path / "p.toml"
    f.write_text(f"[parameters.m_kg]\n{entry}\n")
    with pytest.raises(ParameterError, match=msg):
        ParameterSet.load(f)


def test_zero_capacity_or_efficiency_is_refused_not_divided_by(tmp_path):
    f = tmp_path / "p.toml"
    for name in ("C_bat_Ah", "eta_em", "C_eng_J_per_K"):
        f.write_text(f"[parameters.{name}]\nvalue = 0\n")
        with pytest.raises(ParameterError, match="outside its bounds"):
            ParameterSet.load(f)


def test_an_unknown_parameter_suggests_the_closest():
    with pytest.raises(ParameterError, match="did you mean C_bat_Ah"):
        ParameterSet.from_dict({"parameters": {"C_bat_Ahh": 6.5}})
