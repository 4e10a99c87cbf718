"""The Gaussian head's free profiles (`FreeGaussianProfiles`) as compiled functions of their parameters, forward
and exact adjoint, in float64: what system identification evaluates thousands of times per start
(`pipe.model.interfaces.CompiledProfiles`). The same formulas as `GaussianHead.profile` and
`NormalisedGaussians`, without torch's per-operation cost on tensors of a few hundred numbers. Why by hand: the
objective is a chain of small array operations whose cost in torch is the dispatch, not the arithmetic, and
numba has no vectorised exp here, so the softmax's exponentials use a polynomial that LLVM vectorises.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from pipe.plugins.head.gaussian import SOFTPLUS_ONE, GaussianHead

EXP_FLOOR = -64.0     # softmax exponents below the largest by more than this weigh exp(-64) ~ 1e-28: taken there
EXP_HALVINGS = 10     # exp(x) = exp(x / 2^10)^(2^10), exp(x / 2^10) by its Taylor polynomial of degree 8:
                      # within 1e-13 relative on [EXP_FLOOR, 0], a formula LLVM vectorises (numba has no SVML here)

_jit = numba.njit(cache=True, fastmath={"reassoc", "contract"})
_jit_inline = numba.njit(cache=True, fastmath={"reassoc", "contract"}, inline="always")


@_jit_inline
def _exp_nonpositive(x: float) -> float:
    """exp(x) for x <= 0 (written out: a loop or `max` here keeps LLVM from vectorising the callers' loops)."""
    y = (x if x > EXP_FLOOR else EXP_FLOOR) * (1.0 / 2.0**EXP_HALVINGS)
    e = 1.0 + y * (1.0 / 8.0)
    e = 1.0 + y * (1.0 / 7.0) * e
    e = 1.0 + y * (1.0 / 6.0) * e
    e = 1.0 + y * (1.0 / 5.0) * e
    e = 1.0 + y * (1.0 / 4.0) * e
    e = 1.0 + y * (1.0 / 3.0) * e
    e = 1.0 + y * (1.0 / 2.0) * e
    e = 1.0 + y * e
    e *= e   # ten squarings: EXP_HALVINGS
    e *= e
    e *= e
    e *= e
    e *= e
    e *= e
    e *= e
    e *= e
    e *= e
    e *= e
    return e


@_jit_inline
def _softplus(x: float) -> float:
    return max(x, 0.0) + np.log1p(np.exp(-abs(x)))


@_jit_inline
def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + np.exp(-x)) if x >= 0.0 else np.exp(x) / (1.0 + np.exp(x))


@_jit
def _local_models(values: np.ndarray, depth_max: float, inverse_ratios: tuple, row: int,
                  amplitude: np.ndarray, centre: np.ndarray, precision: np.ndarray) -> None:
    """`GaussianHead.profile` for one parameter's local models (row of values (3, P, N)) on a trajectory that
    reaches depth_max: amplitudes, centres and precisions 1 / (2 c^2), each (N,)."""
    n = values.shape[2]
    total = 0.0
    for i in range(n):
        total += _softplus(values[1, row, i]) + 1e-6
    below = 0.0
    for i in range(n):
        section = (_softplus(values[1, row, i]) + 1e-6) / total * depth_max
        centre[i] = below + 0.5 * section
        below += section
        position = _sigmoid(values[2, row, i])
        width = 0.5 * section * (inverse_ratios[0] + position * (inverse_ratios[1] - inverse_ratios[0]))
        precision[i] = 0.5 / (width * width)
        amplitude[i] = _softplus(values[0, row, i] + SOFTPLUS_ONE)


@_jit
def _profiles_forward(values: np.ndarray, depth: np.ndarray, depth_max: np.ndarray, inverse_ratios: tuple,
                      theta: np.ndarray, weights: np.ndarray) -> None:
    """theta (B, T, P) of the free profiles values (3, P, N) (unconstrained amplitudes, sections, widths) at
    depths (B, T), with the normalised weights (B, P, N, T) kept for the backward. The loops run along the
    samples, contiguous, so that they vectorise."""
    batch, length = depth.shape
    parameters, n = values.shape[1], values.shape[2]
    amplitude, centre, precision = np.empty(n), np.empty(n), np.empty(n)
    largest, total, profile = np.empty(length), np.empty(length), np.empty(length)
    for b in range(batch):
        p_z = depth[b]
        for p in range(parameters):
            _local_models(values, depth_max[b], inverse_ratios, p, amplitude, centre, precision)
            w = weights[b, p]
            largest[:] = -np.inf
            for i in range(n):
                k, c = precision[i], centre[i]
                for t in range(length):
                    offset = p_z[t] - c
                    e = -k * offset * offset
                    w[i, t] = e
                    largest[t] = e if e > largest[t] else largest[t]
            total[:] = 0.0
            for i in range(n):
                for t in range(length):
                    e = _exp_nonpositive(w[i, t] - largest[t])
                    w[i, t] = e
                    total[t] += e
            for t in range(length):
                total[t] = 1.0 / total[t]
            profile[:] = 0.0
            for i in range(n):
                a = amplitude[i]
                for t in range(length):
                    e = w[i, t] * total[t]
                    w[i, t] = e
                    profile[t] += a * e
            for t in range(length):
                theta[b, t, p] = profile[t]


