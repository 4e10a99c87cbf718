"""The compiled discretisation of two-state models (n = 2, mds2's size) in the algebra of 2 x 2 matrices that
commute with X = A dt: every power series in X is alpha I + beta N, with N = X - mu I, mu = tr(X) / 2, and
N^2 = q I, q = ((x11 - x22) / 2)^2 + x12 x21 (Cayley-Hamilton). Two numbers per matrix instead of four.

Phi = exp(X) and phi1(X) = sum_k X^k / (k + 1)! (Gamma = phi1(X) dt B) are computed by scaling and squaring
in that algebra: Y = X / 2^s = m I + N' with |m| + sqrt|Q| (a bound of its spectral radius; N'^2 = Q I) at
most THETA, Taylor polynomials by Horner (of a degree that truncates below the dtype's rounding), then s
squarings exp(2Y) = exp(Y)^2, phi1(2Y) = (exp(Y) + I) phi1(Y) / 2. Unlike the generic kernels
(`pipe.model.ltv_numba`: the 1-norm of the augmented matrix [[X, B dt], [0, 0]]), the number of squarings
follows the spectrum of X alone: mds2's companion matrix at conn's neutral profile has a 1-norm of 25
(7 squarings) and a spectral radius of 0.5 (2 squarings); Gamma is linear in B, which needs no scaling.

The result depends on X only through the two numbers (m, Q), so the backward carries their derivatives
forward through the same Horner steps and squarings (forward mode: the exact derivative of this algorithm,
no stored iterates) and contracts them with the incoming gradients. Samples run side by side, LANES at a
time: every per-sample quantity of a block is a row of a small lane-major array (`lanes`, `state`, `steps`,
`grads`), so that each loop over the lanes reads and writes contiguous rows without branches and vectorises;
only the recurrences step lane by lane. Sums in float64 whatever the tensors' dtype. Why by hand: no library
offers a batched 2 x 2 exponential and phi1 with their derivatives, compiled.
"""

from __future__ import annotations

import numba
import numpy as np

THETA = 0.125         # |m| + sqrt|Q| of X / 2^s at most
# Taylor degree per dtype, its truncation (a relative backward error of Y, which the squarings keep) below
# the dtype's rounding: about 0.125^10 / 10! ~ 3e-16 for float64, 7 * 0.125^6 / 7! ~ 5e-9 for float32 (rounding
# 6e-8); the sums run in float64 either way.
DEGREE_2X2 = {np.dtype(np.float64): 10, np.dtype(np.float32): 6}
MAX_SQUARINGS = 60
LANES = 32            # samples side by side in the innermost loops (16: 1.5x slower, 64: no faster)
CHUNK = 256           # samples per parallel task
X12, X21, N11, M, Q, SCALE, SQUARINGS, RADIUS = range(8)     # rows of a block's `lanes` (float64)
# rows of a block's `steps` (Phi, Gamma and b, in the inputs' dtype) and `grads` (the gradients of Phi and Gamma)
P11, P12, P21, P22, G1, G2, B1, B2 = range(8)

_jit = numba.njit(cache=True, fastmath=False, parallel=True)
_jit_inline = numba.njit(cache=True, fastmath=False, inline="always")


