"""Statistics helpers of the fitters (:mod:`calib.fit.toolkit`). The effective sample size behind the standard-error inflation of every fitter
(:func:`calib.fit.toolkit.neff`), on sequences whose autocorrelation is worked out here with direct sums
(the function under test uses FFTs), against the rule its docstring states: ``tau`` the largest of the
integrated autocorrelation time, the batch-means value (only with at least 4 blocks of
``max(20, sqrt(n))`` samples) and the AR(1) value ``(1 + rho_1) / (1 - rho_1)`` with ``rho_1`` clipped
to [0, 0.995]."""
import math

import numpy as np
import pytest

from calib.fit.toolkit import (WEAK_INFORMED, combine_with_prior, held_by_bound, inflation, map_fit, neff,
                               posterior_estimate)


def _rho1(r):
    r0 = np.asarray(r, float) - np.mean(r)
    return float(r0[:-1] @ r0[1:] / (r0 @ r0))


def test_alternating_residuals_are_independent_samples():
    """+1, -1, ...: rho_1 = -99/100 (below 0.05 at the first lag: tau_int = 1, AR(1) clipped at 0 -> 1),
    block means of 20 alternating samples are 0: n_eff = n."""
    r = np.tile([1.0, -1.0], 50)
    assert _rho1(r) == pytest.approx(-0.99)
    assert neff([r]) == (100, 100.0)
    assert neff([r, r[:40]]) == (140, 140.0)
    assert inflation([r], 2) == 1.0


def test_near_unit_lag_one_correlation_is_capped_at_0_995():
    """One sine period over 79 samples: rho_1 > 0.995, so the AR(1) factor is its cap
    (1 + 0.995) / (1 - 0.995) = 399; the integrated time is at most 1 + 2 * 14 = 29 (79 // 5 = 15 lags) and
    there are fewer than 4 blocks of 20, so tau = 399 and each segment counts 79 / 399 samples."""
    m = 79
    r = np.sin(2 * np.pi * (np.arange(m) + 1) / (m + 1))
    assert _rho1(r) > 0.995
    n, ne = neff([r] * 20)
    assert n == 20 * m
    assert ne == pytest.approx(20 * m / 399.0, rel=1e-12)


def test_effective_sample_size_is_at_least_one():
    """A single such segment counts 79 / 399 < 1 samples: n_eff is floored at 1 (so sqrt(n / n_eff) stays
    finite); no usable segment (fewer than 3 finite samples) gives n = 0 and n_eff = 1."""
    m = 79
    r = np.sin(2 * np.pi * (np.arange(m) + 1) / (m + 1))
    assert neff([r]) == (m, 1.0)
    assert inflation([r]) == pytest.approx(np.sqrt(m))
    assert neff([[1.0, np.nan, 2.0]]) == (0, 1.0)
    # three samples are enough: r0 = (-4, -1, 5) / 3, rho_1 = -1/42 < 0.05, so tau = 1
    assert neff([[1.0, 2.0, 4.0]]) == (3, 3.0)
    # and with two parameters fitted to them: sqrt((3 - 2) / (3 - 2)) = 1
    assert inflation([[1.0, 2.0, 4.0]], 2) == 1.0


def _out(informed, value=1.2, prior_sd=0.5, post_sd=0.4):
    return {"informed": {"a": informed}, "values": {"a": value}, "prior_sd": {"a": prior_sd}, "post_sd": {"a": post_sd}}


def test_posterior_is_weak_when_the_data_narrowed_the_prior_by_less_than_30_percent():
    assert WEAK_INFORMED == 0.3
    e = posterior_estimate("a", _out(0.1), "", 1.0)  # moved 0.4 prior sd: no "moved" remark
    assert (e.status, e.value, e.stderr, e.prior, e.prior_sd) == ("weak", 1.2, 0.4, 1.0, 0.5)
    assert e.note == "data informed 10 % (prior sd 0.5, posterior sd 0.4); weakly informed: the value is mostly the prior"
    e = posterior_estimate("a", _out(0.1, value=1.6), "n", 1.0)  # moved 1.2 prior sd
    assert e.note == ("n; data informed 10 % (prior sd 0.5, posterior sd 0.4); moved +1.2 prior sd from the prior; "
                      "weakly informed: the data moved it, but its sd is still close to the prior's")
    e = posterior_estimate("a", _out(0.3), "", 1.0)
    assert e.status == "estimated" and "weakly" not in e.note
    e = posterior_estimate("a", _out(0.9, post_sd=0.05), "", 1.0)
    assert (e.status, e.note) == ("estimated", "data informed 90 % (prior sd 0.5, posterior sd 0.05)")
    # a posterior mode at a bound says so, after the rest of the note
    out = {**_out(0.9, post_sd=0.05), "at_bound": {"a": "posterior mode 1.2 at its bound [0, 1.2]"}}
    assert posterior_estimate("a", out, "", 1.0).note == ("data informed 90 % (prior sd 0.5, posterior sd 0.05); "
                                                          "posterior mode 1.2 at its bound [0, 1.2]")


