"""The `pipe` command line: `pipe data generate|check|pointcloud` and `pipe report curve`."""

from __future__ import annotations

import argparse
import sys
import textwrap
from pathlib import Path

from rich.console import Console
from rich.table import Table

from pipe.errors import PipeError

console = Console(highlight=False, width=None if sys.stdout.isatty() else 160)


def say(message: str, kind: str) -> None:
    """Print a problem as one wrapped paragraph on stderr."""
    print(textwrap.fill(f"{kind}: {message}", width=100, break_long_words=False), file=sys.stderr)


def fail(message: str) -> int:
    """Report a user error without a traceback; the exit status to return."""
    say(message, "error")
    return 2


def cmd_generate(args: argparse.Namespace) -> int:
    from pipe.synthetic import generate_dataset

    if args.count is not None and args.family is None:
        return fail("--count goes with --family: the number of parts of the family to generate")
    from pipe.synthetic.families import DEFAULT_COUNT

    parts = [p.strip() for p in args.parts.split(",") if p.strip()] if args.parts else None
    count = DEFAULT_COUNT if args.count is None else args.count
    out = generate_dataset(args.out, seed=args.seed, parts=parts, family=args.family, count=count)
    what = f"{count} parts of the {args.family} family" if args.family else "the synthetic dataset"
    console.print(f"wrote {what} to {out} (seed {args.seed}); check it with: pipe data check {out}")
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    from pipe.data.check import SUMMARY_HEADER, check_dataset, summary_rows, write_summary_json

    report = check_dataset(args.dir)
    if args.json:
        write_summary_json(report, args.json)
    if report.parts:
        table = Table(*SUMMARY_HEADER, title=f"dataset {report.root}")
        for row in summary_rows(report):
            table.add_row(*row)
        console.print(table)
    for warning in report.warnings:
        say(str(warning), "warning")
    if not report.ok:
        for problem in report.problems:
            say(str(problem), "error")
        print(f"{len(report.problems)} problem(s) found in {report.root}", file=sys.stderr)
        return 1
    console.print(f"ok: {len(report.parts)} parts, {sum(p.trials for p in report.parts)} trials")
    return 0


def cmd_pointcloud(args: argparse.Namespace) -> int:
    import numpy as np

    from pipe.data.preprocess import cloud_from_mesh

    cloud = cloud_from_mesh(args.mesh, args.units, args.points, seed=args.seed)
    extents = (cloud.points.max(axis=0) - cloud.points.min(axis=0)).astype(float)
    assumed = " (assumed from its size)" if args.units == "auto" else ""
    console.print(f"{args.mesh}: read in {cloud.mesh.units}{assumed}; {len(cloud.points)} points, "
                  f"extents {np.round(extents, 2).tolist()} mm, centred on the {cloud.centre_method} centre "
                  f"{np.round(cloud.centre, 3).tolist()} mm, watertight: {cloud.mesh.watertight}")
    if args.out:
        np.save(args.out, cloud.points)
        console.print(f"wrote {args.out}")
    return 0


def cmd_curve(args: argparse.Namespace) -> int:
    from pipe.evaluation.curve import write_curve

    written = write_curve(args.folders, args.out)
    console.print(f"wrote {', '.join(str(p) for p in written)}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pipe", description="PIPE: contact models of assembly tasks from CAD.")
    kinds = parser.add_subparsers(dest="kind", required=True)
    data = kinds.add_parser("data", help="datasets: generate the synthetic one, check any one")
    verbs = data.add_subparsers(dest="verb", required=True)

    gen = verbs.add_parser("generate", help="write the synthetic dataset of the paper's 27 parts, or of a family")
    gen.add_argument("out", type=Path, help="output folder (a generated dataset there is replaced)")
    gen.add_argument("--seed", type=int, default=0)
    chosen = gen.add_mutually_exclusive_group()
    chosen.add_argument("--parts", help="comma-separated part names (default: all 27)")
    chosen.add_argument("--family", help="parts of a parametric family instead: dsub, rect or pins (docs/synthetic.md)")
    gen.add_argument("--count", type=int, help="how many parts of the family (default 100)")
    gen.set_defaults(run=cmd_generate)

    check = verbs.add_parser("check", help="validate a dataset folder and summarise each part")
    check.add_argument("dir", type=Path)
    check.add_argument("--json", type=Path, help="also write the summary as JSON (for `dvc metrics show`)")
    check.set_defaults(run=cmd_check)

    cloud = verbs.add_parser("pointcloud", help="sample a mesh into the centred point cloud the encoder sees")
    cloud.add_argument("mesh", type=Path)
    cloud.add_argument("--points", type=int, default=1024)
    cloud.add_argument("--units", default="auto", help="length unit of the mesh file, or 'auto' (default)")
    cloud.add_argument("--seed", type=int, default=0)
    cloud.add_argument("--out", type=Path, help="write the points (n x 3, mm) as .npy")
    cloud.set_defaults(run=cmd_pointcloud)

    report = kinds.add_parser("report", help="summaries over finished runs")
    report_verbs = report.add_subparsers(dest="verb", required=True)
    curve = report_verbs.add_parser("curve", help="the learning curve: held-out FIT(F) against the number of "
                                                  "training parts, from learning-curve sweeps (README)")
    curve.add_argument("folders", type=Path, nargs="+", help="one sweep folder per family (its runs' subfolders)")
    curve.add_argument("--out", type=Path, required=True, help="folder for learning_curve.json, .md and .png")
    curve.set_defaults(run=cmd_curve)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except PipeError as err:
        return fail(str(err))


if __name__ == "__main__":
    sys.exit(main())