@_jit_inline
def _load(a: np.ndarray, b: np.ndarray, dt: float, first: int, lanes: np.ndarray, steps: np.ndarray) -> int:
    """For items first.. (one per lane; a short last block repeats its last item) the rows of `lanes`: x12,
    x21, n11 (N = [[n11, x12], [x21, -n11]]), m = mu / 2^s, Q = q / 4^s, 2^-s and s, the squarings that bring
    |mu| + sqrt|q| to THETA; and b into `steps`. The block's largest radius gives the number of halving
    rounds, each of which halves the radii still above THETA (no per-sample loop). Returns the largest s."""
    for lane in range(LANES):
        item = min(first + lane, a.shape[0] - 1)
        x11, x12, x21, x22 = a[item, 0, 0] * dt, a[item, 0, 1] * dt, a[item, 1, 0] * dt, a[item, 1, 1] * dt
        mu, n11 = 0.5 * (x11 + x22), 0.5 * (x11 - x22)
        q = n11 * n11 + x12 * x21
        lanes[X12, lane], lanes[X21, lane], lanes[N11, lane] = x12, x21, n11
        lanes[M, lane], lanes[Q, lane], lanes[RADIUS, lane] = mu, q, abs(mu) + np.sqrt(abs(q))
        lanes[SCALE, lane], lanes[SQUARINGS, lane] = 1.0, 0.0
        steps[B1, lane], steps[B2, lane] = b[item, 0], b[item, 1]
    largest = 0.0
    for lane in range(LANES):
        largest = max(largest, lanes[RADIUS, lane])
    most = 0
    while largest > THETA and most < MAX_SQUARINGS:
        largest *= 0.5
        most += 1
    for _ in range(most):
        for lane in range(LANES):
            active = lanes[RADIUS, lane] > THETA
            lanes[RADIUS, lane] = 0.5 * lanes[RADIUS, lane] if active else lanes[RADIUS, lane]
            lanes[SCALE, lane] = 0.5 * lanes[SCALE, lane] if active else lanes[SCALE, lane]
            lanes[SQUARINGS, lane] = lanes[SQUARINGS, lane] + 1.0 if active else lanes[SQUARINGS, lane]
    for lane in range(LANES):
        scale = lanes[SCALE, lane]
        lanes[M, lane], lanes[Q, lane] = lanes[M, lane] * scale, lanes[Q, lane] * scale * scale
    return most


@_jit_inline
def _exponentials(lanes: np.ndarray, most: int, degree: int, state: np.ndarray) -> None:
    """state[0:4] = (p, r, g, h): exp(X) = p I + r N' and phi1(X) = g I + h N' of every lane. Horner from
    (P, G) = (I, 0): P <- I + Y P / j, G <- (Y G + I) / j for j = d .. 1, then while i < s:
    P <- P^2, G <- (P + I) G / 2, with (a, b)(c, d) = (a c + Q b d, a d + b c)."""
    for lane in range(LANES):
        state[0, lane], state[1, lane], state[2, lane], state[3, lane] = 1.0, 0.0, 0.0, 0.0
    for j in range(degree, 0, -1):
        inv = 1.0 / j
        for lane in range(LANES):
            m, big_q = lanes[M, lane], lanes[Q, lane]
            p, r, g, h = state[0, lane], state[1, lane], state[2, lane], state[3, lane]
            state[0, lane] = 1.0 + (m * p + big_q * r) * inv
            state[1, lane] = (p + m * r) * inv
            state[2, lane] = (m * g + big_q * h + 1.0) * inv
            state[3, lane] = (g + m * h) * inv
    for i in range(most):
        for lane in range(LANES):
            big_q, active = lanes[Q, lane], i < lanes[SQUARINGS, lane]
            p, r, g, h = state[0, lane], state[1, lane], state[2, lane], state[3, lane]
            state[0, lane] = p * p + big_q * r * r if active else p
            state[1, lane] = 2.0 * p * r if active else r
            state[2, lane] = 0.5 * ((p + 1.0) * g + big_q * r * h) if active else g
            state[3, lane] = 0.5 * ((p + 1.0) * h + r * g) if active else h


