"""The compiled simulator: `pipe.model.ltv`'s discretisation and recurrence as numba kernels inside
`torch.autograd.Function`s, with exact reverse-mode (adjoint) backward passes, also compiled.

- `CompiledDiscretize`: A (N, n, n), B (N, n) -> Phi = exp(A dt), Gamma = int_0^dt exp(A s) ds B. For two
  states (mds2) the kernels of `pipe.model.ltv_2x2` (scaling and squaring in the two-dimensional algebra of
  I and A - tr(A)/2 I). For any other n, the exponential of the augmented matrix M = dt [[A, B], [0, 0]] by
  scaling and squaring a degree-10 Taylor polynomial (||M / 2^s||_1 <= 1/4, truncation below 1e-14
  relative); its backward is the exact adjoint of that algorithm: the Horner steps and the squarings run in
  reverse.
- `CompiledRecurrence`: x_{k+1} = Phi_k x_k + Gamma_k u_k from x_0 = 0. Its backward is the adjoint
  recurrence lambda_k = g_k + Phi_k^T lambda_{k+1}, which gives the gradients of Phi, Gamma and u.
- `CompiledSimulate2`: both of them for a two-state model in one kernel each way (what
  `pipe.model.ltv.simulate` runs for mds2): the same numbers without the step matrices as tensors.
- `simulate_arrays` and `simulate_arrays_backward`: `simulate` and its adjoint on numpy arrays, for callers
  that chain compiled pieces without torch (system identification's compiled engine).

All run on CPU float32 or float64 tensors (each dtype compiles once; sums accumulate in float64) and loop
over the batch in parallel (numba's `prange`, `numba.set_num_threads` caps the threads). Why by hand:
torch's `matrix_exp` and a Python loop over time launch thousands of tiny kernels per call; no library
offers a compiled batched small-matrix exponential with its adjoint or a compiled LTV recurrence.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from pipe.model.ltv_2x2 import (
    DEGREE_2X2,
    discretize2_backward,
    discretize2_forward,
    simulate2_backward,
    simulate2_forward,
)

TAYLOR_DEGREE = 10
THETA = 0.25          # ||M / 2^s||_1 bound: 0.25^11 / 11! ~ 6e-15 truncation
MAX_SQUARINGS = 60    # ||M||_1 up to 2^58: beyond any physical stiffness in float64
LANES = 64            # matrices exponentiated side by side, one per SIMD lane of the innermost loops

_jit = numba.njit(cache=True, fastmath=False, parallel=True)
_jit_serial = numba.njit(cache=True, fastmath=False, inline="always")


@_jit_serial
def _load_chunk(a: np.ndarray, b: np.ndarray, dt: float, first: int, x: np.ndarray, y: np.ndarray,
                squarings: np.ndarray) -> int:
    """Blocks of M = dt [[a, b], [0, 0]] for items first.. (as many as x holds lanes), one lane per item
    (x (n, n, L), y (n, L)), each scaled by 2^-s with s its number of squarings; returns the largest s."""
    n, lanes = y.shape
    most = 0
    for lane in range(lanes):
        item = min(first + lane, a.shape[0] - 1)       # a short last chunk repeats its last item
        norm = 0.0
        col_b = 0.0
        for c in range(n):
            col = 0.0
            for r in range(n):
                col += abs(a[item, r, c])
            norm = max(norm, col * abs(dt))
            col_b += abs(b[item, c])
        norm = max(norm, col_b * abs(dt))
        s = 0
        while norm > THETA and s < MAX_SQUARINGS:
            norm *= 0.5
            s += 1
        squarings[lane] = s
        most = max(most, s)
        scale = dt * 0.5 ** s
        for r in range(n):
            for c in range(n):
                x[r, c, lane] = a[item, r, c] * scale
            y[r, lane] = b[item, r] * scale
    return most


@_jit_serial
def _expm_chunk(x: np.ndarray, y: np.ndarray, squarings: np.ndarray, most: int, hp: np.ndarray, hv: np.ndarray,
                sp: np.ndarray, sv: np.ndarray) -> None:
    """exp(M) of every lane, in block form [[P, p], [0, 1]] (every polynomial in M, and every product of
    such blocks, has it), with all iterates kept for the backward. Horner: P_d = I, p_d = 0,
    P_{j-1} = I + x P_j / j, p_{j-1} = (x p_j + y) / j; exp(M / 2^s) ~ (P_0, p_0) = (sp[0], sv[0]).
    Squarings: sp[i + 1] = sp[i]^2, sv[i + 1] = sp[i] sv[i] + sv[i] for lanes with i < s, a copy for the
    others, so sp[most] holds every lane's exp(M). Lanes are the innermost, contiguous dimension."""
    n, lanes = y.shape
    hp[TAYLOR_DEGREE] = 0.0
    hv[TAYLOR_DEGREE] = 0.0
    for r in range(n):
        hp[TAYLOR_DEGREE, r, r, :] = 1.0
    for j in range(TAYLOR_DEGREE, 0, -1):
        inv = 1.0 / j
        for r in range(n):
            for c in range(n):
                out = hp[j - 1, r, c]
                out[:] = 0.0
                for k in range(n):
                    xr, pc = x[r, k], hp[j, k, c]
                    for lane in range(lanes):
                        out[lane] += xr[lane] * pc[lane]
                diagonal = 1.0 if r == c else 0.0
                for lane in range(lanes):
                    out[lane] = out[lane] * inv + diagonal
            out = hv[j - 1, r]
            out[:] = y[r]
            for k in range(n):
                xr, pv = x[r, k], hv[j, k]
                for lane in range(lanes):
                    out[lane] += xr[lane] * pv[lane]
            for lane in range(lanes):
                out[lane] *= inv
    sp[0] = hp[0]
    sv[0] = hv[0]
    for i in range(most):
        for r in range(n):
            for c in range(n):
                out = sp[i + 1, r, c]
                out[:] = 0.0
                for k in range(n):
                    left, right = sp[i, r, k], sp[i, k, c]
                    for lane in range(lanes):
                        out[lane] += left[lane] * right[lane]
            out = sv[i + 1, r]
            out[:] = sv[i, r]
            for k in range(n):
                left, right = sp[i, r, k], sv[i, k]
                for lane in range(lanes):
                    out[lane] += left[lane] * right[lane]
        for r in range(n):
            for lane in range(lanes):
                if i >= squarings[lane]:
                    for c in range(n):
                        sp[i + 1, r, c, lane] = sp[i, r, c, lane]
                    sv[i + 1, r, lane] = sv[i, r, lane]