def test_map_fit_of_a_line_through_the_origin():
    """y = a x with a Gaussian prior on a: the MAP estimate and its sd in closed form,
    a = (x.y / s^2 + a0 / sd0^2) / (x.x / s^2 + 1 / sd0^2), sd = (x.x / s^2 + 1 / sd0^2)^-1/2, with s the
    noise floor (the residuals here are far below it); an input perturbation that gives no residuals
    adds nothing, one that shifts the data by dy adds the shift of the estimate it causes."""
    import lmfit

    x = np.linspace(1.0, 5.0, 40)
    y = 2.0 * x + 0.01 * np.sin(7 * x)
    a0, sd0, s = 1.0, 0.5, 0.1

    def make():
        ps = lmfit.Parameters()
        ps.add("a", value=a0, min=-10, max=10)
        return ps

    def segs(ps, dy=0.0):
        return [ps["a"].value * x - (y + dy)]

    prec = x @ x / s ** 2 + 1 / sd0 ** 2
    a_map = (x @ y / s ** 2 + a0 / sd0 ** 2) / prec
    out = map_fit(make, segs, ["a"], prior={"a": a0}, prior_sd={"a": sd0}, noise_sd=s, floor=s)
    assert out["values"]["a"] == pytest.approx(a_map, rel=1e-6)
    assert out["post_sd"]["a"] == pytest.approx(prec ** -0.5, rel=1e-4)
    out2 = map_fit(make, segs, ["a"], prior={"a": a0}, prior_sd={"a": sd0}, noise_sd=s, floor=s,
                   perturbed=[lambda ps: []])
    assert out2["post_sd"]["a"] == out["post_sd"]["a"]
    out3 = map_fit(make, segs, ["a"], prior={"a": a0}, prior_sd={"a": sd0}, noise_sd=s, floor=s,
                   perturbed=[lambda ps: segs(ps, dy=0.05)])
    shift = (x.sum() * 0.05 / s ** 2) / prec  # moving every y by 0.05 moves a_map by this
    assert out3["post_sd"]["a"] == pytest.approx(np.hypot(prec ** -0.5, shift), rel=1e-3)
    assert out["at_bound"] == {}

    def bounded():  # the data want a = 2.0; the upper bound 1.5 holds it there
        ps = lmfit.Parameters()
        ps.add("a", value=a0, min=-10, max=1.5)
        return ps

    out4 = map_fit(bounded, segs, ["a"], prior={"a": a0}, prior_sd={"a": sd0}, noise_sd=s, floor=s)
    assert out4["values"]["a"] == pytest.approx(1.5, abs=1e-6)
    assert list(out4["at_bound"]) == ["a"] and "at its bound [-10, 1.5]" in out4["at_bound"]["a"]


def test_map_fit_posterior_correlation_of_slope_and_offset():
    """y = a x + c with independent Gaussian priors: posterior covariance (X'X / s^2 + diag(1 / sd0^2))^-1,
    its correlation cov_ac / sqrt(cov_aa cov_cc) (strongly negative: x is far from 0)."""
    import lmfit

    x = np.linspace(5.0, 9.0, 30)
    y = 0.5 * x + 1.0 + 0.01 * np.cos(5 * x)
    s = 0.2

    def make():
        ps = lmfit.Parameters()
        ps.add("a", value=0.0, min=-10, max=10)
        ps.add("c", value=0.0, min=-10, max=10)
        return ps

    out = map_fit(make, lambda ps: [ps["a"].value * x + ps["c"].value - y], ["a", "c"], prior={"a": 0.0, "c": 0.0},
                  prior_sd={"a": 1.0, "c": 2.0}, noise_sd=s, floor=s)
    X = np.column_stack([x, np.ones_like(x)])
    cov = np.linalg.inv(X.T @ X / s ** 2 + np.diag([1.0, 0.25]))
    r = cov[0, 1] / np.sqrt(cov[0, 0] * cov[1, 1])
    assert r < -0.9
    assert list(out["correl"]) == ["a|c"]  # each pair once, in the order of ``cand``
    assert out["correl"]["a|c"] == pytest.approx(r, rel=1e-4)
    assert out["post_sd"]["c"] == pytest.approx(np.sqrt(cov[1, 1]), rel=1e-4)


