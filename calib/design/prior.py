"""What a calibration artifact says the logs left uncertain: the posterior (the plan's prior), the noise
the calibration weighed each channel with, and which parameters are weak."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.errors import ParameterError

#: Parameters a drive plan can target, by the subsystem fit whose output-error replay they enter (the
#: replay's logged channel in brackets): thermal (coolant temperature) and cabin (cabin temperature).
DESIGNABLE = {
    "thermal": ("C_eng_J_per_K", "gamma_exh", "hA_eng_W_per_K", "T_open_degC", "k_rad_W_per_K"),
    "cabin": ("C_cab_J_per_K", "UA_cab_W_per_K", "Q_sun_W"),
}
CHANNEL = {"thermal": "coolant_temp_degC", "cabin": "cabin_temp_degC"}


def subsystem_of(name: str) -> str | None:
    """The subsystem whose replay a designable parameter enters, or None."""
    for sub, names in DESIGNABLE.items():
        if name in names:
            return sub
    return None


@dataclass
class ArtifactPrior:
    """A calibration artifact read as the prior of a drive plan.

    Attributes
    ----------
    params : ParameterSet
        The posterior means (the model the plan is designed on).
    path : str
    sd : dict name -> float
        Posterior sd of each designable scalar parameter (the plan's prior sd).
    prior_sd : dict name -> float
        The calibration's own prior sd (before any log).
    correl : dict (a, b) -> r
        Posterior correlations the artifact kept (it keeps those with ``|r| > 0.9`` only).
    noise : dict subsystem -> (sd, how)
        The noise sd the calibration weighed the subsystem's channel with, and where it comes from.
    """

    params: object
    path: str
    sd: dict
    prior_sd: dict
    correl: dict = field(default_factory=dict)
    noise: dict = field(default_factory=dict)
    fitted: dict = field(default_factory=dict)  # subsystem -> whether its fit ran on some log

    @classmethod
    def load(cls, path) -> "ArtifactPrior":
        """Read a calibration artifact (``iptm calibrate --out``); a parameter file that is not one (no
        ``[calibration]`` section, no posterior sd) is refused with what to do."""
        from calib.fileio import read_config
        from calib.fit.toolkit import T_SENSOR_SD
        from calib.model.params import ParameterSet

        path = Path(path)
        raw = read_config(path, ParameterError, "calibration artifact")
        cal = raw.get("calibration")
        if not isinstance(cal, dict) or not isinstance(cal.get("subsystems"), dict):
            raise ParameterError(f"{path}: not a calibration artifact (no [calibration] section with subsystems): "
                                 "give the file `iptm calibrate --out` wrote")
        params = ParameterSet.load(path)
        sd, psd = {}, {}
        for names in DESIGNABLE.values():
            for n in names:
                p = params.param(n)
                if p.is_table:
                    continue
                s = p.stderr
                if s is None or not isinstance(s, (int, float)) or not math.isfinite(float(s)) or float(s) <= 0:
                    if p.status == "fixed":
                        continue  # held fixed by the calibration: nothing to learn
                    raise ParameterError(f"{path}: parameter {n}: no finite positive posterior sd (stderr); the "
                                         "artifact is incomplete: calibrate again with `iptm calibrate`")
                sd[n] = float(s)
                ps = p.prior_sd
                psd[n] = float(ps) if isinstance(ps, (int, float)) and float(ps) > 0 else float("nan")
        correl, noise, fitted = {}, {}, {}
        for sub in DESIGNABLE:
            d = cal["subsystems"].get(sub, {})
            for key, kind in (("", dict), ("correlations_above_0_9", dict), ("metrics", dict)):
                v = d.get(key) if key and isinstance(d, dict) else d
                if v is not None and not isinstance(v, kind):
                    where = f"[calibration.subsystems.{sub}" + (f".{key}]" if key else "]")
                    raise ParameterError(f"{path}: {where} is not a table: the artifact is damaged; calibrate again "
                                         "with `iptm calibrate`")
            fitted[sub] = bool(d.get("logs"))
            for k, r in (d.get("correlations_above_0_9") or {}).items():
                a, _, b = str(k).partition("|")
                if a in sd and b in sd and isinstance(r, (int, float)) and -1.0 <= r <= 1.0:
                    correl[(a, b)] = float(r)
            s = (d.get("metrics") or {}).get("noise_sd_degC")
            if isinstance(s, (int, float)) and math.isfinite(s) and s > 0:
                noise[sub] = (float(s), "the calibration's fitted noise sd (residual rms inflated for "
                                        "autocorrelation)")
            else:
                noise[sub] = (T_SENSOR_SD, "the calibration's a-priori noise sd (the subsystem was not fitted)")
        return cls(params, str(path), sd, psd, correl, noise, fitted)

    def ratio(self, name) -> float:
        """Posterior sd over prior sd (1: the logs said nothing)."""
        ps = self.prior_sd.get(name, float("nan"))
        return self.sd[name] / ps if ps and math.isfinite(ps) else float("nan")

    def weakest(self, n: int = 2, limit: float | None = None) -> list[str]:
        """The designable parameters whose posterior sd is largest relative to their prior sd: those with
        ratio at least ``limit`` (default ``1 - WEAK_INFORMED``, the calibration's *weak*), at most ``n``;
        when none is weak, the ``n`` largest ratios."""
        from calib.fit.toolkit import WEAK_INFORMED

        limit = 1.0 - WEAK_INFORMED if limit is None else limit
        ranked = sorted((r, k) for k in self.sd if math.isfinite(r := self.ratio(k)))
        ranked.reverse()
        weak = [k for r, k in ranked if r >= limit]
        return (weak or [k for _, k in ranked])[:n]

    def cov(self, names) -> np.ndarray:
        """Prior covariance of ``names``: the posterior sd with the correlations the artifact kept (the rest
        zero); if those few correlations do not form a valid covariance, they are dropped."""
        sd = np.array([self.sd[n] for n in names])
        R = np.eye(len(names))
        for i, a in enumerate(names):
            for j, b in enumerate(names):
                r = self.correl.get((a, b), self.correl.get((b, a)))
                if i != j and r is not None:
                    R[i, j] = r
        if np.linalg.eigvalsh(R).min() <= 1e-9:
            R = np.eye(len(names))
        return R * np.outer(sd, sd)