@_jit_serial
def _exponentials(a: np.ndarray, b: np.ndarray, dt: float, first: int) -> tuple:
    """One chunk's forward pass from item `first` on: the scaled x, each lane's squarings, the largest, and
    the Horner (hp, hv) and squaring (sp, sv) iterates, whose last squaring holds every lane's exp(M)."""
    n = b.shape[1]
    x, y = np.empty((n, n, LANES)), np.empty((n, LANES))
    squarings = np.empty(LANES, dtype=np.int64)
    hp, hv = np.empty((TAYLOR_DEGREE + 1, n, n, LANES)), np.empty((TAYLOR_DEGREE + 1, n, LANES))
    most = _load_chunk(a, b, dt, first, x, y, squarings)
    sp, sv = np.empty((most + 1, n, n, LANES)), np.empty((most + 1, n, LANES))
    _expm_chunk(x, y, squarings, most, hp, hv, sp, sv)
    return x, squarings, most, hp, hv, sp, sv


@_jit
def discretize_forward(a: np.ndarray, b: np.ndarray, dt: float, phi: np.ndarray, gamma: np.ndarray) -> None:
    count, n = b.shape
    chunks = (count + LANES - 1) // LANES
    for chunk in numba.prange(chunks):
        first = chunk * LANES
        _, _, most, _, _, sp, sv = _exponentials(a, b, dt, first)
        for lane in range(min(LANES, count - first)):
            for r in range(n):
                for c in range(n):
                    phi[first + lane, r, c] = sp[most, r, c, lane]
                gamma[first + lane, r] = sv[most, r, lane]