@_jit_inline
def _exponentials_and_derivatives(lanes: np.ndarray, most: int, degree: int, state: np.ndarray) -> None:
    """`_exponentials` with the derivatives of (p, r, g, h) by m in state[4:8] and by Q in state[8:12],
    carried through every step (forward mode)."""
    for lane in range(LANES):
        state[0, lane] = 1.0
        for row in range(1, 12):
            state[row, lane] = 0.0
    for j in range(degree, 0, -1):
        inv = 1.0 / j
        for lane in range(LANES):
            m, big_q = lanes[M, lane], lanes[Q, lane]
            p, r, g, h = state[0, lane], state[1, lane], state[2, lane], state[3, lane]
            pm, rm, gm, hm = state[4, lane], state[5, lane], state[6, lane], state[7, lane]
            pq, rq, gq, hq = state[8, lane], state[9, lane], state[10, lane], state[11, lane]
            state[0, lane] = 1.0 + (m * p + big_q * r) * inv
            state[1, lane] = (p + m * r) * inv
            state[2, lane] = (m * g + big_q * h + 1.0) * inv
            state[3, lane] = (g + m * h) * inv
            state[4, lane] = (p + m * pm + big_q * rm) * inv
            state[5, lane] = (pm + r + m * rm) * inv
            state[6, lane] = (g + m * gm + big_q * hm) * inv
            state[7, lane] = (gm + h + m * hm) * inv
            state[8, lane] = (m * pq + r + big_q * rq) * inv
            state[9, lane] = (pq + m * rq) * inv
            state[10, lane] = (m * gq + h + big_q * hq) * inv
            state[11, lane] = (gq + m * hq) * inv
    for i in range(most):
        for lane in range(LANES):
            big_q, active = lanes[Q, lane], i < lanes[SQUARINGS, lane]
            p, r, g, h = state[0, lane], state[1, lane], state[2, lane], state[3, lane]
            pm, rm, gm, hm = state[4, lane], state[5, lane], state[6, lane], state[7, lane]
            pq, rq, gq, hq = state[8, lane], state[9, lane], state[10, lane], state[11, lane]
            state[0, lane] = p * p + big_q * r * r if active else p
            state[1, lane] = 2.0 * p * r if active else r
            state[2, lane] = 0.5 * ((p + 1.0) * g + big_q * r * h) if active else g
            state[3, lane] = 0.5 * ((p + 1.0) * h + r * g) if active else h
            state[4, lane] = 2.0 * (p * pm + big_q * r * rm) if active else pm
            state[5, lane] = 2.0 * (pm * r + p * rm) if active else rm
            state[6, lane] = 0.5 * (pm * g + (p + 1.0) * gm + big_q * (rm * h + r * hm)) if active else gm
            state[7, lane] = 0.5 * (pm * h + (p + 1.0) * hm + rm * g + r * gm) if active else hm
            state[8, lane] = 2.0 * (p * pq + big_q * r * rq) + r * r if active else pq     # Q meets Q itself too
            state[9, lane] = 2.0 * (pq * r + p * rq) if active else rq
            state[10, lane] = 0.5 * (pq * g + (p + 1.0) * gq + big_q * (rq * h + r * hq) + r * h) if active else gq
            state[11, lane] = 0.5 * (pq * h + (p + 1.0) * hq + rq * g + r * gq) if active else hq


@_jit_inline
def _steps(lanes: np.ndarray, state: np.ndarray, dt: float, steps: np.ndarray) -> None:
    """The rows of `steps` from (p, r, g, h): Phi = p I + r 2^-s N, Gamma = dt (g I + h 2^-s N) b."""
    for lane in range(LANES):
        n11, scale = lanes[N11, lane], lanes[SCALE, lane]
        alpha, beta = state[0, lane], state[1, lane] * scale
        steps[P11, lane], steps[P12, lane] = alpha + beta * n11, beta * lanes[X12, lane]
        steps[P21, lane], steps[P22, lane] = beta * lanes[X21, lane], alpha - beta * n11
        alpha, beta = state[2, lane] * dt, state[3, lane] * scale * dt
        b1, b2 = steps[B1, lane], steps[B2, lane]
        steps[G1, lane] = (alpha + beta * n11) * b1 + beta * lanes[X12, lane] * b2
        steps[G2, lane] = beta * lanes[X21, lane] * b1 + (alpha - beta * n11) * b2