def test_combine_with_prior_is_precision_weighted():
    """Estimate 2.0 (se 0.5) and prior 1.0 (sd 2.0): precisions 4 and 0.25, posterior mean 8.25 / 4.25,
    sd 4.25^-1/2, informed 1 - sd / 2.0."""
    e = combine_with_prior("a", 2.0, 0.5, 1.0, 2.0, "n")
    assert e.value == pytest.approx(8.25 / 4.25, rel=1e-12)
    assert e.stderr == pytest.approx(4.25 ** -0.5, rel=1e-12)
    assert e.informed == pytest.approx(1 - 4.25 ** -0.5 / 2.0, rel=1e-12) and e.status == "estimated"


def test_output_error_initial_temperature_within_5_K_of_the_first_measured_value():
    from calib.fit.toolkit import output_error_params

    make = output_error_params(["a"], {"a": (0.0, 2.0)}, {"a": 1.0}, [{"name": "T0_0", "T0": -7.5}])
    ps = make({"a"})
    assert (ps["T0_0"].value, ps["T0_0"].min, ps["T0_0"].max, ps["T0_0"].vary) == (-7.5, -12.5, -2.5, True)
    assert (ps["a"].value, ps["a"].min, ps["a"].max, ps["a"].vary) == (1.0, 0.0, 2.0, True)
    assert not make(set())["a"].vary


def _constant_fit(y, s, a0, sd0, **kw):
    """map_fit of a constant ``a`` (start 0.5, bounds +-100) to the samples ``y``, prior N(a0, sd0^2), noise
    sd ``s`` (also the floor)."""
    import lmfit

    def make():
        ps = lmfit.Parameters()
        ps.add("a", value=0.5, min=-100, max=100)
        return ps

    return map_fit(make, lambda ps: [ps["a"].value - y], ["a"], prior={"a": a0}, prior_sd={"a": sd0}, noise_sd=s,
                   floor=s, **kw)


def test_posterior_note_says_how_far_the_data_moved_the_value_from_half_a_prior_sd():
    """The note names a move of half a prior sd or more (here exactly 0.5: 1.0 -> 2.0 with a prior sd of
    2), and says nothing of a smaller one."""
    from calib.fit.toolkit import posterior_estimate

    out = {"informed": {"a": 0.5}, "prior_sd": {"a": 2.0}, "post_sd": {"a": 1.0}, "values": {"a": 2.0}}
    assert "moved +0.5 prior sd from the prior" in posterior_estimate("a", out, "", 1.0).note
    out["values"]["a"] = 1.98
    assert "moved" not in posterior_estimate("a", out, "", 1.0).note


def test_combine_with_prior_takes_a_zero_standard_error_as_no_estimate():
    """A closed-form estimate whose standard error is 0 (a noise-free or degenerate regression) carries no
    usable uncertainty: the posterior is the prior, with a note saying so, as for a missing or infinite
    one; a positive one is precision-weighted."""
    for se in (0.0, None, float("inf"), -1.0):
        e = combine_with_prior("a", 2.0, se, 1.0, 0.5, "fit")
        assert (e.value, e.stderr, e.informed) == (1.0, 0.5, 0.0) and "no usable estimate" in e.note, se
    e = combine_with_prior("a", 2.0, 0.5, 1.0, 0.5, "fit")
    assert e.value == pytest.approx(1.5, rel=1e-12) and e.stderr == pytest.approx(0.5 / np.sqrt(2.0), rel=1e-12)


