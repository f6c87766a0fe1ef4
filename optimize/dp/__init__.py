"""The generic dynamic-programming engine (backward pass, forward pass at true states, multilinear
interpolation, level-set terminal constraints) and its compiled kernels."""
from .engine import (FORWARD_INTERP, DPProblem, DPResult, ValueFunctions, backward_pass, cartesian, forward_pass,
                     interpolate, solve)

__all__ = ["DPProblem", "DPResult", "ValueFunctions", "cartesian", "solve", "backward_pass", "forward_pass",
           "interpolate", "FORWARD_INTERP"]