@_jit
def discretize_backward(a: np.ndarray, b: np.ndarray, dt: float, grad_phi: np.ndarray, grad_gamma: np.ndarray,
                        grad_a: np.ndarray, grad_b: np.ndarray) -> None:
    """The exact adjoint of discretize_forward's algorithm, its steps in reverse (the forward is recomputed):
    squarings (S' = S S, g' = S g + g):  S_bar = S'_bar S^T + S^T S'_bar + g'_bar g^T, g_bar = S^T g'_bar + g'_bar
    (the identity for lanes that copied); Horner (P' = I + x P / j, p' = (x p + y) / j):
    x_bar += (P'_bar P^T + p'_bar p^T) / j, y_bar += p'_bar / j, P_bar = x^T P'_bar / j, p_bar = x^T p'_bar / j."""
    count, n = b.shape
    chunks = (count + LANES - 1) // LANES
    for chunk in numba.prange(chunks):
        first = chunk * LANES
        x, squarings, most, hp, hv, sp, sv = _exponentials(a, b, dt, first)
        adj_p, adj_v = np.zeros((n, n, LANES)), np.zeros((n, LANES))
        new_p, new_v = np.empty((n, n, LANES)), np.empty((n, LANES))
        grad_x, grad_y = np.zeros((n, n, LANES)), np.zeros((n, LANES))
        for lane in range(min(LANES, count - first)):
            for r in range(n):
                for c in range(n):
                    adj_p[r, c, lane] = grad_phi[first + lane, r, c]
                adj_v[r, lane] = grad_gamma[first + lane, r]
        for i in range(most - 1, -1, -1):
            for r in range(n):
                for c in range(n):
                    out = new_p[r, c]
                    vc, ar = sv[i, c], adj_v[r]
                    for lane in range(LANES):
                        out[lane] = ar[lane] * vc[lane]
                    for k in range(n):
                        p1, s1, s2, p2 = adj_p[r, k], sp[i, c, k], sp[i, k, r], adj_p[k, c]
                        for lane in range(LANES):
                            out[lane] += p1[lane] * s1[lane] + s2[lane] * p2[lane]
                out = new_v[r]
                out[:] = adj_v[r]
                for k in range(n):
                    s2, v2 = sp[i, k, r], adj_v[k]
                    for lane in range(LANES):
                        out[lane] += s2[lane] * v2[lane]
            for lane in range(LANES):
                if i < squarings[lane]:
                    for r in range(n):
                        for c in range(n):
                            adj_p[r, c, lane] = new_p[r, c, lane]
                        adj_v[r, lane] = new_v[r, lane]
        for j in range(1, TAYLOR_DEGREE + 1):
            inv = 1.0 / j
            for r in range(n):
                ar = adj_v[r]
                gy = grad_y[r]
                for lane in range(LANES):
                    gy[lane] += ar[lane] * inv
                for c in range(n):
                    gx, hvc = grad_x[r, c], hv[j, c]
                    for lane in range(LANES):
                        gx[lane] += ar[lane] * hvc[lane] * inv
                    for k in range(n):
                        p1, h1 = adj_p[r, k], hp[j, c, k]
                        for lane in range(LANES):
                            gx[lane] += p1[lane] * h1[lane] * inv
            for r in range(n):
                for c in range(n):
                    out = new_p[r, c]
                    out[:] = 0.0
                    for k in range(n):
                        x1, p2 = x[k, r], adj_p[k, c]
                        for lane in range(LANES):
                            out[lane] += x1[lane] * p2[lane]
                    for lane in range(LANES):
                        out[lane] *= inv
                out = new_v[r]
                out[:] = 0.0
                for k in range(n):
                    x1, v2 = x[k, r], adj_v[k]
                    for lane in range(LANES):
                        out[lane] += x1[lane] * v2[lane]
                for lane in range(LANES):
                    out[lane] *= inv
            adj_p[:] = new_p
            adj_v[:] = new_v
        for lane in range(min(LANES, count - first)):
            scale = 0.5 ** squarings[lane] * dt
            for r in range(n):
                for c in range(n):
                    grad_a[first + lane, r, c] = grad_x[r, c, lane] * scale
                grad_b[first + lane, r] = grad_y[r, lane] * scale


@_jit
def recurrence_forward(phi: np.ndarray, gamma: np.ndarray, u: np.ndarray, x: np.ndarray) -> None:
    """x (B, T + 1, n) with x[:, 0] = 0 and x[:, k + 1] = phi[:, k] x[:, k] + gamma[:, k] u[:, k]."""
    batch, steps, n = gamma.shape
    for row in numba.prange(batch):
        for i in range(n):
            x[row, 0, i] = 0.0
        for k in range(steps):
            for i in range(n):
                acc = gamma[row, k, i] * u[row, k]
                for j in range(n):
                    acc += phi[row, k, i, j] * x[row, k, j]
                x[row, k + 1, i] = acc