def test_map_fit_noise_sd_counts_fewer_than_two_effective_samples():
    """A constant through a 10-sample ramp: the residual is one slow drift, n_eff = 1.76 (AR(1) factor of
    rho_1 = 0.7, :func:`neff`), and the noise sd is re-estimated as rms * sqrt(n / n_eff) with that value
    (the floor of n_eff at 1 does not apply)."""
    y = np.arange(10.0)
    out = _constant_fit(y, 0.01, 0.0, 100.0)
    r = out["values"]["a"] - y
    n, ne = neff([r])
    assert n == 10 and 1.0 < ne < 2.0
    assert out["noise_sd"] == pytest.approx(np.sqrt(np.mean(r ** 2) * n / ne), rel=1e-9)


def test_map_fit_robust_loss_discounts_an_outlier():
    """A constant through 40 zeros and one sample at 50 with a broad prior: squares put the estimate near
    the mean (50/41 = 1.22), a robust loss (soft_l1, f_scale 3 noise sd) keeps it below 0.75; loss='linear'
    reaches the closed-form least-squares MAP."""

    y = np.zeros(41)
    y[20] = 50.0
    s, a0, sd0 = 1.0, 0.0, 100.0

    lin = _constant_fit(y, s, a0, sd0)
    prec = y.size / s ** 2 + 1 / sd0 ** 2
    # (the second pass weighs the prior with the re-estimated noise sd: a 1e-4 effect with this broad prior)
    assert lin["values"]["a"] == pytest.approx((y.sum() / s ** 2 + a0 / sd0 ** 2) / prec, rel=1e-3)
    rob = _constant_fit(y, s, a0, sd0, loss="soft_l1")
    assert abs(rob["values"]["a"]) < 0.75 and lin["values"]["a"] > 1.2


def test_batch_means_count_from_exactly_four_blocks():
    """80 samples: four blocks of 20 at +1, -1, +1, -1 plus a +-1 alternation. By hand: lag-one sum
    73 (block pairs) - 79 (alternation) + 2 (cross terms at the block edges) = -4 over a sum of squares
    160, rho_1 = -0.025 (tau_int = 1, AR(1) factor 1); the block means are +-1 (variance 1) against a
    residual variance 2: tau = 20 x 1 / 2 = 10, n_eff = 8. The first 79 samples make only 3 blocks of 20:
    no batch-means term, n_eff = 79."""
    r = np.repeat([1.0, -1.0, 1.0, -1.0], 20) + np.tile([1.0, -1.0], 40)
    assert _rho1(r) == pytest.approx(-0.025, rel=1e-12)
    n, ne = neff([r])
    assert n == 80 and ne == pytest.approx(8.0, rel=1e-12)
    assert _rho1(r[:79]) < 0.05
    assert neff([r[:79]]) == (79, 79.0)


def test_map_fit_robust_loss_is_scipy_soft_l1_with_f_scale_3():
    """The robust first look is scipy.optimize.least_squares with loss='soft_l1' and f_scale=3 (noise sd)
    on the documented objective [(model - data) / s, (a - prior) / prior_sd]. Here s is the floor 1.0 (the
    residuals' rms, 0.86, is below it, so the fit is not repeated); three outliers 4 sd out sit where
    f_scale 3 and 4 weigh them differently (weights 0.60 against 0.71)."""
    from scipy.optimize import least_squares

    y = 0.1 * np.sin(np.arange(63.0))
    y[[10, 30, 50]] = 4.0
    s, a0, sd0 = 1.0, 0.0, 10.0

    rob = _constant_fit(y, s, a0, sd0, loss="soft_l1")
    assert rob["noise_sd"] == s and rob["rmse"] < s

    def ref(f_scale):
        fun = lambda p: np.concatenate([(p[0] - y) / s, [(p[0] - a0) / sd0]])  # noqa: E731
        return least_squares(fun, [0.5], loss="soft_l1", f_scale=f_scale, xtol=1e-15, ftol=1e-15, gtol=1e-15).x[0]

    assert abs(ref(3.0) - ref(4.0)) > 0.01  # the two scales are told apart far beyond the tolerance below
    assert rob["values"]["a"] == pytest.approx(ref(3.0), rel=1e-6)


