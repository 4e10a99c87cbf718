"""The compiled simulator: `pipe.model.ltv`'s discretisation and recurrence as numba kernels inside
`torch.autograd.Function`s, with exact reverse-mode (adjoint) backward passes, also compiled.

- `CompiledDiscretize`: A (N, n, n), B (N, n) -> Phi = exp(A dt), Gamma = int_0^dt exp(A s) ds B, as the
  exponential of the augmented matrix M = dt [[A, B], [0, 0]] by scaling and squaring a degree-10 Taylor
  polynomial (||M / 2^s||_1 <= 1/4, truncation below 1e-14 relative). Its backward is the exact adjoint of
  that algorithm: the Horner steps and the squarings run in reverse.
- `CompiledRecurrence`: x_{k+1} = Phi_k x_k + Gamma_k u_k from x_0 = 0. Its backward is the adjoint
  recurrence lambda_k = g_k + Phi_k^T lambda_{k+1}, which gives the gradients of Phi, Gamma and u.

Both run on CPU float32 or float64 tensors (each dtype compiles once; sums accumulate in float64) and loop
over the batch in parallel (numba's `prange`, `numba.set_num_threads` caps the threads). Why by hand:
torch's `matrix_exp` and a Python loop over time launch thousands of tiny kernels per call; no library
offers a compiled batched small-matrix exponential with its adjoint or a compiled LTV recurrence.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

TAYLOR_DEGREE = 10
THETA = 0.25          # ||M / 2^s||_1 bound: 0.25^11 / 11! ~ 6e-15 truncation
MAX_SQUARINGS = 60    # ||M||_1 up to 2^58: beyond any physical stiffness in float64
CHUNKS = 64           # work items per kernel call, shared among numba's threads

_jit = numba.njit(cache=True, fastmath=False, parallel=True)
_jit_serial = numba.njit(cache=True, fastmath=False, inline="always")


@_jit_serial
def _matmul(x: np.ndarray, y: np.ndarray, out: np.ndarray, cx: float) -> None:
    """out = cx x y (n x n)."""
    n = x.shape[0]
    for i in range(n):
        for j in range(n):
            acc = 0.0
            for k in range(n):
                acc += x[i, k] * y[k, j]
            out[i, j] = cx * acc


@_jit_serial
def _matvec(x: np.ndarray, v: np.ndarray, out: np.ndarray, cx: float) -> None:
    """out = cx x v."""
    n = x.shape[0]
    for i in range(n):
        acc = 0.0
        for k in range(n):
            acc += x[i, k] * v[k]
        out[i] = cx * acc


@_jit_serial
def _matvec_t(x: np.ndarray, v: np.ndarray, out: np.ndarray, cx: float) -> None:
    """out = cx x^T v."""
    n = x.shape[0]
    for i in range(n):
        acc = 0.0
        for k in range(n):
            acc += x[k, i] * v[k]
        out[i] = cx * acc


@_jit_serial
def _squarings(x: np.ndarray, y: np.ndarray) -> int:
    """How often to halve M = [[x, y], [0, 0]] so that its 1-norm is at most THETA."""
    n = x.shape[0]
    norm = 0.0
    for j in range(n):
        col = 0.0
        for i in range(n):
            col += abs(x[i, j])
        norm = max(norm, col)
    col = 0.0
    for i in range(n):
        col += abs(y[i])
    norm = max(norm, col)
    s = 0
    while norm > THETA and s < MAX_SQUARINGS:
        norm *= 0.5
        s += 1
    return s


@_jit_serial
def _expm_forward(a: np.ndarray, b: np.ndarray, dt: float, x: np.ndarray, y: np.ndarray, hp: np.ndarray,
                  hv: np.ndarray, sp: np.ndarray, sv: np.ndarray) -> int:
    """exp(M) for M = dt [[a, b], [0, 0]], kept in block form [[P, p], [0, 1]] (every polynomial in M and
    every product of such blocks has that form); returns the number of squarings s.

    x, y: M's blocks scaled by 2^-s. Horner: P_d = I, p_d = 0, P_{j-1} = I + x P_j / j,
    p_{j-1} = (x p_j + y) / j, so exp(M / 2^s) ~ (P_0, p_0) = (sp[0], sv[0]); squarings:
    sp[i + 1] = sp[i]^2, sv[i + 1] = sp[i] sv[i] + sv[i]. All iterates are kept for the backward.
    """
    n = a.shape[0]
    for i in range(n):
        for j in range(n):
            x[i, j] = a[i, j] * dt
        y[i] = b[i] * dt
    s = _squarings(x, y)
    scale = 0.5 ** s
    for i in range(n):
        for j in range(n):
            x[i, j] *= scale
        y[i] *= scale
    hp[TAYLOR_DEGREE, :, :] = 0.0
    hv[TAYLOR_DEGREE, :] = 0.0
    for i in range(n):
        hp[TAYLOR_DEGREE, i, i] = 1.0
    for j in range(TAYLOR_DEGREE, 0, -1):
        _matmul(x, hp[j], hp[j - 1], 1.0 / j)
        _matvec(x, hv[j], hv[j - 1], 1.0 / j)
        for r in range(n):
            hp[j - 1, r, r] += 1.0
            hv[j - 1, r] += y[r] / j
    sp[0, :, :] = hp[0]
    sv[0, :] = hv[0]
    for i in range(s):
        _matmul(sp[i], sp[i], sp[i + 1], 1.0)
        _matvec(sp[i], sv[i], sv[i + 1], 1.0)
        for r in range(n):
            sv[i + 1, r] += sv[i, r]
    return s


@_jit
def discretize_forward(a: np.ndarray, b: np.ndarray, dt: float, phi: np.ndarray, gamma: np.ndarray) -> None:
    count, n = b.shape
    chunks = min(count, CHUNKS)
    for chunk in numba.prange(chunks):       # one workspace per chunk, not per matrix
        x, y = np.empty((n, n)), np.empty(n)
        hp, hv = np.empty((TAYLOR_DEGREE + 1, n, n)), np.empty((TAYLOR_DEGREE + 1, n))
        sp, sv = np.empty((MAX_SQUARINGS + 1, n, n)), np.empty((MAX_SQUARINGS + 1, n))
        for item in range(chunk * count // chunks, (chunk + 1) * count // chunks):
            s = _expm_forward(a[item], b[item], dt, x, y, hp, hv, sp, sv)
            phi[item] = sp[s]
            gamma[item] = sv[s]


@_jit
def discretize_backward(a: np.ndarray, b: np.ndarray, dt: float, grad_phi: np.ndarray, grad_gamma: np.ndarray,
                        grad_a: np.ndarray, grad_b: np.ndarray) -> None:
    """The exact adjoint of discretize_forward's algorithm, its steps in reverse (the forward is recomputed):
    squarings (S' = S S, g' = S g + g):  S_bar = S'_bar S^T + S^T S'_bar + g'_bar g^T, g_bar = S^T g'_bar + g'_bar;
    Horner (P' = I + x P / j, p' = (x p + y) / j):  x_bar += (P'_bar P^T + p'_bar p^T) / j, y_bar += p'_bar / j,
    P_bar = x^T P'_bar / j, p_bar = x^T p'_bar / j."""
    count, n = b.shape
    chunks = min(count, CHUNKS)
    for chunk in numba.prange(chunks):
        x, y = np.empty((n, n)), np.empty(n)
        hp, hv = np.empty((TAYLOR_DEGREE + 1, n, n)), np.empty((TAYLOR_DEGREE + 1, n))
        sp, sv = np.empty((MAX_SQUARINGS + 1, n, n)), np.empty((MAX_SQUARINGS + 1, n))
        adj_p, adj_v = np.empty((n, n)), np.empty(n)
        new_p, new_v = np.empty((n, n)), np.empty(n)
        grad_x, grad_y = np.empty((n, n)), np.empty(n)
        for item in range(chunk * count // chunks, (chunk + 1) * count // chunks):
            s = _expm_forward(a[item], b[item], dt, x, y, hp, hv, sp, sv)
            adj_p[:, :] = grad_phi[item]
            adj_v[:] = grad_gamma[item]
            for i in range(s - 1, -1, -1):
                sq, v = sp[i], sv[i]
                for r in range(n):
                    for c in range(n):
                        acc = adj_v[r] * v[c]
                        for k in range(n):
                            acc += adj_p[r, k] * sq[c, k] + sq[k, r] * adj_p[k, c]
                        new_p[r, c] = acc
                _matvec_t(sq, adj_v, new_v, 1.0)
                for r in range(n):
                    new_v[r] += adj_v[r]
                adj_p[:, :] = new_p
                adj_v[:] = new_v
            grad_x[:, :] = 0.0
            grad_y[:] = 0.0
            for j in range(1, TAYLOR_DEGREE + 1):
                hpj, hvj = hp[j], hv[j]
                for r in range(n):
                    grad_y[r] += adj_v[r] / j
                    for c in range(n):
                        acc = adj_v[r] * hvj[c]
                        for k in range(n):
                            acc += adj_p[r, k] * hpj[c, k]
                        grad_x[r, c] += acc / j
                for r in range(n):
                    for c in range(n):
                        acc = 0.0
                        for k in range(n):
                            acc += x[k, r] * adj_p[k, c]
                        new_p[r, c] = acc / j
                _matvec_t(x, adj_v, new_v, 1.0 / j)
                adj_p[:, :] = new_p
                adj_v[:] = new_v
            scale = 0.5 ** s * dt
            for r in range(n):
                for c in range(n):
                    grad_a[item, r, c] = grad_x[r, c] * scale
                grad_b[item, r] = grad_y[r] * scale


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


def _numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class CompiledDiscretize(torch.autograd.Function):
    """(A (..., n, n), B (..., n), dt) -> (Phi, Gamma), as `pipe.model.ltv.discretize`, compiled."""

    @staticmethod
    def forward(ctx, a: torch.Tensor, b: torch.Tensor, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
        n = a.shape[-1]
        a_np, b_np = _numpy(a).reshape(-1, n, n), _numpy(b).reshape(-1, n)
        phi, gamma = np.empty_like(a_np), np.empty_like(b_np)
        discretize_forward(a_np, b_np, float(dt), phi, gamma)
        ctx.save_for_backward(a, b)
        ctx.dt = float(dt)
        return torch.from_numpy(phi).view(a.shape), torch.from_numpy(gamma).view(b.shape)

    @staticmethod
    def backward(ctx, grad_phi: torch.Tensor, grad_gamma: torch.Tensor):
        a, b = ctx.saved_tensors
        n = a.shape[-1]
        a_np, b_np = _numpy(a).reshape(-1, n, n), _numpy(b).reshape(-1, n)
        grad_a, grad_b = np.empty_like(a_np), np.empty_like(b_np)
        discretize_backward(a_np, b_np, ctx.dt, _numpy(grad_phi.to(a.dtype)).reshape(-1, n, n),
                            _numpy(grad_gamma.to(b.dtype)).reshape(-1, n), grad_a, grad_b)
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
