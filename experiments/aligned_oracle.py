"""Issue 9: how much of the dynamic model's limit is the frame of p_z? (docs/experiments.md, "Trials aligned on
their final depth")

The oracle's identification (its starts, stopping rule and ridge: `oracle` on the recordings, `oracle_clean` on
the noise-free force) of a generated family's test parts, once on their trials as recorded (p_z from where the
robot started, whose gap to the part changes from trial to trial) and once aligned on their final depth
(`data.align_final_depth`, pipe.data.alignment), scored on the same trials as every method is. With --domain,
a paper domain's parts on the embedded dataset instead, any of them (training and validation parts too) with
--only. Rows (the domain's FIT(F) and each part's) are printed and appended to OUT as JSON lines. Usage (two
worker processes):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/aligned_oracle.py OUT.jsonl --family rect \
      --only rect_0000 rect_0001 [--frames recorded aligned]
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/aligned_oracle.py OUT.jsonl --domain dsub \
      --only dsub15 dsub25
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from common import append_row
from twin_oracle import identification_context, only_parts, run_config

from pipe.data.alignment import align_final_depth
from pipe.evaluation.evaluate import evaluate_methods
from pipe.model import ltv
from pipe.pipeline import load_domain

FRAMES = ("recorded", "aligned")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="JSON lines file the rows are appended to")
    ap.add_argument("--family", default="pins")
    ap.add_argument("--domain", choices=("dsub", "pins", "conn"), default=None,
                    help="a paper domain's parts on the embedded dataset instead of a family's test parts")
    ap.add_argument("--seed", type=int, default=0, help="the identification's random starts")
    ap.add_argument("--only", nargs="+", default=None, metavar="PART",
                    help="these test parts alone (with --domain: these parts, of any split)")
    ap.add_argument("--frames", nargs="+", default=list(FRAMES), choices=FRAMES)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    cfg = run_config(args.family, args.domain, args.seed)
    ltv.set_backend(cfg.simulator)
    data = load_domain(cfg)
    test = data.splits["test"]
    if args.only is not None:
        if args.domain is None:
            test = only_parts(test, args.only, args.family)
        else:
            test = only_parts([p for split in data.splits.values() for p in split], args.only, args.domain, "a part")
    for frame in args.frames:
        parts = test if frame == "recorded" else [align_final_depth(part) for part in test]
        start = time.perf_counter()
        ctx = identification_context(cfg, data, parts, args.seed, args.workers)
        for method, result in evaluate_methods(ctx, parts, ["oracle", "oracle_clean"]).items():
            append_row(args.out, {
                "family": args.domain or args.family, "seed": args.seed, "frame": frame, "method": method,
                "fit_F": result.domain["fit_F"], "seconds": time.perf_counter() - start,
                "parts": {p: m["fit_F"] for p, m in result.per_part.items()}})


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
