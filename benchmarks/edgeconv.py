"""EdgeConv: the textbook per-edge 1x1 convolution vs pipe's per-point projection, side by side.

Both compute LeakyReLU(BN(W [x_i, x_j - x_i])) max-pooled over k neighbours (identical outputs, checked
here too). Times one DGCNN-sized layer stack forward + backward at the paper's batch and cloud size.

    python benchmarks/edgeconv.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import time

import torch

from pipe.plugins.encoder.dgcnn import EdgeConv, gather_neighbours, knn


def per_edge(layer: EdgeConv, x: torch.Tensor) -> torch.Tensor:
    """The reference: build the (B, 2C, n, k) edge features, then convolve them."""
    neighbours = gather_neighbours(x, knn(x, layer.k))
    centre = x.unsqueeze(-1).expand_as(neighbours)
    edges = torch.nn.functional.conv2d(torch.cat([centre, neighbours - centre], 1), layer.weight.unsqueeze(-1))
    return layer.act(layer.norm(edges)).max(dim=-1).values


def stack_time(forward, layers, x: torch.Tensor, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        h, outs = x, []
        for layer in layers:
            h = forward(layer, h)
            outs.append(h)
        torch.cat([o.max(dim=2).values for o in outs], 1).sum().backward()
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--points", type=int, default=1024)
    parser.add_argument("--k", type=int, default=20)
    args = parser.parse_args()
    torch.manual_seed(0)
    channels = (64, 64, 128, 256)
    layers = [EdgeConv(c_in, c_out, args.k) for c_in, c_out in zip((3, *channels[:-1]), channels)]
    x = torch.randn(10, 3, args.points)
    with torch.no_grad():
        for layer in layers:
            layer.eval()
        assert torch.allclose(layers[0](x), per_edge(layers[0], x), atol=1e-5)
        for layer in layers:
            layer.train()
    reference = stack_time(per_edge, layers, x, args.repeats)
    projected = stack_time(lambda layer, h: layer(h), layers, x, args.repeats)
    print(f"EdgeConv stack (64, 64, 128, 256), batch 10, {args.points} points, k = {args.k}, "
          f"forward + backward, best of {args.repeats}, {torch.get_num_threads()} threads")
    print(f"  per-edge convolution : {reference:.3f} s")
    print(f"  per-point projection : {projected:.3f} s")
    print(f"  ratio                : {reference / projected:.2f}x")


if __name__ == "__main__":
    main()
