"""Exact discretisation and simulation of linear time-varying ODEs x' = A(t) x + B(t) u(t).

Over each sample period the parameters and the input are held at their midpoint values and the step is
solved exactly with the matrix exponential (zero-order hold on the midpoint). For a Hurwitz A (all
positive coefficients of a mass-spring-damper) the step matrix has spectral radius below one whatever the
stiffness, so the recursion cannot blow up; it is differentiable and batched. The recursion itself is a
short loop over time with (n x n) products.
"""

from __future__ import annotations

import torch


def discretize(a: torch.Tensor, b: torch.Tensor, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A (..., n, n), B (..., n) -> Phi = exp(A dt) (..., n, n), Gamma = int_0^dt exp(A s) ds B (..., n)."""
    n = a.shape[-1]
    augmented = torch.zeros(*a.shape[:-2], n + 1, n + 1, dtype=a.dtype, device=a.device)
    augmented[..., :n, :n] = a * dt
    augmented[..., :n, n] = b * dt
    step = torch.linalg.matrix_exp(augmented)
    return step[..., :n, :n], step[..., :n, n]


def midpoints(x: torch.Tensor) -> torch.Tensor:
    """Averages of consecutive samples along dim 1: (B, T, ...) -> (B, T - 1, ...)."""
    return 0.5 * (x[:, 1:] + x[:, :-1])


def simulate(a: torch.Tensor, b: torch.Tensor, u: torch.Tensor, dt: float) -> torch.Tensor:
    """States (B, T, n) from zero initial state; A (B, T-1, n, n) and B (B, T-1, n) act over each period
    and u (B, T-1) is the input over it."""
    phi, gamma = discretize(a, b, dt)
    drive = gamma * u.unsqueeze(-1)
    x = torch.zeros(u.shape[0], a.shape[-1], dtype=a.dtype, device=a.device)
    states = [x]
    for k in range(u.shape[1]):
        x = torch.einsum("bij,bj->bi", phi[:, k], x) + drive[:, k]
        states.append(x)
    return torch.stack(states, dim=1)
