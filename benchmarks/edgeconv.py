"""EdgeConv three ways, side by side: the textbook per-edge convolution, the per-point projection with
batch norm and activation on every edge (pipe before 0.3), and pipe's layer (batch norm and activation
after the max, statistics from per-point sums). All three give the same output (checked here, and with
gradients in tests/test_model_math.py). Times DGCNN's four EdgeConv layers, forward + backward, in
training mode at the paper's batch and cloud size; median of --repeats.

    python benchmarks/edgeconv.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from timing import print_ratio_table

from pipe.plugins.encoder.dgcnn import EdgeConv, gather_neighbours, knn


def per_edge(layer: EdgeConv, x: torch.Tensor) -> torch.Tensor:
    """The textbook: build the (B, 2C, n, k) edge features, then convolve, normalise, activate, max."""
    neighbours = gather_neighbours(x, knn(x, layer.k))
    centre = x.unsqueeze(-1).expand_as(neighbours)
    edges = torch.nn.functional.conv2d(torch.cat([centre, neighbours - centre], 1), layer.weight.unsqueeze(-1))
    return layer.act(layer.norm(edges)).max(dim=-1).values


def projected_per_edge_norm(layer: EdgeConv, x: torch.Tensor) -> torch.Tensor:
    """Projection per point, then batch norm and activation on the (B, C, n, k) edges, then max."""
    c_in = x.shape[1]
    w_centre, w_offset = layer.weight[:, :c_in, 0], layer.weight[:, c_in:, 0]
    own = torch.einsum("oc,bcn->bon", w_centre - w_offset, x)
    neighbour = torch.einsum("oc,bcn->bon", w_offset, x)
    edges = own.unsqueeze(-1) + gather_neighbours(neighbour, knn(x, layer.k))
    return layer.act(layer.norm(edges)).max(dim=-1).values


def stack_time(forward, layers, x: torch.Tensor, repeats: int) -> float:
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        h, outs = x, []
        for layer in layers:
            h = forward(layer, h)
            outs.append(h)
        torch.cat([o.max(dim=2).values for o in outs], 1).sum().backward()
        times.append(time.perf_counter() - start)
    return statistics.median(times[1:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--points", type=int, default=1024)
    parser.add_argument("--k", type=int, default=20)
    args = parser.parse_args()
    torch.manual_seed(0)
    channels = (64, 64, 128, 256)
    layers = [EdgeConv(c_in, c_out, args.k) for c_in, c_out in zip((3, *channels[:-1]), channels)]
    x = torch.randn(10, 3, args.points)
    variants = {"per-edge convolution (textbook)": per_edge,
                "per-point projection, per-edge batch norm": projected_per_edge_norm,
                "pipe: batch norm and activation after the max": lambda layer, h: layer(h)}
    with torch.no_grad():
        for layer in layers:
            layer.eval()
        outputs = [fn(layers[0], x) for fn in variants.values()]
        assert all(torch.allclose(out, outputs[0], atol=1e-5) for out in outputs)
        for layer in layers:
            layer.train()
    seconds = {name: stack_time(fn, layers, x, args.repeats) for name, fn in variants.items()}
    print(f"EdgeConv stack {channels}, batch 10, {args.points} points, k = {args.k}, forward + backward, "
          f"median of {args.repeats}, {torch.get_num_threads()} threads")
    print_ratio_table("EdgeConv stack", seconds)


if __name__ == "__main__":
    main()