def test_map_fit_covariance_with_a_nuisance_parameter_near_zero_matches_the_analytic_jacobian():
    """r = a x + exp(b t) - y with a Gaussian prior on a and b a nuisance parameter (no prior: its forward
    difference step is 1e-3 (0.1 |b| + 1e-3), about 1.6e-6 here, as for an initial temperature near 0 degC).
    The posterior covariance is (J'J)^-1 with the analytic Jacobian J = [x / s, t exp(b t) / s] over the
    data and [1 / sd0, 0] for the prior, at the MAP; b's column is curved in b, so a step of 1e-3 would
    be off by about 1e-3."""
    import lmfit

    x = np.linspace(1.0, 5.0, 50)
    t = np.linspace(0.0, 2.0, 50)
    y = 2.0 * x + 1.0 + 0.01 * np.sin(7 * x)
    s, a0, sd0 = 0.1, 1.0, 0.5

    def make():
        ps = lmfit.Parameters()
        ps.add("a", value=a0, min=-10, max=10)
        ps.add("b", value=0.1)
        return ps

    out = map_fit(make, lambda ps: [ps["a"].value * x + np.exp(ps["b"].value * t) - y], ["a"], prior={"a": a0},
                  prior_sd={"a": sd0}, noise_sd=s, floor=s)
    b = out["params"]["b"].value
    assert abs(b) < 0.01 and out["noise_sd"] == s and out["cov_names"] == ["a", "b"]
    J = np.vstack([np.column_stack([x, t * np.exp(b * t)]) / s, [[1.0 / sd0, 0.0]]])
    cov = np.linalg.inv(J.T @ J)
    np.testing.assert_allclose(out["cov"], cov, rtol=2e-5)
    assert out["post_sd"]["a"] == pytest.approx(np.sqrt(cov[0, 0]), rel=2e-5)


@pytest.mark.parametrize("statuses,logs,fitted", [
    (("estimated", "prior"), ["a"], True),
    (("fixed", "weak"), ["a"], True),
    (("prior", "fixed"), ["a"], False),
    (("estimated",), [], False),
    ((), ["a"], False),
])
def test_subsystem_is_fitted_when_a_parameter_is_estimated_or_weak_from_some_log(statuses, logs, fitted):
    from calib.fit.toolkit import ParamEstimate, SubsystemFit

    est = {f"p{i}": ParamEstimate(f"p{i}", 1.0, 0.1, s) for i, s in enumerate(statuses)}
    assert SubsystemFit("t", (), estimates=est, logs=logs).fitted is fitted


def test_map_fit_stops_rescaling_the_noise_once_it_moved_less_than_5_percent():
    """A constant a with a strong prior N(2, 0.03^2) against data of mean 3: the MAP moves with the noise
    scale s, a(s) = (sum y / s^2 + a0 / sd0^2) / (n / s^2 + 1 / sd0^2). From s0 = 0.95 the first fit gives
    a(s0) and the rms of its residuals s1 = 1.0245 s0 (within 5 %): the fit stops there, with a(s0) and
    noise_sd s1 (another pass at s1 would give a(s1), 0.1 % lower)."""
    import lmfit

    n = 50
    y = 3.0 + 0.2 * np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    a0, sd0, s0 = 2.0, 0.03, 0.95

    def a_map(s):
        return (y.sum() / s ** 2 + a0 / sd0 ** 2) / (n / s ** 2 + 1 / sd0 ** 2)

    a1 = a_map(s0)
    s1 = float(np.sqrt(np.mean((a1 - y) ** 2)))
    assert 1.0 < s1 / s0 < 1.05 and abs(a_map(s1) / a1 - 1.0) > 5e-4

    def make():
        ps = lmfit.Parameters()
        ps.add("a", value=0.5, min=-100, max=100)
        return ps

    # max_tau = 1: the scale is the plain rms (the residuals' common offset would count as correlation)
    out = map_fit(make, lambda ps: [ps["a"].value - y], ["a"], prior={"a": a0}, prior_sd={"a": sd0},
                  noise_sd=s0, floor=1e-6, max_tau=1.0)
    assert out["values"]["a"] == pytest.approx(a1, rel=1e-7)
    assert out["noise_sd"] == pytest.approx(s1, rel=1e-7)


