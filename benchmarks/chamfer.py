"""The Chamfer loss's nearest-pair search two ways, side by side: torch's (one batched matrix product and an
argmin per direction, through the (B, n, m) distance ranking) and pipe's numba kernel (both directions in
one pass over the point pairs, no matrix). Both give the same pairs (checked here, and against brute force
in tests/test_model_math.py). Then the whole loss, forward + backward. Stage 1's sizes: batch 10, 1024
points per cloud; median of --repeats.

    python benchmarks/chamfer.py [--repeats 9]
"""

from __future__ import annotations

import argparse

import torch
from timing import median_seconds

from pipe.model import chamfer as module


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9)
    args = parser.parse_args()
    g = torch.Generator().manual_seed(0)
    x, y = torch.randn(10, 1024, 3, generator=g), torch.randn(10, 1024, 3, generator=g)
    torch_pairs = (module._nearest(x, y), module._nearest(y, x))
    compiled_pairs = module.nearest_pairs(x, y)
    assert all(torch.equal(a, b) for a, b in zip(torch_pairs, compiled_pairs)), "the two searches disagree"

    def loss() -> None:
        leaf = x.clone().requires_grad_()
        module.chamfer(leaf, y).sum().backward()

    compiled = {"search": median_seconds(lambda: module.nearest_pairs(x, y), args.repeats),
                "loss": median_seconds(loss, args.repeats)}
    numba = module.numba
    module.numba = None                     # the torch fallback
    try:
        fallback = {"search": median_seconds(lambda: module.nearest_pairs(x, y), args.repeats),
                    "loss": median_seconds(loss, args.repeats)}
    finally:
        module.numba = numba
    print(f"threads {torch.get_num_threads()}, median of {args.repeats}, batch 10 x 1024 points")
    print("| part | torch | compiled | ratio |")
    print("| --- | --- | --- | --- |")
    for part, label in (("search", "nearest pairs, both directions"), ("loss", "Chamfer loss, forward + backward")):
        print(f"| {label} | {fallback[part] * 1e3:.2f} ms | {compiled[part] * 1e3:.2f} ms | "
              f"{fallback[part] / compiled[part]:.1f}x |")


if __name__ == "__main__":
    main()
