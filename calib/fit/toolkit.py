"""Identification toolkit shared by the subsystem fitters: result types, the maximum a posteriori fit
(lmfit, prior as extra residuals), effective sample size. The method is described in
:mod:`calib.fit.driver`."""
import math
from dataclasses import dataclass, field

import numpy as np

#: Calibration uncertainty (1 sd, relative) of logged inputs of the output-error fits: heater power,
#: fuel rate, engine power (speed x torque, resampled to 1 s bins). Propagated into the standard errors.
INPUT_REL_SD = 0.01
#: Calibration uncertainty (1 sd, an offset) of a temperature sensor, degC; propagated like INPUT_REL_SD.
T_SENSOR_SD = 0.5
MIN_SAMPLES = 60


# ------------------------------------------------------------------------------------------------
# result types shared by the fitters
# ------------------------------------------------------------------------------------------------
@dataclass
class ParamEstimate:
    """Outcome for one parameter (scalar or table).

    ``value`` is the posterior (maximum a posteriori), ``stderr`` its sd, ``prior``/``prior_sd`` the prior,
    ``informed`` how much the data narrowed it. ``status`` is ``estimated``, ``weak`` (informed below
    :data:`WEAK_INFORMED`: mostly the prior), ``fixed`` or ``prior`` (the fit could not run). For tables
    these are lists and ``entry_status`` gives each entry's status.
    """

    name: str
    value: object
    stderr: object
    status: str
    note: str = ""
    prior: object = None
    entry_status: list | None = None
    prior_sd: object = None
    informed: object = None


@dataclass
class SubsystemFit:
    """Result of one subsystem fitter."""

    subsystem: str
    needs: tuple
    estimates: dict = field(default_factory=dict)
    correlations: dict = field(default_factory=dict)  # "a|b" -> r (fitted pairs)
    conf_intervals: dict = field(default_factory=dict)  # name -> {"1sigma": [lo, hi], ...}
    metrics: dict = field(default_factory=dict)
    logs: list = field(default_factory=list)
    skipped: dict = field(default_factory=dict)  # log label -> why not used
    message: str = ""  # why nothing was fitted
    nuisance: dict = field(default_factory=dict)  # per-log initial states etc.
    used: dict = field(default_factory=dict)  # log label -> what the fit used (logged or inferred inputs)
    confounded: list = field(default_factory=list)  # [(a, b, r)] posterior |r| > CONFOUNDED
    advice: list = field(default_factory=list)  # what drive would inform what the data did not

    @property
    def fitted(self) -> bool:
        """Whether any parameter of this subsystem was fitted (not all held at prior or fixed)."""
        return any(e.status in ("estimated", "weak") for e in self.estimates.values()) and bool(self.logs)


def usable_logs(logs, needs, subsystem, any_of=()):
    """Split logs into those with every channel of ``needs`` and a dict label -> missing-channel reason.

    ``any_of``: alternative channel groups of which a log needs at least one, e.g.
    ``(("heater_power_W",), ("vent_temp_degC", "blower_flow_kg_per_s"))``.
    """
    use, skipped = [], {}
    for lg in logs:
        miss = lg.missing(needs)
        if any_of and not any(lg.has(*group) for group in any_of):
            first, *rest = [" + ".join(g) for g in any_of]
            miss.append(first + "".join(f" (or {r})" for r in rest))
        if miss:
            skipped[lg.label()] = f"missing channel(s) {', '.join(miss)}"
        else:
            use.append(lg)
    return use, skipped


def output_error_params(names, bounds, prior, data):
    """``make_params(vary)`` for an output-error fit: the physical parameters ``names`` (bounded, at their
    prior, varied when in ``vary``) plus each log's initial temperature ``d["name"]`` (always fitted,
    within 5 K of its first measured value ``d["T0"]``)."""
    import lmfit

    def make_params(vary):
        ps = lmfit.Parameters()
        for n in names:
            lo, hi = bounds[n]
            ps.add(n, value=prior[n], min=lo, max=hi, vary=n in vary)
        for d in data:
            ps.add(d["name"], value=d["T0"], min=d["T0"] - 5.0, max=d["T0"] + 5.0, vary=True)
        return ps

    return make_params