def test_map_fit_tries_the_further_starts_in_its_first_minimisation():
    """m(a) = a^3 - 3a against data y = 3: a local minimum of the misfit at a = -1 (m = 2, residual 1 per
    sample) and the global one where a^3 - 3a = 3 (a = 2.1038). From a = -1.2 the first minimisation ends
    at -1; the start a = 2.5 reaches the global one. With the noise sd set to what a fit at -1 ends with,
    a fit there moves its noise sd by less than 5 % and stops: only starts tried in the *first*
    minimisation can leave the local mode."""
    import lmfit

    rng = np.random.default_rng(3)
    y = 3.0 + 0.01 * rng.standard_normal(200)

    def make():
        ps = lmfit.Parameters()
        ps.add("a", value=-1.2, min=-3.0, max=3.0)
        return ps

    def segs(ps):
        a = ps["a"].value
        return [(a ** 3 - 3.0 * a) - y]

    kw = dict(prior={"a": 0.0}, prior_sd={"a": 100.0})
    local = map_fit(make, segs, ["a"], noise_sd=0.01, **kw)
    assert local["values"]["a"] == pytest.approx(-1.0, abs=1e-3)
    out = map_fit(make, segs, ["a"], noise_sd=local["noise_sd"], starts=[{"a": 2.5}], **kw)
    root = float(np.real([r for r in np.roots([1.0, 0.0, -3.0, -3.0]) if abs(r.imag) < 1e-12 and r.real > 0][0]))
    assert root == pytest.approx(2.1038, abs=1e-4)
    assert out["values"]["a"] == pytest.approx(root, abs=1e-3)
    # and the noise sd is re-estimated at the global mode: about the data's 0.01, not the local mode's ~1
    assert out["noise_sd"] < 0.1 < local["noise_sd"]


def _level_fit(nuisance_start=1.0):
    """Data y = 3 + noise fitted by a level ``a`` (prior 0 +- 100); ``c`` is in the parameters but in no
    residual: neither the data nor a prior constrain it."""
    import lmfit

    y = 3.0 + 0.01 * np.random.default_rng(3).standard_normal(200)

    def make():
        ps = lmfit.Parameters()
        ps.add("a", value=1.0, min=-5.0, max=5.0)
        ps.add("c", value=nuisance_start, min=-10.0, max=10.0)
        return ps

    return make, (lambda ps: [ps["a"].value - y]), dict(noise_sd=0.01, prior={"a": 0.0}, prior_sd={"a": 100.0})


def test_map_fit_keeps_the_first_minimisation_on_a_tie():
    """A start that moves only ``c`` (which no residual reads) ends at the same objective to the last bit:
    the tie keeps ``make_params``'s own start, so the result does not depend on the order of the starts."""
    make, segs, kw = _level_fit()
    out = map_fit(make, segs, ["a"], starts=[{"c": 5.0}], **kw)
    assert out["params"]["c"].value == 1.0
    assert out["values"]["a"] == pytest.approx(3.0, abs=0.01)


def test_map_fit_reports_a_parameter_nothing_constrains_as_unknown_not_exact():
    """Posterior sd by the Gauss-Newton normal matrix: ``c`` spans its null space, where a pseudo-inverse
    gives variance 0; the fit reports sd inf, informed 0 and no correlation for it, while ``a`` keeps its
    sd, 0.01 / sqrt(200) against the prior's 100 (scaled by the noise sd the fit re-estimates)."""
    make, segs, kw = _level_fit()
    out = map_fit(make, segs, ["a", "c"], **kw)
    assert out["post_sd"]["c"] == math.inf
    assert out["informed"]["c"] == 0.0
    assert out["correl"] == {}
    assert out["post_sd"]["a"] == pytest.approx(out["noise_sd"] / math.sqrt(200), rel=0.05)
    assert 0.99 < out["informed"]["a"] < 1.0


