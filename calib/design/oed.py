"""Optimal experiment design on linearised sensitivities: Fisher information, posterior covariance,
D-optimal and posterior-sd criteria, and an exhaustive search over a finite set of candidate designs.

The model is linearised around the current estimate: a design whose outputs ``y(theta)`` are measured with
independent Gaussian noise of sd ``s`` carries the Fisher information ``F = S^T S / s^2`` with
``S = dy/dtheta``. Under a Gaussian prior of covariance ``P0`` the posterior covariance after the experiment
is ``(P0^-1 + F)^-1`` (Laplace approximation). Nuisance parameters (an initial temperature per replay
segment) enter with a flat prior and are marginalised by taking the sub-block of the inverse.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Precision given to a nuisance parameter (flat prior): small against any information a sample carries.
FLAT_PRECISION = 1e-12


def central_sensitivities(fun, theta, steps) -> np.ndarray:
    """``d fun / d theta`` by central differences: columns in the order of ``theta``.

    Parameters
    ----------
    fun : callable(ndarray) -> ndarray
        The outputs (any shape, flattened) for a parameter vector.
    theta : sequence of float
        Where to linearise.
    steps : sequence of float
        Step per parameter (positive, in its unit).
    """
    theta = np.asarray(theta, float)
    cols = []
    for j, h in enumerate(np.asarray(steps, float)):
        if not h > 0:
            raise ValueError(f"central_sensitivities: step {j} is {h}; steps must be positive")
        up, dn = theta.copy(), theta.copy()
        up[j] += h
        dn[j] -= h
        cols.append((np.ravel(fun(up)) - np.ravel(fun(dn))) / (2.0 * h))
    return np.column_stack(cols)


def fisher(S, noise_sd) -> np.ndarray:
    """Fisher information ``S^T diag(1/s^2) S`` of outputs with sensitivities ``S`` (rows: samples) and
    noise sd ``noise_sd`` (scalar or per row); rows with a non-finite sensitivity carry nothing."""
    S = np.atleast_2d(np.asarray(S, float))
    w = np.broadcast_to(1.0 / np.asarray(noise_sd, float) ** 2, (S.shape[0],))
    ok = np.all(np.isfinite(S), axis=1)
    Sw = S[ok] * np.sqrt(w[ok])[:, None]
    return Sw.T @ Sw


def posterior_cov(prior_cov, F) -> np.ndarray:
    """``(P0^-1 + F)^-1``, computed as ``L (I + L^T F L)^-1 L^T`` with ``P0 = L L^T`` (no inverse of ``P0``:
    stable when the prior is tight in some directions and the data strong in others)."""
    P0 = np.asarray(prior_cov, float)
    ev, V = np.linalg.eigh(0.5 * (P0 + P0.T))
    L = V * np.sqrt(np.maximum(ev, 0.0))
    A = np.eye(P0.shape[0]) + L.T @ np.asarray(F, float) @ L
    return L @ np.linalg.solve(0.5 * (A + A.T), L.T)


def marginal_posterior(prior_cov, F, idx) -> np.ndarray:
    """Posterior covariance of the parameters ``idx`` when the others are marginalised; ``prior_cov`` may
    hold ``inf`` on the diagonal for nuisance parameters (flat prior, :data:`FLAT_PRECISION`)."""
    P0 = np.array(prior_cov, float)
    flat = ~np.isfinite(np.diag(P0))
    prec = np.zeros_like(P0)
    fin = ~flat
    if fin.any():
        prec[np.ix_(fin, fin)] = np.linalg.inv(P0[np.ix_(fin, fin)])
    prec[flat, flat] = FLAT_PRECISION
    post_prec = prec + np.asarray(F, float)
    # scale to unit diagonal before inverting: sensitivities in K per (J/K) and K per K differ by 1e8
    d = np.sqrt(np.maximum(np.diag(post_prec), 1e-300))
    C = np.linalg.pinv(post_prec / np.outer(d, d), hermitian=True) / np.outer(d, d)
    return C[np.ix_(idx, idx)]


def d_criterion(cov) -> float:
    """The D-optimal (Ds for a sub-block) criterion: ``log det`` of the posterior covariance (smaller is
    better: the volume of the confidence ellipsoid)."""
    sign, logdet = np.linalg.slogdet(np.atleast_2d(cov))
    return float(logdet) if sign > 0 else -math.inf


def sd_criterion(cov, sd_now) -> float:
    """Mean over the parameters of (predicted posterior sd / sd now): smaller is better."""
    sd = np.sqrt(np.maximum(np.diag(np.atleast_2d(cov)), 0.0))
    return float(np.mean(sd / np.asarray(sd_now, float)))


CRITERIA = ("d", "sd")


@dataclass
class Scored:
    """One candidate of a search: the design, its criterion value (smaller is better), and what the
    evaluation returned (or why the candidate is infeasible)."""

    design: object
    value: float
    info: object = None
    infeasible: str = ""


def search(candidates, evaluate) -> list[Scored]:
    """Evaluate every candidate and sort by criterion (best first); infeasible ones last.

    ``evaluate(design) -> (value, info)`` or raises :class:`Infeasible` with the reason.
    """
    out = []
    for c in candidates:
        try:
            v, info = evaluate(c)
            out.append(Scored(c, float(v), info))
        except Infeasible as exc:
            out.append(Scored(c, math.inf, None, str(exc)))
    out.sort(key=lambda s: (bool(s.infeasible), s.value))
    return out


class Infeasible(Exception):
    """A candidate design breaks a constraint (car limits, comfort): it is not a plan."""