@_jit
def _profiles_backward(values: np.ndarray, depth: np.ndarray, depth_max: np.ndarray, inverse_ratios: tuple,
                       theta: np.ndarray, weights: np.ndarray, grad_theta: np.ndarray, grad: np.ndarray) -> None:
    """The adjoint of `_profiles_forward`: grad (3, P, N) of the values from grad_theta (B, T, P), through the
    written-out derivatives of the softmax (as `NormalisedGaussians.backward`) and of `_local_models`."""
    batch, length = depth.shape
    parameters, n = values.shape[1], values.shape[2]
    amplitude, centre, precision = np.empty(n), np.empty(n), np.empty(n)
    d_centre, d_precision = np.empty(n), np.empty(n)
    grad[:] = 0.0
    for p in range(parameters):
        delta = np.empty(n)
        total = 0.0
        for i in range(n):
            delta[i] = _softplus(values[1, p, i]) + 1e-6
            total += delta[i]
        for b in range(batch):
            _local_models(values, depth_max[b], inverse_ratios, p, amplitude, centre, precision)
            w = weights[b, p]
            for i in range(n):
                d_amplitude, d_c, d_k = 0.0, 0.0, 0.0
                for t in range(length):
                    g = grad_theta[b, t, p]
                    weighted = w[i, t] * g
                    d_amplitude += weighted
                    exponent = weighted * (amplitude[i] - theta[b, t, p])   # d/d(-k (p - c)^2)
                    offset = depth[b, t] - centre[i]
                    d_c += exponent * offset
                    d_k -= exponent * offset * offset
                grad[0, p, i] += d_amplitude * _sigmoid(values[0, p, i] + SOFTPLUS_ONE)
                d_centre[i] = 2.0 * precision[i] * d_c
                d_precision[i] = d_k
            # centre_i = sum_{j<i} s_j + s_i / 2 and width_i = s_i h_i / 2 with s = delta / total * depth_max and
            # h_i the ratio between the edge widths; precision = 1 / (2 width^2)
            d_section = np.zeros(n)
            after = 0.0
            for i in range(n - 1, -1, -1):
                section = delta[i] / total * depth_max[b]
                position = _sigmoid(values[2, p, i])
                h = inverse_ratios[0] + position * (inverse_ratios[1] - inverse_ratios[0])
                width = 0.5 * section * h
                d_width = -d_precision[i] / (width * width * width)
                d_section[i] = after + 0.5 * d_centre[i] + 0.5 * h * d_width
                after += d_centre[i]
                grad[2, p, i] += 0.5 * section * d_width * (inverse_ratios[1] - inverse_ratios[0]) * position * (
                    1.0 - position)
            along = 0.0
            for i in range(n):
                along += d_section[i] * delta[i]
            for i in range(n):
                d_delta = (d_section[i] - along / total) * depth_max[b] / total
                grad[1, p, i] += d_delta * _sigmoid(values[1, p, i])


class CompiledFreeProfiles:
    """`FreeGaussianProfiles` of one set on fixed trajectories as compiled functions of its flat parameters
    (amplitudes, sections, widths, as `torch.cat` of its parameters orders them), in float64: what system
    identification evaluates thousands of times (`pipe.model.interfaces.CompiledProfiles`)."""

    def __init__(self, head: GaussianHead, depth: np.ndarray) -> None:
        self.depth = np.ascontiguousarray(depth, dtype=np.float64)
        self.depth_max = np.abs(self.depth).max(axis=1)
        self.shape = (3, head.num_parameters, head.n)
        self.inverse_ratios = tuple(1.0 / math.sqrt(2.0 * math.log(1.0 / r)) for r in head.edge_ratios)
        batch, length = self.depth.shape
        self.weights = np.empty((batch, head.num_parameters, head.n, length))
        self.theta = np.empty((batch, length, head.num_parameters))
        self.values = np.zeros(self.shape)

    def forward(self, values: np.ndarray) -> np.ndarray:
        """theta (B, T, P) for the flat parameters."""
        self.values = np.ascontiguousarray(values, dtype=np.float64).reshape(self.shape)
        _profiles_forward(self.values, self.depth, self.depth_max, self.inverse_ratios, self.theta, self.weights)
        return self.theta

    def backward(self, grad_theta: np.ndarray) -> np.ndarray:
        """The gradient of the flat parameters at the last `forward`'s, from that of theta (B, T, P)."""
        grad = np.empty(self.shape)
        _profiles_backward(self.values, self.depth, self.depth_max, self.inverse_ratios, self.theta, self.weights,
                           np.ascontiguousarray(grad_theta, dtype=np.float64), grad)
        return grad.reshape(-1)
