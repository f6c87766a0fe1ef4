"""A DP outcome saved as a result folder of kind ``dp-outcome`` (docs/results.md).

``result.json`` holds the figures (costs, timings, sizes, grids, scenario, the formulation's extra figures),
``arrays.npz`` the DP trajectory (``dp__x``, ``dp__u``...) and the extra figures that are arrays
(``extra__NAME``), ``sim/`` the re-simulated drive and ``on_thermal/`` Baseline-DP's controls on the thermal
model (both of kind ``simulation``). The value functions are large (a float per state and step) and are
kept only when asked for (``value_functions=True``); without them the loaded ``dp.V``, ``dp.L`` and
``dp.policy`` are None.
"""
from __future__ import annotations

import numpy as np

from calib.errors import ResultFileError
from calib.results import need, read_parts, save_result, write_parts

KIND = "dp-outcome"
_FIGURES = ("formulation", "dp_cost", "predicted_cost", "t_backward", "t_forward", "t_total", "n_evaluations",
            "n_states", "n_controls", "peak_rss_mb", "grids", "scenario")
_DP_FIGURES = ("terminal_cost", "cost", "feasible", "terminal_level", "steps_completed", "t_backward", "t_forward",
               "n_evaluations", "kernel")
_DP_ARRAYS = ("t", "x", "u", "u_index", "stage_cost", "predicted_cost")
_DP_LARGE = ("V", "L", "policy")


def save_outcome(o, path, value_functions: bool = False):
    """Save a :class:`optimize.formulations.solve.DPOutcome` at ``path``, atomically; returns the path."""

    def fill(folder):
        extra = {k: v for k, v in o.extra.items() if not isinstance(v, np.ndarray)}
        arrays = {f"extra__{k}": v for k, v in o.extra.items() if isinstance(v, np.ndarray)}
        arrays.update({f"dp__{k}": getattr(o.dp, k) for k in _DP_ARRAYS})
        for k in _DP_LARGE if value_functions else ():
            if getattr(o.dp, k) is not None:
                arrays[f"dp__{k}"] = getattr(o.dp, k)
        if o.T_cab_lb is not None:
            arrays["T_cab_lb"] = o.T_cab_lb
        meta = {k: getattr(o, k) for k in _FIGURES}
        meta.update(dp={k: getattr(o.dp, k) for k in _DP_FIGURES}, extra=extra, extra_order=list(o.extra),
                    value_functions=bool(value_functions), on_thermal=o.on_thermal is not None)
        write_parts(folder, KIND, meta, arrays)
        o.sim.write_into(folder / "sim")
        if o.on_thermal is not None:
            o.on_thermal.write_into(folder / "on_thermal")

    return save_result(path, fill)


def load_outcome(path, outcome_cls):
    """Read a folder written by :func:`save_outcome` as an ``outcome_cls`` (:class:`DPOutcome`, passed in: this
    module is imported by solve.py); a ResultFileError where it is not one."""
    from calib.model.simulate import SimResult
    from optimize.dp.engine import DPResult

    doc, arrays, path = read_parts(path, KIND)
    try:
        dpf = need(doc, "dp", path)
        dp = DPResult(**{k: arrays[f"dp__{k}"] for k in _DP_ARRAYS}, **{k: dpf[k] for k in _DP_FIGURES},
                      **{k: arrays.get(f"dp__{k}") for k in _DP_LARGE})
        extra = dict(need(doc, "extra", path))
        extra.update({k[7:]: v for k, v in arrays.items() if k.startswith("extra__")})
        order = [k for k in doc.get("extra_order", []) if k in extra]
        extra = {k: extra[k] for k in order + [k for k in extra if k not in order]}
    except KeyError as exc:
        raise ResultFileError(f"{path}: {exc.args[0]!r} is missing") from None
    return outcome_cls(**{k: need(doc, k, path) for k in _FIGURES}, sim=SimResult.load(path / "sim"), dp=dp,
                     on_thermal=SimResult.load(path / "on_thermal") if doc.get("on_thermal") else None, extra=extra,
                     T_cab_lb=arrays.get("T_cab_lb"))