@_jit_inline
def _contract(lanes: np.ndarray, state: np.ndarray, dt: float, steps: np.ndarray, grads: np.ndarray,
              out: np.ndarray) -> None:
    """Rows of `out` (the gradients of a11, a12, a21, a22, b1, b2) from `grads` (those of Phi and Gamma): the
    gradients of (p, r, g, h), of N and of b; the derivatives of (p, r, g, h) by m and Q give those of
    mu = 2^s m and q = 4^s Q, and with mu = (x11 + x22) / 2, n11 = (x11 - x22) / 2, q = n11^2 + x12 x21 those
    of X = a dt."""
    for lane in range(LANES):
        x12, x21, n11, scale = lanes[X12, lane], lanes[X21, lane], lanes[N11, lane], lanes[SCALE, lane]
        f11, f12, f21, f22 = grads[P11, lane], grads[P12, lane], grads[P21, lane], grads[P22, lane]
        g1, g2, b1, b2 = grads[G1, lane], grads[G2, lane], steps[B1, lane], steps[B2, lane]
        beta_p, alpha_g, beta_g = state[1, lane] * scale, state[2, lane] * dt, state[3, lane] * scale * dt
        out[4, lane] = (alpha_g + beta_g * n11) * g1 + beta_g * x21 * g2
        out[5, lane] = beta_g * x12 * g1 + (alpha_g - beta_g * n11) * g2
        bar_p = f11 + f22
        bar_r = (n11 * (f11 - f22) + x12 * f12 + x21 * f21) * scale
        bar_g = dt * (g1 * b1 + g2 * b2)
        bar_h = dt * (n11 * (g1 * b1 - g2 * b2) + x12 * g1 * b2 + x21 * g2 * b1) * scale
        bar_mu = scale * (bar_p * state[4, lane] + bar_r * state[5, lane] + bar_g * state[6, lane]
                          + bar_h * state[7, lane])
        bar_q = scale * scale * (bar_p * state[8, lane] + bar_r * state[9, lane] + bar_g * state[10, lane]
                                 + bar_h * state[11, lane])
        bar_n11 = beta_p * (f11 - f22) + beta_g * (g1 * b1 - g2 * b2) + 2.0 * n11 * bar_q
        out[0, lane] = 0.5 * (bar_mu + bar_n11) * dt
        out[1, lane] = (beta_p * f12 + beta_g * g1 * b2 + x21 * bar_q) * dt
        out[2, lane] = (beta_p * f21 + beta_g * g2 * b1 + x12 * bar_q) * dt
        out[3, lane] = 0.5 * (bar_mu - bar_n11) * dt


@_jit_inline
def _store_gradients(out: np.ndarray, first: int, count: int, grad_a: np.ndarray, grad_b: np.ndarray) -> None:
    """The block's first `count` lanes of `out` into grad_a and grad_b at items first.."""
    for lane in range(count):
        item = first + lane
        grad_a[item, 0, 0], grad_a[item, 0, 1] = out[0, lane], out[1, lane]
        grad_a[item, 1, 0], grad_a[item, 1, 1] = out[2, lane], out[3, lane]
        grad_b[item, 0], grad_b[item, 1] = out[4, lane], out[5, lane]


