"""Layout of the flat float64 parameter vector the compiled HEV transition and fused kernels read.

numba's parallel kernels cannot take the ``ModelParams`` namedtuple (a struct holding arrays), so the
model scalars, the grid configuration and the tables travel as one vector; this module owns its layout."""
from __future__ import annotations

import numpy as np
from numba import njit


# ---------------------------------------------------------------------------------------------------
# compiled transition
# ---------------------------------------------------------------------------------------------------
# cfg layout (float64 array in the params tuple)
_C_NX, _C_NQ, _C_TAMB, _C_TS, _C_TBAT, _C_WBL = 0, 1, 2, 3, 4, 5
_C_SLO, _C_SHI, _C_SH, _C_TLO, _C_THI, _C_TH, _C_CHI, _C_CH, _C_PEN = 6, 7, 8, 9, 10, 11, 12, 13, 14
# 1.0: the cabin state is the temperature above the step's comfort bound (w_k[3] at k, w_k[2] at k+1)
_C_CREL = 15

# array descriptors (offset, length) in the flat parameter vector, then the model scalars
_A_SOCG, _A_FCLG, _A_LOSSG, _A_SOCBP, _A_UOC, _A_SOCBPR, _A_RINT, _A_TFCL, _A_FCL, _A_BIG = range(16, 36, 2)
_MS0 = 40
_HEADER = 64

#: Penalty (g of fuel) per grid step of state-constraint violation (see :func:`hev_transition`), also the
#: Thermal-Cabin terminal cost per grid step below the 1500-W final cabin temperature.
PENALTY_G_PER_STEP = 1000.0
#: Level-set tolerance (grid steps): signed levels at or below it count as "terminal set reachable".
LEVEL_TOL = 0.0
# model scalars (float64 array): the generic engine's parallel kernel cannot take the ModelParams namedtuple
# (numba's parfor gufunc rejects a struct holding arrays), so the transition gets plain arrays.
_MS = ("R_tc", "T_bat_ref", "C_bat_As", "kappa", "hA_eng", "T_open", "k_rad", "Q_rad_max", "eps_hc", "cp_air",
       "recirc", "LHV", "gamma_exh", "C_eng", "UA_cab", "C_cab", "Q_sun", "U_hyst")
(_R_TC, _TBREF, _CBAT, _KAPPA, _HA, _TOPEN, _KRAD, _QRADMAX, _EPS, _CP, _RECIRC, _LHV, _GAMMA, _CENG, _UACAB,
 _CCAB, _QSUN, _UHYST) = range(len(_MS))
# heater range and the "hold the bound" switch (after the model scalars, inside the header)
_C_QLO, _C_QHI, _C_HOLD = 58, 59, 60
assert _MS0 + len(_MS) <= _C_QLO and _C_HOLD < _HEADER
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
    sizes = [int(np.prod(a)) if isinstance(a, tuple) else a.size for a in arrays]
    P = np.zeros(_HEADER + sum(sizes))
    P[: cfg.size] = cfg
    P[_MS0: _MS0 + ms.size] = ms
    o = _HEADER
    for j, (a, n) in enumerate(zip(arrays, sizes)):
        P[16 + 2 * j] = o
        P[17 + 2 * j] = n
        if not isinstance(a, tuple):
            P[o: o + n] = a.ravel()
        o += n
    return P


def packed_array(P, j: int, shape) -> np.ndarray:
    """The ``j``-th array of a packed vector as a writable view of ``shape``."""
    o, n = int(P[16 + 2 * j]), int(P[17 + 2 * j])
    return P[o: o + n].reshape(shape)