@_jit
def recurrence_backward(phi: np.ndarray, gamma: np.ndarray, u: np.ndarray, x: np.ndarray, grad_x: np.ndarray,
                        grad_phi: np.ndarray, grad_gamma: np.ndarray, grad_u: np.ndarray) -> None:
    """The adjoint recurrence: lambda_T = g_T, lambda_k = g_k + phi_k^T lambda_{k+1}; with it
    dL/dphi_k = lambda_{k+1} x_k^T, dL/dgamma_k = lambda_{k+1} u_k and dL/du_k = gamma_k . lambda_{k+1}."""
    batch, steps, n = gamma.shape
    for row in numba.prange(batch):
        lam = grad_x[row, steps].copy()
        nxt = np.empty(n)
        for k in range(steps - 1, -1, -1):
            dot = 0.0
            for i in range(n):
                grad_gamma[row, k, i] = lam[i] * u[row, k]
                dot += gamma[row, k, i] * lam[i]
                for j in range(n):
                    grad_phi[row, k, i, j] = lam[i] * x[row, k, j]
            grad_u[row, k] = dot
            for j in range(n):
                acc = grad_x[row, k, j]
                for i in range(n):
                    acc += phi[row, k, i, j] * lam[i]
                nxt[j] = acc
            lam[:] = nxt


