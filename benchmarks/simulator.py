"""The simulator's backends side by side: forward + backward of `pipe.model.ltv.simulate` (discretisation
and recurrence), of the discretisation and of the recurrence alone, the torch loop against the compiled
kernels, at a long trajectory batch (10 x 2000 steps) and a whole conn epoch (120 x 400 steps), mds2 (n = 2),
float32 as in training. "generic" is the compiled path with the two-state discretisation
(`pipe.model.ltv_2x2`) swapped for the kernels of any size (`pipe.model.ltv_numba`, the augmented matrix),
what mds2 ran before 2026-11-25, as two kernels (discretisation, then recurrence). "simulate" is what
`ltv.simulate` runs: the torch loop, and for mds2 compiled the fused kernel (`CompiledSimulate2`, both steps
in one pass); "discretize, then recurrence" is the same computation as two kernels with the step matrices as
tensors in between. Median of --repeats after a warm-up call (numba compiles, or loads its cache, on the
first).

    python benchmarks/simulator.py [--repeats 5] [--threads 2]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from pipe.model import ltv, ltv_numba

# CompiledDiscretize looks its kernels up at each call, so swapping them here swaps what it runs
TWO_STATE = (ltv_numba.discretize2_forward, ltv_numba.discretize2_backward)
GENERIC = (lambda a, b, dt, degree, *out: ltv_numba.discretize_forward(a, b, dt, *out),    # no degree argument
           lambda a, b, dt, degree, *grads: ltv_numba.discretize_backward(a, b, dt, *grads))


def system(batch: int, steps: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    k = 1e3 * (0.1 + torch.rand(batch, steps, generator=g))
    c = 30.0 * (0.1 + torch.rand(batch, steps, generator=g))
    a = torch.zeros(batch, steps, 2, 2)
    a[..., 0, 1], a[..., 1, 0], a[..., 1, 1] = 1.0, -k, -c
    b = torch.stack([torch.zeros_like(k), 0.5 * k], -1)
    u = torch.cumsum(torch.rand(batch, steps, generator=g), 1) * 0.01
    return a, b, u


def timed(fn, inputs: tuple[torch.Tensor, ...], repeats: int) -> float:
    """Median seconds of forward + backward (the sum of the first state) over fresh leaf inputs."""
    times = []
    for _ in range(repeats + 1):           # the first call warms up (numba compiles or loads its cache)
        leaves = [t.clone().requires_grad_() for t in inputs]
        start = time.perf_counter()
        fn(*leaves)[..., 0].sum().backward()
        times.append(time.perf_counter() - start)
    return statistics.median(times[1:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    import numba
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    dt = 0.01
    print(f"threads {args.threads}, median of {args.repeats}, forward + backward, float32")
    print("| case | part | torch loop | compiled, generic | compiled | ratio to the loop | ratio to generic |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for batch, steps in ((10, 2000), (120, 400)):
        a, b, u = system(batch, steps)
        with torch.no_grad():
            phi, gamma = ltv.discretize_torch(a, b, dt)
        unfused = lambda a, b, u: ltv.recurrence(*ltv.discretize(a, b, dt), u)      # noqa: E731
        parts = {   # part: (function, inputs); for "simulate" the torch and generic columns run `unfused`
            "simulate": ((lambda a, b, u: ltv.simulate(a, b, u, dt)), (a, b, u)),
            "discretize, then recurrence": (unfused, (a, b, u)),
            "discretize": ((lambda a, b: torch.cat([t.flatten() for t in ltv.discretize(a, b, dt)])[:, None]),
                           (a, b)),
            "recurrence": (ltv.recurrence, (phi, gamma, u)),
        }
        for part, (fn, inputs) in parts.items():
            seconds = {}
            for name, backend, kernels in (("torch", "torch", TWO_STATE), ("generic", "compiled", GENERIC),
                                           ("compiled", "compiled", TWO_STATE)):
                ltv.set_backend(backend)
                ltv_numba.discretize2_forward, ltv_numba.discretize2_backward = kernels
                seconds[name] = timed(unfused if part == "simulate" and name != "compiled" else fn, inputs,
                                      args.repeats)
            ltv_numba.discretize2_forward, ltv_numba.discretize2_backward = TWO_STATE
            torch_ms, generic_ms, compiled_ms = (seconds[name] * 1e3 for name in ("torch", "generic", "compiled"))
            print(f"| {batch} x {steps} | {part} | {torch_ms:.2f} ms | {generic_ms:.3f} ms | {compiled_ms:.3f} ms | "
                  f"{torch_ms / compiled_ms:.0f}x | {generic_ms / compiled_ms:.1f}x |")
    ltv.set_backend("auto")


if __name__ == "__main__":
    main()
