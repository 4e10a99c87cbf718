"""PointNet's feature network two ways, side by side: the layers as written (the last convolution, batch
norm and ReLU on every point, then the max pool) and pipe's training path (`max_pooled_conv_norm_relu`:
the max taken before batch norm and ReLU, the batch statistics from the input's covariance). Both give
the same features (checked here, and with gradients and running statistics in tests/test_model_math.py).
Forward + backward in training mode at the paper's batch and cloud size; median of --repeats.

    python benchmarks/pointnet.py [--repeats 9]
"""

from __future__ import annotations

import argparse

import torch
from timing import median_seconds, print_ratio_table

from pipe.plugins.encoder.pointnet import PointNetVAE


def layers_as_written(model: PointNetVAE, points: torch.Tensor) -> torch.Tensor:
    return model.convs(points.transpose(1, 2)).max(dim=2).values


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--points", type=int, default=1024)
    args = parser.parse_args()
    torch.manual_seed(0)
    model = PointNetVAE(num_points=args.points).train()
    points = torch.randn(10, args.points, 3)
    variants = {"layers as written": layers_as_written, "pipe": lambda m, p: m.features(p)}
    expected, got = (fn(model, points) for fn in variants.values())
    torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-4)
    seconds = {name: median_seconds(lambda fn=fn: fn(model, points).sum().backward(), args.repeats)
               for name, fn in variants.items()}
    print(f"PointNet features, batch 10, {args.points} points, forward + backward, training mode, "
          f"median of {args.repeats}, {torch.get_num_threads()} threads")
    print_ratio_table("feature network", seconds, milliseconds=True)


if __name__ == "__main__":
    main()