def simulate_arrays(a: np.ndarray, b: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """States x (B, T + 1, n) from x_0 = 0 for A (B, T, n, n), B (B, T, n) and u (B, T), float64 arrays."""
    batch, steps, n = b.shape
    x = np.empty((batch, steps + 1, n))
    if n == 2:
        simulate2_forward(a, b, u, float(dt), DEGREE_2X2[a.dtype], x)
    else:
        phi, gamma = np.empty_like(a), np.empty_like(b)
        discretize_forward(a.reshape(-1, n, n), b.reshape(-1, n), float(dt), phi.reshape(-1, n, n),
                           gamma.reshape(-1, n))
        recurrence_forward(phi, gamma, u, x)
    return x


def simulate_arrays_backward(a: np.ndarray, b: np.ndarray, u: np.ndarray, dt: float, x: np.ndarray,
                             grad_x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The gradients of A and B from those of the states x of `simulate_arrays` (the input's is not needed)."""
    batch, steps, n = b.shape
    grad_a, grad_b, grad_u = np.empty_like(a), np.empty_like(b), np.empty_like(u)
    if n == 2:
        simulate2_backward(a, b, u, float(dt), DEGREE_2X2[a.dtype], x, grad_x, grad_a, grad_b, grad_u)
        return grad_a, grad_b
    phi, gamma = np.empty_like(a), np.empty_like(b)
    discretize_forward(a.reshape(-1, n, n), b.reshape(-1, n), float(dt), phi.reshape(-1, n, n), gamma.reshape(-1, n))
    grad_phi, grad_gamma = np.empty_like(a), np.empty_like(b)
    recurrence_backward(phi, gamma, u, x, grad_x, grad_phi, grad_gamma, grad_u)
    discretize_backward(a.reshape(-1, n, n), b.reshape(-1, n), float(dt), grad_phi.reshape(-1, n, n),
                        grad_gamma.reshape(-1, n), grad_a.reshape(-1, n, n), grad_b.reshape(-1, n))
    return grad_a, grad_b


def _numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class CompiledDiscretize(torch.autograd.Function):
    """(A (..., n, n), B (..., n), dt) -> (Phi, Gamma), as `pipe.model.ltv.discretize`, compiled: the two-state
    kernels for n = 2, with a Taylor degree that truncates below the dtype's rounding (`DEGREE_2X2`), the
    generic ones otherwise."""

    @staticmethod
    def forward(ctx, a: torch.Tensor, b: torch.Tensor, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
        n = a.shape[-1]
        a_np, b_np = _numpy(a).reshape(-1, n, n), _numpy(b).reshape(-1, n)
        phi, gamma = np.empty_like(a_np), np.empty_like(b_np)
        if n == 2:
            discretize2_forward(a_np, b_np, float(dt), DEGREE_2X2[a_np.dtype], phi, gamma)
        else:
            discretize_forward(a_np, b_np, float(dt), phi, gamma)
        ctx.save_for_backward(a, b)
        ctx.dt = float(dt)
        return torch.from_numpy(phi).view(a.shape), torch.from_numpy(gamma).view(b.shape)

    @staticmethod
    def backward(ctx, grad_phi: torch.Tensor, grad_gamma: torch.Tensor):
        a, b = ctx.saved_tensors
        n = a.shape[-1]
        a_np, b_np = _numpy(a).reshape(-1, n, n), _numpy(b).reshape(-1, n)
        grad_phi_np = _numpy(grad_phi.to(a.dtype)).reshape(-1, n, n)
        grad_gamma_np = _numpy(grad_gamma.to(b.dtype)).reshape(-1, n)
        grad_a, grad_b = np.empty_like(a_np), np.empty_like(b_np)
        if n == 2:
            discretize2_backward(a_np, b_np, ctx.dt, DEGREE_2X2[a_np.dtype], grad_phi_np, grad_gamma_np, grad_a, grad_b)
        else:
            discretize_backward(a_np, b_np, ctx.dt, grad_phi_np, grad_gamma_np, grad_a, grad_b)
        return torch.from_numpy(grad_a).view(a.shape), torch.from_numpy(grad_b).view(b.shape), None


class CompiledRecurrence(torch.autograd.Function):
    """(Phi (B, T, n, n), Gamma (B, T, n), u (B, T)) -> states (B, T + 1, n) from x_0 = 0, compiled."""

    @staticmethod
    def forward(ctx, phi: torch.Tensor, gamma: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        phi_np, gamma_np, u_np = _numpy(phi), _numpy(gamma), _numpy(u)
        x = np.empty((gamma_np.shape[0], gamma_np.shape[1] + 1, gamma_np.shape[2]), dtype=gamma_np.dtype)
        recurrence_forward(phi_np, gamma_np, u_np, x)
        states = torch.from_numpy(x)
        ctx.save_for_backward(phi, gamma, u, states)
        return states

    @staticmethod
    def backward(ctx, grad_states: torch.Tensor):
        phi, gamma, u, states = ctx.saved_tensors
        phi_np, gamma_np, u_np = _numpy(phi), _numpy(gamma), _numpy(u)
        grad_phi, grad_gamma, grad_u = np.empty_like(phi_np), np.empty_like(gamma_np), np.empty_like(u_np)
        recurrence_backward(phi_np, gamma_np, u_np, states.numpy(), _numpy(grad_states.to(states.dtype)), grad_phi,
                            grad_gamma, grad_u)
        return torch.from_numpy(grad_phi), torch.from_numpy(grad_gamma), torch.from_numpy(grad_u)


class CompiledSimulate2(torch.autograd.Function):
    """(A (B, T, 2, 2), B (B, T, 2), u (B, T), dt) -> states (B, T + 1, 2) from x_0 = 0: `CompiledDiscretize`
    and `CompiledRecurrence` of a two-state model in one kernel each way, the same numbers without the step
    matrices and their gradients as tensors in between."""

    @staticmethod
    def forward(ctx, a: torch.Tensor, b: torch.Tensor, u: torch.Tensor, dt: float) -> torch.Tensor:
        a_np, b_np, u_np = _numpy(a), _numpy(b), _numpy(u)
        x = np.empty((u_np.shape[0], u_np.shape[1] + 1, 2), dtype=a_np.dtype)
        simulate2_forward(a_np, b_np, u_np, float(dt), DEGREE_2X2[a_np.dtype], x)
        states = torch.from_numpy(x)
        ctx.save_for_backward(a, b, u, states)
        ctx.dt = float(dt)
        return states

    @staticmethod
    def backward(ctx, grad_states: torch.Tensor):
        a, b, u, states = ctx.saved_tensors
        a_np, b_np, u_np = _numpy(a), _numpy(b), _numpy(u)
        grad_a, grad_b, grad_u = np.empty_like(a_np), np.empty_like(b_np), np.empty_like(u_np)
        simulate2_backward(a_np, b_np, u_np, ctx.dt, DEGREE_2X2[a_np.dtype], states.numpy(),
                           _numpy(grad_states.to(states.dtype)), grad_a, grad_b, grad_u)
        return torch.from_numpy(grad_a), torch.from_numpy(grad_b), torch.from_numpy(grad_u), None
