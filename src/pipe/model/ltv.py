"""Exact discretisation and simulation of linear time-varying ODEs x' = A(t) x + B(t) u(t).

Over each sample period the parameters and the input are held at their midpoint values and the step is
solved exactly with the matrix exponential (zero-order hold on the midpoint). For a Hurwitz A (all
positive coefficients of a mass-spring-damper) the step matrix has spectral radius below one whatever the
stiffness, so the recursion cannot blow up; it is differentiable and batched.

Two implementations give the same numbers (tests/test_simulator.py):
- "compiled" (`pipe.model.ltv_numba`): numba kernels with exact adjoint backward passes; they run on the CPU,
  and tensors on another device (a GPU) are copied to it and the results back, autograd carrying the
  gradients across the copies;
- "torch": `torch.linalg.matrix_exp` and a Python loop over time; on the tensors' own device, the reference.
The backend is "auto" by default: compiled wherever numba imports, whatever the size, torch otherwise. A size
threshold once kept small work on the loop, so that predict.py would not load the kernels for one trajectory
(0.6 s, once per process); it sent stage 2's batches, a distributed fit's half batches and then the
evaluation's trial-by-trial predictions to the loop (about 26 s of conn's evaluation), which takes about
30 ms for one trial of 487 samples on two cores where the kernels take 0.05 ms (BENCHMARKS.md, "The
simulator in the evaluation"). On a GPU the loop launches a few small kernels per time step, forward and
backward: with it, stage 2 of conn took 263 s on an H200 against 12 s on two CPU cores (BENCHMARKS.md), so
CUDA tensors take the compiled kernels too. Choose one with `set_backend`, the `PIPE_SIMULATOR`
environment variable or train.py's `simulator=` option.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from functools import cache
from types import ModuleType
from typing import Any

import torch

from pipe.errors import PipeError

BACKENDS = ("auto", "compiled", "torch")
_COMPILED_DTYPES = (torch.float32, torch.float64)
_backend = "auto"


def set_backend(name: str) -> None:
    """Choose the simulator: "auto", "compiled" (fails if numba is missing) or "torch"."""
    global _backend
    if name not in BACKENDS:
        raise PipeError(f"unknown simulator {name!r}; choose one of {', '.join(BACKENDS)}")
    if name == "compiled" and _compiled() is None:
        raise PipeError("simulator=compiled needs numba (pip install numba); simulator=torch works without it")
    _backend = name


def get_backend() -> str:
    return _backend


def compiled_available() -> bool:
    """Whether the compiled kernels load here (numba installed)."""
    return _compiled() is not None


@cache
def _compiled() -> ModuleType | None:
    """The numba kernels, imported (and compiled from numba's cache) on first use; None without numba."""
    try:
        from pipe.model import ltv_numba
    except ImportError:
        return None
    return ltv_numba


def _use_compiled(*tensors: torch.Tensor) -> bool:
    """Compiled for float32/float64 tensors of one dtype on one device unless "torch" is chosen or numba is
    missing."""
    if _backend == "torch" or any(t.dtype not in _COMPILED_DTYPES for t in tensors):
        return False
    if len({t.device for t in tensors}) != 1 or len({t.dtype for t in tensors}) != 1:
        return False
    return _compiled() is not None


def _on_the_cpu(function: Callable[..., Any], *tensors: torch.Tensor, dt: float | None = None) -> Any:
    """`function` (a compiled kernel's autograd Function) on CPU copies of `tensors`, its results returned to
    their device; `.cpu()` and `.to()` are differentiable, so the gradients travel back the same way (on CPU
    tensors both return the tensor itself)."""
    device = tensors[0].device
    result = function(*(t.cpu() for t in tensors), *(() if dt is None else (dt,)))
    return tuple(r.to(device) for r in result) if isinstance(result, tuple) else result.to(device)


def discretize(a: torch.Tensor, b: torch.Tensor, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A (..., n, n), B (..., n) -> Phi = exp(A dt) (..., n, n), Gamma = int_0^dt exp(A s) ds B (..., n)."""
    if _use_compiled(a, b):
        return _on_the_cpu(_compiled().CompiledDiscretize.apply, a, b, dt=dt)
    return discretize_torch(a, b, dt)


def discretize_torch(a: torch.Tensor, b: torch.Tensor, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
    """`discretize` through the exponential of the augmented matrix dt [[A, B], [0, 0]]."""
    n = a.shape[-1]
    augmented = torch.zeros(*a.shape[:-2], n + 1, n + 1, dtype=a.dtype, device=a.device)
    augmented[..., :n, :n] = a * dt
    augmented[..., :n, n] = b * dt
    step = torch.linalg.matrix_exp(augmented)
    return step[..., :n, :n], step[..., :n, n]


def recurrence(phi: torch.Tensor, gamma: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """States (B, T + 1, n) of x_{k+1} = Phi_k x_k + Gamma_k u_k from x_0 = 0; Phi (B, T, n, n),
    Gamma (B, T, n), u (B, T)."""
    if _use_compiled(phi, gamma, u):
        return _on_the_cpu(_compiled().CompiledRecurrence.apply, phi, gamma, u)
    return recurrence_torch(phi, gamma, u)


def recurrence_torch(phi: torch.Tensor, gamma: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """`recurrence` as a Python loop over time (autograd records every step)."""
    drive = gamma * u.unsqueeze(-1)
    x = torch.zeros(u.shape[0], phi.shape[-1], dtype=phi.dtype, device=phi.device)
    states = [x]
    for k in range(u.shape[1]):
        x = torch.einsum("bij,bj->bi", phi[:, k], x) + drive[:, k]
        states.append(x)
    return torch.stack(states, dim=1)


def midpoints(x: torch.Tensor) -> torch.Tensor:
    """Averages of consecutive samples along dim 1: (B, T, ...) -> (B, T - 1, ...)."""
    return 0.5 * (x[:, 1:] + x[:, :-1])


def simulate(a: torch.Tensor, b: torch.Tensor, u: torch.Tensor, dt: float) -> torch.Tensor:
    """States (B, T, n) from zero initial state; A (B, T-1, n, n) and B (B, T-1, n) act over each period
    and u (B, T-1) is the input over it."""
    two_states = a.shape == (*u.shape, 2, 2) and b.shape == (*u.shape, 2)     # and nothing broadcast
    if two_states and _use_compiled(a, b, u):
        return _on_the_cpu(_compiled().CompiledSimulate2.apply, a, b, u, dt=dt)  # both steps in one kernel
    phi, gamma = discretize(a, b, dt)
    return recurrence(phi, gamma, u)


if os.environ.get("PIPE_SIMULATOR"):
    set_backend(os.environ["PIPE_SIMULATOR"])   # an unknown name fails here, naming the choices