def test_integrated_autocorrelation_time_sums_at_most_n_over_5_lags():
    """A slow cosine (period 160 samples) under white noise, 100 samples: the autocorrelation stays above
    0.05 past lag 20 = n/5, so the integrated time sums lags 1-19 (15.1; 12.9 had it stopped at n/6),
    more than the batch-means (9.9) and AR(1) (2.7) values: n_eff = 100 / 15.1, worked out here with
    direct sums."""
    rng = np.random.default_rng(2)
    m = 100
    r = np.cos(2 * np.pi * np.arange(m) / 160) + 0.8 * rng.standard_normal(m)
    r0 = r - r.mean()
    c0 = float(np.sum(r0 * r0))
    rho = np.array([np.sum(r0[:m - k] * r0[k:]) / c0 for k in range(m)])
    assert np.all(rho[1:21] >= 0.05)
    tau = 1.0 + 2.0 * float(np.sum(rho[1:20]))
    assert 1.0 + 2.0 * float(np.sum(rho[1:16])) < 13.0 < 15.0 < tau
    r1 = float(rho[1])
    bm = r0.reshape(5, 20).mean(axis=1)
    assert max((1.0 + r1) / (1.0 - r1), 20 * float(np.var(bm)) / (c0 / m)) < 10.0
    n, ne = neff([r])
    assert n == m and ne == pytest.approx(m / tau, rel=1e-9)


def test_map_fit_adds_an_inputs_calibration_uncertainty_as_the_shift_it_causes():
    """A level fitted to data whose calibration is uncertain by 0.05 (one sd, an offset): with the data
    moved by it the estimate moves by 0.05 (the prior, sd 100, barely pulls), and the posterior sd is the
    data's alone and that shift in quadrature, also where the level is held at a bound."""
    make, segs, kw = _level_fit()
    out = map_fit(make, segs, ["a"], **kw)
    moved = map_fit(make, segs, ["a"], perturbed=[lambda ps: [r - 0.05 for r in segs(ps)]], **kw)
    assert moved["values"]["a"] == out["values"]["a"]
    assert moved["post_sd"]["a"] == pytest.approx(math.hypot(out["post_sd"]["a"], 0.05), rel=1e-6)
    # the same with the level held at a bound (2.95, below the data's 3), where the misfit's gradient is
    # not zero: the shift is still the one the moved data cause, not a step towards the unbounded optimum
    def bounded():
        ps = make()
        ps["a"].set(max=2.95)
        return ps

    out = map_fit(bounded, segs, ["a"], **kw)
    moved = map_fit(bounded, segs, ["a"], perturbed=[lambda ps: [r - 0.05 for r in segs(ps)]], **kw)
    assert out["values"]["a"] == pytest.approx(2.95) and "a" in out["at_bound"]
    assert moved["post_sd"]["a"] == pytest.approx(math.hypot(out["post_sd"]["a"], 0.05), rel=1e-6)


def test_map_fit_takes_half_the_difference_of_an_input_moved_both_ways():
    """A pair ``(up, down)`` is a central difference: data moved by -0.05 - 0.02 one way and by +0.05 - 0.02
    the other (a response with a second-order part, 0.02 both ways) shift the level by half the
    difference, 0.05, not by either side's 0.07 or 0.03; a pair whose side gives no residuals adds none."""
    make, segs, kw = _level_fit()
    out = map_fit(make, segs, ["a"], **kw)
    pair = (lambda ps: [r - 0.07 for r in segs(ps)], lambda ps: [r + 0.03 for r in segs(ps)])
    moved = map_fit(make, segs, ["a"], perturbed=[pair], **kw)
    assert moved["post_sd"]["a"] == pytest.approx(math.hypot(out["post_sd"]["a"], 0.05), rel=1e-6)
    empty = map_fit(make, segs, ["a"], perturbed=[(pair[0], lambda ps: [])], **kw)
    assert empty["post_sd"]["a"] == out["post_sd"]["a"]



def test_a_bound_holds_a_posterior_mode_closer_than_1e_4_of_the_span():
    """Bounds [0, 1e4]: 1e-4 of the span is exactly 1, so 1 and 9999 are free and anything closer to a bound
    is held; an infinite or empty span holds nothing."""
    assert 1e-4 * 1e4 == 1.0
    assert not held_by_bound(1.0, 0.0, 1e4) and held_by_bound(0.999, 0.0, 1e4) and held_by_bound(0.0, 0.0, 1e4)
    assert not held_by_bound(9999.0, 0.0, 1e4) and held_by_bound(9999.5, 0.0, 1e4) and held_by_bound(1e4, 0.0, 1e4)
    assert not held_by_bound(5e3, 0.0, 1e4)
    assert not held_by_bound(0.0, 0.0, np.inf) and not held_by_bound(0.0, -np.inf, 0.0)
    assert not held_by_bound(2.0, 2.0, 2.0)
