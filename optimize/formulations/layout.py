"""Layout of the flat float64 parameter vector the compiled HEV transition and fused kernels read.

numba's parallel kernels cannot take the ``ModelParams`` namedtuple (a struct holding arrays), so the
model scalars, the grid configuration and the tables travel as one vector; this module owns its layout.
Every slot is numbered by code, none by hand: the model scalars are :data:`calib.model.params.SCALAR_FIELDS`,
in the order of the table that ties each compiled name to its parameter (:data:`calib.model.params.COMPILED`)."""
from __future__ import annotations

import numpy as np
from numba import njit

from calib.model.params import SCALAR_FIELDS


# ---------------------------------------------------------------------------------------------------
# compiled transition
# ---------------------------------------------------------------------------------------------------
#: The grid and scenario configuration (solve.py writes it; ``cab_rel`` 1.0: the cabin state is the temperature
#: above the step's comfort bound, w_k[3] at k, w_k[2] at k+1).
CFG = ("nx", "nq", "T_amb", "Ts", "T_bat", "W_bl", "soc_lo", "soc_hi", "soc_step", "T_cl_lo", "T_cl_hi", "T_cl_step",
       "T_cab_hi", "T_cab_step", "penalty", "cab_rel")
#: The arrays after the header, each with an (offset, length) descriptor in the header.
ARRAYS = ("socg", "fclg", "lossg", "soc_bp", "U_oc", "soc_bp_R", "R_int", "T_fcl", "f_cl", "big")
#: The model scalars: every number of the compiled model (:class:`calib.model.params.ModelParams`).
_MS = SCALAR_FIELDS
#: The heater range and the "hold the bound" switch.
HEATER = ("Q_lo", "Q_hi", "hold")

#: Slot of each name in the flat vector: configuration (``cfg:NAME``), array descriptors (``array:NAME``), model
#: scalars, heater, in that order.
SLOT = {}
for _n in CFG:
    SLOT["cfg:" + _n] = len(SLOT)
_A0 = len(SLOT)
for _n in ARRAYS:
    SLOT["array:" + _n] = _A0 + 2 * ARRAYS.index(_n)
_MS0 = _A0 + 2 * len(ARRAYS)
#: Offset of each model scalar from :data:`_MS0` (the kernels read ``P[_MS0 + offset]``).
MS_OFFSET = {n: i for i, n in enumerate(_MS)}
for _n in _MS:
    SLOT[_n] = _MS0 + MS_OFFSET[_n]
for _i, _n in enumerate(HEATER):
    SLOT[_n] = _MS0 + len(_MS) + _i
_HEADER = _MS0 + len(_MS) + len(HEATER)
assert len(set(SLOT.values())) == len(SLOT) == len(CFG) + len(ARRAYS) + len(_MS) + len(HEATER), "a slot named twice"

# the kernels' names for the slots (module-level integers: numba folds them as constants)
(_C_NX, _C_NQ, _C_TAMB, _C_TS, _C_TBAT, _C_WBL, _C_SLO, _C_SHI, _C_SH, _C_TLO, _C_THI, _C_TH, _C_CHI, _C_CH, _C_PEN,
 _C_CREL) = (SLOT["cfg:" + n] for n in CFG)
_A_SOCG, _A_FCLG, _A_LOSSG, _A_SOCBP, _A_UOC, _A_SOCBPR, _A_RINT, _A_TFCL, _A_FCL, _A_BIG = (SLOT["array:" + n]
                                                                                           for n in ARRAYS)
(_R_TC, _TBREF, _CBAT, _KAPPA, _HA, _TOPEN, _KRAD, _QRADMAX, _EPS, _CP, _RECIRC, _LHV, _GAMMA, _CENG, _UACAB,
 _CCAB, _QSUN, _UHYST) = (MS_OFFSET[n] for n in ("R_tc", "T_bat_ref", "C_bat_As", "kappa", "hA_eng", "T_open", "k_rad",
                                                 "Q_rad_max", "eps_hc", "cp_air", "recirc", "LHV", "gamma_exh", "C_eng",
                                                 "UA_cab", "C_cab", "Q_sun", "U_hyst"))
_C_QLO, _C_QHI, _C_HOLD = (SLOT[n] for n in HEATER)

#: Penalty (g of fuel) per grid step of state-constraint violation (see :func:`hev_transition`), also the
#: Thermal-Cabin terminal cost per grid step below the 1500-W final cabin temperature.
PENALTY_G_PER_STEP = 1000.0
#: Level-set tolerance (grid steps): signed levels at or below it count as "terminal set reachable".
LEVEL_TOL = 0.0
#: Heater command of the "hold the bound" control (a control row's Q_heat): the heat that puts the next cabin
#: temperature on the next step's comfort bound, clipped to the heater grid's ends
#: (:func:`optimize.formulations.transition.hold_heat`).
HOLD = float("nan")
# tab columns per power control
_T_OK, _T_PE, _T_WF, _T_PBAT, _T_SOC0 = 0, 1, 2, 3, 4



@njit(inline="always", cache=True)
def _arr(p, a):
    o = int(p[a])
    return p[o: o + int(p[a + 1])]


def pack_params(cfg, ms, arrays) -> np.ndarray:
    """One flat float64 vector: header (cfg, descriptors, model scalars) then the arrays.

    A flat array (rather than a tuple holding the ModelParams namedtuple) because numba's parallel
    backward kernel rejects a struct with arrays as a prange argument, and because a tuple of arrays
    costs reference-count traffic on every transition call. An entry given as a shape tuple reserves
    zeros of that shape, to be filled in place (:func:`packed_array`)."""
    if cfg.size != len(CFG) or ms.size != len(_MS) or len(arrays) != len(ARRAYS):
        raise ValueError(f"pack_params: {len(CFG)} configuration values, {len(_MS)} model scalars and "
                         f"{len(ARRAYS)} arrays expected; got {cfg.size}, {ms.size} and {len(arrays)}")
    sizes = [int(np.prod(a)) if isinstance(a, tuple) else a.size for a in arrays]
    P = np.zeros(_HEADER + sum(sizes))
    P[: cfg.size] = cfg
    P[_MS0: _MS0 + ms.size] = ms
    o = _HEADER
    for name, a, n in zip(ARRAYS, arrays, sizes, strict=True):
        P[SLOT["array:" + name]] = o
        P[SLOT["array:" + name] + 1] = n
        if not isinstance(a, tuple):
            P[o: o + n] = a.ravel()
        o += n
    return P


def packed_array(P, name: str, shape) -> np.ndarray:
    """The array ``name`` (one of :data:`ARRAYS`) of a packed vector as a writable view of ``shape``."""
    j = SLOT["array:" + name]
    o, n = int(P[j]), int(P[j + 1])
    return P[o: o + n].reshape(shape)


