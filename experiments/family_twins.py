"""Issue 9, the pins target: how many of a generated family's test parts have a training part of the same
standard size at each size of the learning curve's training set (docs/experiments.md, "The head fed the
cross-section and the slices").

`nearest` is PIPE's own head read at the input of the training part nearest to the test part, so where the two
parts are the same standard size the two methods predict nearly alike. Pins come in ISO diameters and lengths
(`pipe.synthetic.families`); a pin's twin here is a training pin of its type and diameter, and its exact twin
one of its length too (they may differ by their lead-in). Plugs' sizes are drawn from continuous ranges, so
the count is for pins. Usage:
  python experiments/family_twins.py --sizes 5 10 20 50 100
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from parameter_codes import generator_parts
from twin_oracle import family_config

from pipe.pipeline import load_domain
from pipe.synthetic.catalogue import Pin


def twin_counts(test: list[Pin], train: list[Pin]) -> tuple[int, int]:
    """How many of `test` have a pin of their type and diameter in `train`, and how many one of their length too."""
    sizes = {(p.family, p.diameter) for p in train}
    exact = {(p.family, p.diameter, p.length) for p in train}
    return (sum((p.family, p.diameter) in sizes for p in test),
            sum((p.family, p.diameter, p.length) in exact for p in test))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[5, 10, 20, 50, 100],
                    help="numbers of training parts (the curve's training sets are nested: each adds parts)")
    args = ap.parse_args()
    cfg = family_config("pins", 0)
    data = load_domain(cfg)
    drawn = generator_parts(cfg)
    test = [drawn[p.name] for p in data.splits["test"]]
    train = [drawn[p.name] for p in data.splits["train"]]
    if max(args.sizes) > len(train):
        raise SystemExit(f"the curve's largest training set has {len(train)} parts, not {max(args.sizes)}")
    print("| training pins | test pins with a training pin of their type and diameter | ... and length |")
    print("| --- | --- | --- |")
    for size in args.sizes:
        same_size, same_length = twin_counts(test, train[:size])
        print(f"| {size} | {same_size} of {len(test)} | {same_length} of {len(test)} |")


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