@_jit
def discretize2_forward(a: np.ndarray, b: np.ndarray, dt: float, degree: int, phi: np.ndarray,
                        gamma: np.ndarray) -> None:
    """a (N, 2, 2), b (N, 2) -> phi = exp(a dt) (N, 2, 2), gamma = phi1(a dt) dt b (N, 2)."""
    count = a.shape[0]
    for chunk in numba.prange((count + CHUNK - 1) // CHUNK):
        lanes, state = np.empty((8, LANES)), np.empty((4, LANES))
        steps = np.empty((8, LANES), dtype=a.dtype)
        for first in range(chunk * CHUNK, min(count, (chunk + 1) * CHUNK), LANES):
            _exponentials(lanes, _load(a, b, dt, first, lanes, steps), degree, state)
            _steps(lanes, state, dt, steps)
            for lane in range(min(LANES, count - first)):
                item = first + lane
                phi[item, 0, 0], phi[item, 0, 1] = steps[P11, lane], steps[P12, lane]
                phi[item, 1, 0], phi[item, 1, 1] = steps[P21, lane], steps[P22, lane]
                gamma[item, 0], gamma[item, 1] = steps[G1, lane], steps[G2, lane]


@_jit
def discretize2_backward(a: np.ndarray, b: np.ndarray, dt: float, degree: int, grad_phi: np.ndarray,
                         grad_gamma: np.ndarray, grad_a: np.ndarray, grad_b: np.ndarray) -> None:
    """Gradients of a (N, 2, 2) and b (N, 2) from those of phi and gamma (`_contract`)."""
    count = a.shape[0]
    for chunk in numba.prange((count + CHUNK - 1) // CHUNK):
        lanes, state, out = np.empty((8, LANES)), np.empty((12, LANES)), np.empty((6, LANES))
        steps, grads = np.empty((8, LANES), dtype=a.dtype), np.zeros((6, LANES), dtype=a.dtype)
        for first in range(chunk * CHUNK, min(count, (chunk + 1) * CHUNK), LANES):
            _exponentials_and_derivatives(lanes, _load(a, b, dt, first, lanes, steps), degree, state)
            for lane in range(min(LANES, count - first)):
                item = first + lane
                grads[P11, lane], grads[P12, lane] = grad_phi[item, 0, 0], grad_phi[item, 0, 1]
                grads[P21, lane], grads[P22, lane] = grad_phi[item, 1, 0], grad_phi[item, 1, 1]
                grads[G1, lane], grads[G2, lane] = grad_gamma[item, 0], grad_gamma[item, 1]
            _contract(lanes, state, dt, steps, grads, out)
            _store_gradients(out, first, min(LANES, count - first), grad_a, grad_b)


@_jit
def simulate2_forward(a: np.ndarray, b: np.ndarray, u: np.ndarray, dt: float, degree: int, x: np.ndarray) -> None:
    """discretize2_forward and `pipe.model.ltv_numba.recurrence_forward` in one pass per trajectory: a
    (B, T, 2, 2), b (B, T, 2), u (B, T) -> states x (B, T + 1, 2) from x_0 = 0. Each block of LANES steps is
    discretised into a small array of the inputs' dtype and stepped through at once, so the step matrices
    never reach memory as tensors; the same operations in the same order as the two kernels, so the same
    numbers to the last bit."""
    batch, length = u.shape
    for row in numba.prange(batch):
        lanes, state = np.empty((8, LANES)), np.empty((4, LANES))
        steps = np.empty((8, LANES), dtype=a.dtype)
        x[row, 0, 0], x[row, 0, 1] = 0.0, 0.0
        x1, x2 = x[row, 0, 0], x[row, 0, 1]       # the states of the inputs' dtype, carried in registers
        for first in range(0, length, LANES):
            _exponentials(lanes, _load(a[row], b[row], dt, first, lanes, steps), degree, state)
            _steps(lanes, state, dt, steps)
            for lane in range(min(LANES, length - first)):
                k = first + lane
                drive = u[row, k]
                y1 = steps[G1, lane] * drive
                y1 += steps[P11, lane] * x1
                y1 += steps[P12, lane] * x2
                y2 = steps[G2, lane] * drive
                y2 += steps[P21, lane] * x1
                y2 += steps[P22, lane] * x2
                x1, x2 = y1, y2
                x[row, k + 1, 0], x[row, k + 1, 1] = x1, x2


@_jit
def simulate2_backward(a: np.ndarray, b: np.ndarray, u: np.ndarray, dt: float, degree: int, x: np.ndarray,
                       grad_x: np.ndarray, grad_a: np.ndarray, grad_b: np.ndarray, grad_u: np.ndarray) -> None:
    """The adjoint of simulate2_forward, block by block from the end: each block's steps are discretised
    again with their derivatives, the adjoint recurrence lambda_k = g_k + Phi_k^T lambda_{k+1} runs through
    them (as `pipe.model.ltv_numba.recurrence_backward`, lambda in registers) and its gradients of Phi and
    Gamma are contracted at once into those of a and b (`_contract`)."""
    batch, length = u.shape
    for row in numba.prange(batch):
        lanes, state, out = np.empty((8, LANES)), np.empty((12, LANES)), np.empty((6, LANES))
        steps, grads = np.empty((8, LANES), dtype=a.dtype), np.zeros((6, LANES), dtype=a.dtype)
        l1, l2 = grad_x[row, length, 0], grad_x[row, length, 1]
        for first in range((length - 1) // LANES * LANES, -1, -LANES):
            count = min(LANES, length - first)
            _exponentials_and_derivatives(lanes, _load(a[row], b[row], dt, first, lanes, steps), degree, state)
            _steps(lanes, state, dt, steps)
            for lane in range(count - 1, -1, -1):
                k = first + lane
                drive, y1, y2 = u[row, k], x[row, k, 0], x[row, k, 1]
                grads[G1, lane], grads[G2, lane] = l1 * drive, l2 * drive
                grads[P11, lane], grads[P12, lane] = l1 * y1, l1 * y2
                grads[P21, lane], grads[P22, lane] = l2 * y1, l2 * y2
                dot = 0.0
                dot += steps[G1, lane] * l1
                dot += steps[G2, lane] * l2
                grad_u[row, k] = dot
                m1 = grad_x[row, k, 0]
                m1 += steps[P11, lane] * l1
                m1 += steps[P21, lane] * l2
                m2 = grad_x[row, k, 1]
                m2 += steps[P12, lane] * l1
                m2 += steps[P22, lane] * l2
                l1, l2 = m1, m2
            _contract(lanes, state, dt, steps, grads, out)
            _store_gradients(out, first, count, grad_a[row], grad_b[row])