def not_fitted(fit: SubsystemFit, base, names, reason):
    """Mark ``names`` as not attempted (status prior) with ``reason``."""
    fit.message = reason
    for n in names:
        p = base.param(n)
        from calib.model.params import prior_sd_of

        sd = prior_sd_of(p)
        fit.estimates[n] = ParamEstimate(n, p.value, sd, "prior", f"not fitted: {reason}", prior=p.value,
                                         prior_sd=sd, informed=[0.0] * len(p.value) if p.is_table else 0.0)
    return fit


# ------------------------------------------------------------------------------------------------
# statistics helpers
# ------------------------------------------------------------------------------------------------
def neff(residual_segments) -> tuple[int, float]:
    """(n, n_eff) over per-log residual arrays (of at least 3 finite samples); n_eff is at least 1.

    ``n_eff = n / tau`` per log with ``tau`` the largest of: the integrated autocorrelation time
    ``1 + 2 sum_k rho_k`` (summed until the autocorrelation first drops below 0.05, at most n/5 lags), the
    batch-means estimate ``B var(block means) / var(residual)`` with blocks of ``B = max(20, sqrt(n))``
    samples (sensitive to slow drifts), and the AR(1) value ``(1 + rho_1) / (1 - rho_1)``.
    """
    n_tot, n_eff = 0, 0.0
    for r in residual_segments:
        r = np.asarray(r, float)
        r = r[np.isfinite(r)]
        if r.size < 3:
            continue
        r0 = r - r.mean()
        m = r0.size
        nfft = 1 << (2 * m - 1).bit_length()
        fr = np.fft.rfft(r0, nfft)
        ac = np.fft.irfft(fr * np.conj(fr), nfft)[:m]
        if ac[0] <= 0:
            continue
        rho = ac / ac[0]
        kmax = max(2, m // 5)
        below = np.flatnonzero(rho[1:kmax] < 0.05)
        K = int(below[0]) + 1 if below.size else kmax
        tau = 1.0 + 2.0 * float(np.sum(rho[1:K]))
        r1 = min(max(float(rho[1]), 0.0), 0.995)
        # batch means (blocks of ~sqrt(n) samples) catch slow drifts that carry little variance
        B = max(20, int(math.sqrt(m)))
        nb = m // B
        if nb >= 4:
            bm = r0[: nb * B].reshape(nb, B).mean(axis=1)
            tau_bm = B * float(np.var(bm)) / (ac[0] / m)
        else:
            tau_bm = 1.0
        tau = max(tau, tau_bm, (1.0 + r1) / (1.0 - r1), 1.0)
        n_tot += m
        n_eff += m / tau
    return n_tot, max(n_eff, 1.0)


def inflation(residual_segments, nvarys=0) -> float:
    """Factor on standard errors for correlated residuals: sqrt((n - p) / (n_eff - p)), >= 1."""
    n, ne = neff(residual_segments)
    if n == 0:
        return 1.0
    return float(math.sqrt(max(n - nvarys, 1) / max(ne - nvarys, 1.0)))


# ------------------------------------------------------------------------------------------------
# maximum a posteriori estimation
# ------------------------------------------------------------------------------------------------
#: A parameter whose posterior sd is not at least this fraction below its prior sd is *weakly informed*
#: by the data: its value is still the posterior (mostly the prior), flagged ``weak``.
WEAK_INFORMED = 0.3
#: Posterior correlation above which two parameters are reported as confounded (the data determine a
#: combination of them better than each one).
CONFOUNDED = 0.9


def prior_residual(values, prior, prior_sd):
    """The prior penalty as residuals ``(p - prior) / prior_sd`` (their squares sum to -2 log prior)."""
    return np.array([(values[n] - prior[n]) / prior_sd[n] for n in prior], float)


def map_fit(make_params, data_segments, cand, *, prior, prior_sd, noise_sd, extra=None, perturbed=(),
            floor=None, loss="linear", max_tau=None, starts=(), jac=None, trf=False):
    """Maximum a posteriori fit with lmfit: data misfit plus prior penalty.

    The objective is ``sum (r_data / s)^2 + sum ((p - prior) / prior_sd)^2 (+ extra^2)``: the data residuals
    are divided by their noise sd ``s`` so that both terms are in units of standard deviations. ``s`` is
    first ``noise_sd`` (a priori, e.g. the sensor's noise), then re-estimated from the fit's residuals as
    ``rms * sqrt(n / n_eff)``: autocorrelated residuals (a slow model-structure error) carry fewer
    independent samples, and dividing by the inflated sd gives the data exactly the weight of ``n_eff``
    independent samples. The fit is repeated once with that ``s``.

    Parameters
    ----------
    make_params : callable() -> lmfit.Parameters
        Every parameter of ``cand`` (at its prior, bounded) plus nuisance parameters (initial states),
        all varied.
    data_segments : callable(params) -> list of ndarray
        Per-log data residuals (model - measured) in the channel's unit.
    cand : list of str
        The model parameters reported (values, posterior sd, correlations).
    prior, prior_sd : dict name -> float
        Gaussian prior of the parameters that have one directly (others, e.g. increments of a table,
        get theirs through ``extra``).
    extra : callable(params) -> ndarray, optional
        Further prior residuals (e.g. smoothness of a table), already in sd units.
    perturbed : sequence of callable(params) -> list of ndarray, or of pairs of them
        Data residuals with one logged input moved by one sd of its calibration uncertainty; the
        linearised shift of the MAP estimate is added in quadrature to the posterior sd (none if it gives no
        residuals). A pair ``(up, down)`` moves the input both ways and takes half the difference (a central
        difference: for a replay that is not affine in the input, the shift without its second-order
        part).
    floor : float, optional
        Smallest ``s`` (the resolution of the measurement).
    max_tau : float, optional
        Cap on the autocorrelation time used for ``s`` (for residuals that are not a time series, such as
        selected operating points, where slow drifts of the selection are not lost information).
    starts : sequence of dict name -> float
        Further starting points (values of some parameters; the others as ``make_params`` gives them): the
        first minimisation runs from each, and the one with the lowest objective is carried on (a
        posterior with more than one mode, e.g. a level traded against a table's far end); on a tie the
        earliest, ``make_params``'s own start first.
    loss : str
        ``linear`` (least squares) or a robust loss of scipy's ``least_squares`` (``soft_l1``, residuals
        beyond 3 sd weigh less): for a first look that finds outliers; the posterior sd assume squares.
    jac : callable(params) -> (ndarray, ndarray), optional
        The analytic Jacobians of the concatenated ``data_segments`` (unscaled) and of ``extra``, columns
        in the order of the varied parameters. Given, each minimisation is scipy's trust-region reflective
        ``least_squares`` with the bounds held as bounds: Levenberg-Marquardt's transform of a bounded
        parameter flattens the objective next to its bound (an increment at 0), where it then crawls
        through thousands of finite-difference Jacobians. The posterior covariance is computed as without.
    trf : bool
        The trust-region reflective minimiser (bounds held as bounds) with a finite-difference Jacobian, for
        a fit without an analytic one whose parameters sit at or near their bounds.

    Returns
    -------
    dict: ``values``, ``post_sd``, ``prior_sd``, ``informed`` (``1 - post_sd / sd under the prior alone``,
    the latter including the couplings of ``extra``), ``correl``
    ("a|b" -> r over ``cand``), ``params`` (lmfit Parameters at the MAP, nuisance included), ``noise_sd``,
    ``rmse``, ``n``, ``n_eff``, ``at_bound`` {name: text}. A parameter that neither the data nor a prior
    constrains has ``post_sd`` inf, ``informed`` 0 and no correlation.
    """
    from threadpoolctl import threadpool_limits

    # the matrices here are small (bins x parameters): a threaded BLAS only adds its hand-off, and on a
    # busy machine its threads wait on each other (an SVD of 1300 x 19 took 0.1 s on 2 threads, 2 ms on 1)
    with threadpool_limits(1, user_api="blas"):
        return _map_fit(make_params, data_segments, cand, prior=prior, prior_sd=prior_sd, noise_sd=noise_sd,
                        extra=extra, perturbed=perturbed, floor=floor, loss=loss, max_tau=max_tau, starts=starts,
                        jac=jac, trf=trf)


def _map_fit(make_params, data_segments, cand, *, prior, prior_sd, noise_sd, extra, perturbed, floor, loss, max_tau,
             starts, jac, trf):
    import lmfit

    extra = extra or (lambda ps: np.zeros(0))

    def total(ps, s):
        segs = data_segments(ps)
        r = np.concatenate(segs) / s if segs else np.zeros(0)
        v = ps.valuesdict()
        return np.concatenate([r, prior_residual(v, prior, prior_sd), extra(ps)])

    def jacobian(ps, s):
        jd, je = jac(ps)
        names = [k for k in ps if ps[k].vary]
        jp = np.zeros((len(prior), len(names)))
        for i, k in enumerate(prior):
            jp[i, names.index(k)] = 1.0 / prior_sd[k]
        return np.vstack([jd / s, jp, je.reshape(-1, len(names))])

    def minimise(ps, s):
        mini = lmfit.Minimizer(total, ps, fcn_args=(s,))
        if jac is not None and loss == "linear":
            return mini.minimize(method="least_squares", jac=jacobian)
        if trf and loss == "linear":
            return mini.minimize(method="least_squares")
        if loss == "linear":
            return mini.minimize(method="leastsq")
        # robust first look (outliers weigh less); the caller drops them and refits with squares
        return mini.minimize(method="least_squares", loss=loss, f_scale=3.0)

    def cost(ps, s):
        r = total(ps, s)
        return float(np.sum(r[np.isfinite(r)] ** 2))

    s = float(noise_sd)
    params = make_params()
    res = None
    for it in range(2):
        res = minimise(params, s)
        if it == 0 and starts:
            best = cost(res.params, s)
            for st in starts:
                p1 = make_params()
                for k, v in st.items():
                    p1[k].set(value=float(np.clip(v, p1[k].min, p1[k].max)))
                r1 = minimise(p1, s)
                c1 = cost(r1.params, s)
                if c1 < best:
                    res, best = r1, c1
        params = res.params
        segs = data_segments(params)
        n, ne = neff(segs)
        allr = np.concatenate(segs) if segs else np.zeros(0)
        allr = allr[np.isfinite(allr)]
        rms = float(np.sqrt(np.mean(allr ** 2))) if allr.size else s
        tau = max(n, 1) / max(ne, 1.0)
        if max_tau is not None:
            tau = min(tau, max_tau)
        s_new = max(rms * math.sqrt(tau), floor or 0.0, 1e-12)
        if abs(s_new / s - 1.0) < 0.05:
            s = s_new
            break
        s = s_new
    # posterior covariance: Gauss-Newton (J^T J)^-1 of the scaled objective at the MAP, by forward differences
    names = [k for k in params if params[k].vary]
    x0 = np.array([params[k].value for k in names])
    r0 = total(params, s)
    J = np.empty((r0.size, len(names)))
    # each parameter's scale (its prior sd): the normal matrix is inverted in these units, where a
    # prior-only parameter's tiny precision is not cut off as numerical noise by pinv's cutoff
    D = np.array([prior_sd[k] if k in prior_sd else max(abs(x0[j]), 1e-3) * 1e-1 + 1e-3 for j, k in enumerate(names)])
    for j, k in enumerate(names):
        h = 1e-3 * D[j]
        p1 = params.copy()
        p1[k].set(value=x0[j] + h, min=-np.inf, max=np.inf)
        J[:, j] = (total(p1, s) - r0) / h
    # pseudo-inverse of the normal matrix from its eigenvectors (pinv's cutoff, 1e-15 of the largest); a
    # direction below the cutoff is one no residual constrains (no data, no prior), where the inverse
    # would read variance 0: a parameter with a share in it is not known at all, its sd is infinite
    ev, evec = np.linalg.eigh((J * D).T @ (J * D))
    ok = ev > 1e-15 * max(float(ev.max(initial=0.0)), 1e-300)
    cov0 = D[:, None] * ((evec[:, ok] / ev[ok]) @ evec[:, ok].T) * D[None, :]
    unconstrained = np.any(np.abs(evec[:, ~ok]) > 1e-6, axis=1)
    cov = cov0.copy()
    idx = {k: j for j, k in enumerate(names)}
    # calibration uncertainty of the inputs: linearised shift of the estimate, added (as a rank-one
    # covariance term, so that functions of several parameters get it too)
    nd = sum(x.size for x in segs)

    def moved(rfun):
        segs1 = rfun(params)
        return np.concatenate([np.concatenate(segs1) / s, r0[nd:]]) - r0 if segs1 else None

    for rfun in perturbed:
        if isinstance(rfun, tuple):
            up, down = moved(rfun[0]), moved(rfun[1])
            d = 0.5 * (up - down) if up is not None and down is not None else None
        else:
            d = moved(rfun)
        if d is None or d.size != r0.size:
            continue
        dx = -cov0 @ (J.T @ d)
        cov += np.outer(dx, dx)
    var = {k: math.inf if unconstrained[idx[k]] else max(float(cov[idx[k], idx[k]]), 0.0) for k in cand}
    values = {k: float(params[k].value) for k in cand}
    post = {k: math.sqrt(var[k]) for k in cand}
    # what the prior alone (its own sd plus the couplings of `extra`, e.g. smoothness) gives: the data
    # informed a parameter only as far as its posterior sd is below *that*
    ci = [idx[k] for k in cand]
    Jp = J[nd:][:, ci] * D[ci]
    prior_cov = D[ci][:, None] * np.linalg.pinv(Jp.T @ Jp) * D[ci][None, :]
    ref = {k: math.sqrt(max(float(prior_cov[i, i]), 0.0)) for i, k in enumerate(cand)}
    informed = {k: float(max(0.0, 1.0 - post[k] / ref[k])) if ref[k] > 0 else 0.0 for k in cand}
    correl = {}
    for i, a in enumerate(cand):
        for b in cand[i + 1:]:
            den = math.sqrt(var[a] * var[b])
            if 0.0 < den < math.inf:
                correl[f"{a}|{b}"] = float(cov[idx[a], idx[b]] / den)
    at_bound = {}
    for k in cand:
        lo, hi = params[k].min, params[k].max
        if held_by_bound(values[k], lo, hi):
            at_bound[k] = f"posterior mode {values[k]:.6g} at its bound [{lo:g}, {hi:g}]"
    n, ne = neff(data_segments(params))
    return {"values": values, "post_sd": post, "prior_sd": {k: float(prior_sd[k]) for k in cand if k in prior_sd},
            "informed": informed, "correl": correl, "params": params, "noise_sd": s,
            "rmse": rms, "n": n, "n_eff": float(ne), "at_bound": at_bound, "cov": cov, "cov_names": names,
            "prior_cov": prior_cov}


def held_by_bound(value, lo, hi) -> bool:
    """Whether a posterior mode lies less than 1e-4 of its bounds' span from either bound (the bound holds
    it; an infinite or empty span holds nothing)."""
    span = hi - lo
    return bool(np.isfinite(span) and span > 0 and (value - lo < 1e-4 * span or hi - value < 1e-4 * span))


def posterior_estimate(name, out, note, prior_value):
    """A :class:`ParamEstimate` from a :func:`map_fit` result: the posterior, flagged ``weak`` when the
    data narrowed the prior by less than :data:`WEAK_INFORMED`."""
    inf = out["informed"][name]
    st = "estimated" if inf >= WEAK_INFORMED else "weak"
    txt = f"data informed {100 * inf:.0f} % (prior sd {out['prior_sd'][name]:.3g}, posterior sd {out['post_sd'][name]:.3g})"
    shift = (out["values"][name] - prior_value) / out["prior_sd"][name] if out["prior_sd"][name] > 0 else 0.0
    if abs(shift) >= 0.5:
        txt += f"; moved {shift:+.1f} prior sd from the prior"
    if st == "weak":
        txt += ("; weakly informed: the value is mostly the prior" if abs(shift) < 1.0 else
                "; weakly informed: the data moved it, but its sd is still close to the prior's")
    if name in out.get("at_bound", {}):
        txt += "; " + out["at_bound"][name]
    return ParamEstimate(name, out["values"][name], out["post_sd"][name], st, f"{note}; {txt}" if note else txt,
                         prior=prior_value, prior_sd=out["prior_sd"][name], informed=inf)


def prior_only(name, prior_value, prior_sd, why, status="weak"):
    """Estimate of a parameter no data reaches: the prior, with the prior sd (status ``weak``, or ``prior``
    when the fit could not run for lack of channels)."""
    return ParamEstimate(name, prior_value, prior_sd, status, f"{why}; the value and sd are the prior's",
                         prior=prior_value, prior_sd=prior_sd, informed=0.0)


def confounded_pairs(correl, limit=CONFOUNDED):
    """[(a, b, r)] with ``|r| > limit``, strongest first."""
    out = []
    for k, r in correl.items():
        if abs(r) > limit:
            a, b = k.split("|")
            out.append((a, b, float(r)))
    return sorted(out, key=lambda t: -abs(t[2]))


def combine_with_prior(name, est, se, prior_value, prior_sd, note, bounds=None):
    """Posterior of a parameter estimated in closed form (a linear regression with standard error ``se``)
    under its Gaussian prior: precision-weighted mean, ``1/post^2 = 1/se^2 + 1/prior_sd^2``. With ``bounds``
    (the parameter's physical limits) a mean beyond them is held at the bound, and the note says so: the
    data then disagree with the model, which the reader must know."""
    if se is None or not np.isfinite(se) or se <= 0 or not np.isfinite(est):
        return prior_only(name, prior_value, prior_sd, note + "; the data gave no usable estimate")
    w1, w0 = 1.0 / se ** 2, 1.0 / prior_sd ** 2
    v = (w1 * est + w0 * prior_value) / (w1 + w0)
    post = math.sqrt(1.0 / (w1 + w0))
    at_bound = {}
    if bounds is not None and not bounds[0] <= v <= bounds[1]:
        lo, hi = bounds
        at_bound[name] = (f"the data put it at {v:.4g} (estimate {est:.4g} +- {se:.2g}), beyond its physical bounds "
                          f"[{lo:g}, {hi:g}]: held at the bound; the log disagrees with the model here")
        v = float(min(max(v, lo), hi))
    out = {"values": {name: v}, "post_sd": {name: post}, "prior_sd": {name: prior_sd},
           "informed": {name: max(0.0, 1.0 - post / prior_sd)}, "at_bound": at_bound}
    return posterior_estimate(name, out, note, prior_value)
