"""Driving statistics: a first-order Markov chain of the wheel-power demand, one per ambient band.

The demand of a step is the model's traction power :func:`calib.model.equations.traction_power` of the
speed trace (so the chain speaks the same quantity the controllers see). Demands are put in fixed bins
(:data:`DEFAULT_EDGES_W`, a narrow bin around 0 W for standstill); each bin is represented by the mean
demand of the training samples in it. Transition counts get an additive prior (``alpha``) so that a bin
pair never seen in training keeps a small probability.

Sources are drive cycles (bundled names, CSV, :class:`calib.model.cycles.Cycle`) and ingested drive
logs (:class:`calib.drivelog.DriveLog`, their speed channel; their mean ``ambient_temp_degC`` puts them
in one band). A source without an ambient (a cycle) counts in every band.

:meth:`DemandMarkov.validate` compares the chain with held-out drives: distribution distance, the
probability of staying in a bin, the lag-1 autocorrelation and the log-likelihood per step against an
i.i.d. model of the same bins.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from calib.errors import IptmError

#: Bin edges of the wheel-power demand (W); the outer bins are open.
DEFAULT_EDGES_W = np.array([-20e3, -12e3, -8e3, -5e3, -3e3, -1.5e3, -0.3e3, 0.3e3, 1.5e3, 3e3, 5e3, 7.5e3,
                            10e3, 13e3, 17e3, 22e3, 28e3, 36e3])
#: Ambient bands (degC): upper edges of all bands but the last.
DEFAULT_BANDS_DEGC = (-5.0,)
#: Additive prior on the transition counts, chosen with the SDP's settings on the training drives
#: (``studies/causal_select/causal_select.py``).
DEFAULT_ALPHA = 0.1


def demand_trace(params, source, Ts: float = 1.0):
    """(name, P_trac per step (W), mean ambient or None) of a cycle or drive log."""
    from calib.drivelog import DriveLog
    from calib.model.cycles import load_cycle
    from calib.model.equations import traction_power

    mp = params.model_params() if hasattr(params, "model_params") else params
    amb = None
    if isinstance(source, DriveLog):
        if source.has("ambient_temp_degC"):
            a = source.data["ambient_temp_degC"].to_numpy(float)
            if np.any(np.isfinite(a)):
                amb = float(np.nanmean(a))
    cyc = load_cycle(source, Ts)
    g = cyc.grade if cyc.grade is not None else np.zeros(cyc.n_steps + 1)
    P = np.array([traction_power(mp, cyc.v[k], cyc.v[k + 1], g[k], cyc.Ts) for k in range(cyc.n_steps)])
    return cyc.name, P, amb


def band_of(T_amb: float, bands=DEFAULT_BANDS_DEGC) -> int:
    return int(np.searchsorted(np.asarray(bands, float), T_amb, side="right"))


@dataclass
class DemandMarkov:
    """Markov chains of the binned demand, one per ambient band.

    Attributes
    ----------
    edges_W : ndarray (nb-1,)
        Inner bin edges.
    values_W : ndarray (n_bands, nb)
        Representative demand of each bin (training mean; bin midpoint where a bin is empty).
    P : ndarray (n_bands, nb, nb)
        Row-stochastic transition matrices.
    counts : ndarray (n_bands, nb, nb)
        Raw transition counts.
    bands_degC : tuple
        Upper edges of the ambient bands.
    sources : list of dict
        Which drives built each band.
    """

    edges_W: np.ndarray
    values_W: np.ndarray
    P: np.ndarray
    counts: np.ndarray
    bands_degC: tuple = DEFAULT_BANDS_DEGC
    sources: list = field(default_factory=list)
    alpha: float = DEFAULT_ALPHA

    @property
    def n_bins(self) -> int:
        return self.P.shape[1]

    def bin(self, P_W):
        return np.searchsorted(self.edges_W, np.asarray(P_W, float), side="right")

    def band(self, T_amb: float) -> int:
        return band_of(T_amb, self.bands_degC)

    def chain(self, T_amb: float):
        """(values_W, P) of the band holding ``T_amb``."""
        b = self.band(T_amb)
        return self.values_W[b], self.P[b]

    @classmethod
    def estimate(cls, params, sources, *, edges_W=None, bands_degC=DEFAULT_BANDS_DEGC, alpha: float = DEFAULT_ALPHA,
                 Ts: float = 1.0) -> DemandMarkov:
        """Count transitions of every source (cycle names, CSV paths, Cycles, DriveLogs). The default
        ``alpha`` was chosen with the SDP's settings on the training drives (``studies/causal_select/causal_select.py``)."""
        edges = np.asarray(DEFAULT_EDGES_W if edges_W is None else edges_W, float)
        if np.any(np.diff(edges) <= 0):
            raise IptmError("Markov demand bins: edges must increase strictly")
        nb, n_bands = edges.size + 1, len(bands_degC) + 1
        counts = np.zeros((n_bands, nb, nb))
        sums = np.zeros((n_bands, nb))
        hits = np.zeros((n_bands, nb))
        used = []
        if not sources:
            raise IptmError("Markov demand model: no drives given; name bundled cycles or logs")
        for src in sources:
            name, P, amb = demand_trace(params, src, Ts)
            if P.size < 2:
                raise IptmError(f"Markov demand model: drive {name} is shorter than two steps")
            b = np.searchsorted(edges, P, side="right")
            targets = range(n_bands) if amb is None else [band_of(amb, bands_degC)]
            for bd in targets:
                np.add.at(counts[bd], (b[:-1], b[1:]), 1.0)
                np.add.at(sums[bd], b, P)
                np.add.at(hits[bd], b, 1.0)
            used.append({"name": name, "steps": int(P.size), "ambient_degC": amb,
                         "bands": list(targets)})
        mids = np.concatenate([[edges[0] - 5e3], 0.5 * (edges[1:] + edges[:-1]), [edges[-1] + 8e3]])
        values = np.where(hits > 0, sums / np.maximum(hits, 1), mids[None, :])
        Pm = counts + alpha
        Pm /= Pm.sum(axis=2, keepdims=True)
        return cls(edges, values, Pm, counts, tuple(bands_degC), used, alpha)

    # --- validation ---------------------------------------------------------------------------
    def validate(self, params, sources, T_amb: float | None = None) -> list[dict]:
        """Statistics of each held-out drive against the chain of its band (``T_amb`` overrides)."""
        rows = []
        for src in sources:
            name, P, amb = demand_trace(params, src)
            bd = self.band(T_amb if T_amb is not None else (amb if amb is not None else 0.0))
            Pm = self.P[bd]
            b = self.bin(P)
            nb = self.n_bins
            emp = np.bincount(b, minlength=nb) / b.size
            stat = _stationary(Pm)
            train_marg = self.counts[bd].sum(axis=1)
            train_marg = train_marg / max(train_marg.sum(), 1)
            # transition statistics
            ecount = np.zeros((nb, nb))
            np.add.at(ecount, (b[:-1], b[1:]), 1.0)
            stay_emp = np.trace(ecount) / max(ecount.sum(), 1)
            stay_model = float(np.sum(stat * np.diag(Pm)))
            ll_markov = float(np.mean(np.log(Pm[b[:-1], b[1:]])))
            iid = (train_marg + 1e-3) / (train_marg + 1e-3).sum()
            ll_iid = float(np.mean(np.log(iid[b[1:]])))
            vals = self.values_W[bd]
            x = vals[b]
            rows.append({
                "drive": name, "band": bd, "steps": int(P.size),
                "tv_distance_vs_stationary": 0.5 * float(np.abs(emp - stat).sum()),
                "tv_distance_vs_training": 0.5 * float(np.abs(emp - train_marg).sum()),
                "stay_prob_heldout": float(stay_emp), "stay_prob_model": stay_model,
                "lag1_autocorr_heldout": float(np.corrcoef(x[:-1], x[1:])[0, 1]),
                "lag1_autocorr_model": _lag1_model(Pm, stat, vals),
                "mean_demand_kW_heldout": float(np.mean(P) / 1e3),
                "mean_demand_kW_model": float(stat @ vals / 1e3),
                "loglik_per_step_markov": ll_markov, "loglik_per_step_iid": ll_iid,
            })
        return rows

    # --- storage (no pickle) ------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"edges_W": self.edges_W.tolist(), "values_W": self.values_W.tolist(), "P": self.P.tolist(),
                "counts": self.counts.tolist(), "bands_degC": list(self.bands_degC), "sources": self.sources,
                "alpha": self.alpha}

    @classmethod
    def from_dict(cls, d: dict) -> DemandMarkov:
        try:
            return cls(np.asarray(d["edges_W"], float), np.asarray(d["values_W"], float),
                       np.asarray(d["P"], float), np.asarray(d["counts"], float), tuple(d["bands_degC"]),
                       list(d.get("sources", [])), float(d.get("alpha", DEFAULT_ALPHA)))
        except KeyError as exc:
            raise IptmError(f"Markov demand model: field {exc} missing in the stored model") from None

    def save(self, path) -> None:
        from calib.fileio import write_json

        write_json(path, self.to_dict())

    @classmethod
    def load(cls, path) -> DemandMarkov:
        with open(path) as f:
            return cls.from_dict(json.load(f))


def _stationary(P: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eig(P.T)
    i = int(np.argmin(np.abs(w - 1.0)))
    s = np.abs(np.real(v[:, i]))
    return s / s.sum()


def _lag1_model(P, stat, vals) -> float:
    m = stat @ vals
    var = stat @ (vals - m) ** 2
    cov = np.sum(stat[:, None] * P * np.outer(vals - m, vals - m))
    return float(cov / var) if var > 0 else float("nan")
