"""The `pipe` command line: `pipe data generate|import|check|pointcloud|preprocess`, `pipe params`, `pipe report
curve|summary`, `pipe kernels`."""

from __future__ import annotations

import argparse
import sys
import textwrap
from pathlib import Path

from rich.console import Console
from rich.table import Table

from pipe.errors import PipeError, debugging
from pipe.settings import KERNELS as KERNEL_CHOICES
from pipe.settings import POSITIVE, SEED, WHOLE_FROM_0, WHOLE_FROM_1, argument_type

console = Console(highlight=False, width=None if sys.stdout.isatty() else 160)


def say(message: str, kind: str) -> None:
    """Print a problem as one wrapped paragraph on stderr."""
    print(textwrap.fill(f"{kind}: {message}", width=100, break_long_words=False,
                        break_on_hyphens=False), file=sys.stderr)


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


def cmd_import(args: argparse.Namespace) -> int:
    from pipe.importing.dataset_import import REPORT_FILE, import_dataset
    from pipe.importing.insertion import InsertionSettings
    from pipe.importing.readers import ReaderOptions, TableColumns

    tf = tuple(args.tf.split(",")) if args.tf else None
    if tf is not None and (len(tf) != 2 or not all(tf)):
        return fail(f"--tf takes two frame ids, PARENT,CHILD (e.g. base,tool0), got {args.tf!r}")
    if args.format in ("rtde", "ur_rtde") and (args.columns or args.force_frame != "base"):
        return fail(f"--columns and --force-frame describe other formats; the {args.format} format has fixed "
                    "columns in the base frame")
    options = ReaderOptions(columns=TableColumns.parse(args.columns) if args.columns else TableColumns(),
                            time_unit=args.time_unit, position_unit=args.position_unit, delimiter=args.delimiter,
                            force_in_tool_frame=args.force_frame == "tool", wrench_topic=args.wrench_topic,
                            pose_topic=args.pose_topic, tf_frames=tf, wrench_data=args.wrench_data,
                            wrench_time=args.wrench_time, pose_data=args.pose_data, pose_time=args.pose_time,
                            quaternion=args.quaternion)
    settings = InsertionSettings(axis=args.axis, direction=args.direction, frame=args.frame,
                                 force_sign=args.force_sign, contact_threshold_n=args.contact_threshold,
                                 contact_min_s=args.contact_min_duration, approach_s=args.approach,
                                 retreat_mm=args.retreat, bias_s=args.bias_window)
    result = import_dataset(args.out, args.format, args.recordings, args.meshes, args.mapping, args.mesh_units,
                            args.name, options, settings, args.mesh_axis)
    if result.problems:
        for problem in result.problems:
            say(str(problem), "error")
        print(f"{len(result.problems)} problem(s); nothing was written to {args.out}", file=sys.stderr)
        return 1
    table = Table("part", "trial", "kept [s]", "contact at [s]", "retreat cut", "depth max [mm]", "force max [N]",
                  title=f"imported into {result.out}")
    for r in result.reports:
        table.add_row(r["part"], r["trial"], f"{r['kept_from_s']:.2f} to {r['kept_to_s']:.2f}",
                      f"{r['contact_at_s']:.3f}", "yes" if r["retreat_cut"] else "no", f"{r['depth_max_mm']:.2f}",
                      f"{r['force_max_n']:.2f}")
    console.print(table)
    for warning in result.warnings + [f"{r['file']}: {w}" for r in result.reports for w in r["warnings"]]:
        say(warning, "warning")
    console.print(f"wrote {len(result.reports)} trials of {len(result.trials)} parts (what was cut and why: "
                  f"{result.out / REPORT_FILE}); check it with: pipe data check {result.out}")
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

    cloud = cloud_from_mesh(args.mesh, args.units, args.points, seed=args.seed, axis=args.axis)
    extents = (cloud.points.max(axis=0) - cloud.points.min(axis=0)).astype(float)
    assumed = " (assumed from its size)" if args.units == "auto" else ""
    console.print(f"{args.mesh}: read in {cloud.mesh.units}{assumed}; {len(cloud.points)} points, "
                  f"extents {np.round(extents, 2).tolist()} mm, centred on the {cloud.centre_method} centre "
                  f"{np.round(cloud.centre, 3).tolist()} mm, watertight: {cloud.mesh.watertight}")
    if args.out:
        np.save(args.out, cloud.points)
        console.print(f"wrote {args.out}")
    return 0


def cmd_preprocess(args: argparse.Namespace) -> int:
    from importlib.resources import files

    from omegaconf import OmegaConf

    from pipe.data.prepared import PreprocessSettings, write_prepared

    defaults = OmegaConf.load(files("pipe.conf").joinpath("data", "recorded.yaml"))   # train.py's data settings
    given = {name: getattr(args, name) for name in ("points", "cloud_seed", "rate_hz", "steady_samples")}
    settings = PreprocessSettings.from_config({k: defaults[k] if v is None else v for k, v in given.items()})
    parts = write_prepared(args.dataset, args.out, settings)
    console.print(f"wrote {len(parts)} preprocessed parts of {args.dataset} to {args.out} ({settings}); train on "
                  f"them with data.prepared={args.out}", markup=False)
    return 0


def cmd_curve(args: argparse.Namespace) -> int:
    from pipe.evaluation.curve import write_curve

    written = write_curve(args.folders, args.out)
    console.print(f"wrote {', '.join(str(p) for p in written)}")
    return 0


def cmd_summary(args: argparse.Namespace) -> int:
    from pipe.errors import read_yaml_mapping
    from pipe.evaluation.summary import write_summary

    domains = None
    if args.params is not None:
        domains = list(read_yaml_mapping(args.params, missing="params file does not exist").get("domains") or [])
        if not domains:
            return fail(f"{args.params}: names no domains (a list under `domains`)")
    written = write_summary(args.runs, args.out, domains)
    console.print(f"wrote {', '.join(str(p) for p in written)}")
    return 0


def cmd_params(args: argparse.Namespace) -> int:
    from pipe.params import compose_params

    compose_params(args.out, args.overrides)
    given = f" with {' '.join(args.overrides)}" if args.overrides else ""
    console.print(f"wrote {args.out} (conf/pipeline.yaml{given})", markup=False)
    return 0


def cmd_kernels(args: argparse.Namespace) -> int:
    from pipe.kernels import shell_lines

    print(shell_lines(args.choice))
    return 0


def add_import_parser(verbs: argparse._SubParsersAction) -> None:
    from pipe.importing.insertion import FRAMES, InsertionSettings
    from pipe.importing.readers import READERS, TIME_UNITS, ReaderOptions

    default = InsertionSettings()
    formats = "; ".join(f"{r.name}: {r.summary}" for r in READERS.values())
    imp = verbs.add_parser("import", help="convert robot recordings and CAD meshes into a dataset folder",
                           description="Cut each recording to one insertion (README, 'Bringing your own "
                                       f"recordings') and write the dataset. Formats: {formats}.")
    imp.add_argument("out", type=Path, help="output dataset folder (an earlier dataset there is replaced)")
    imp.add_argument("--format", required=True, choices=list(READERS))
    imp.add_argument("--recordings", type=Path, required=True,
                     help="folder with a subfolder of recordings per part (or give --mapping)")
    imp.add_argument("--meshes", type=Path, required=True,
                     help="folder with one <part>.<ext> per part (STL, OBJ, PLY, OFF, GLB/glTF, 3MF, STEP, IGES)")
    imp.add_argument("--mapping", type=Path, help="CSV (recording,part) or YAML (recording: part) file")
    imp.add_argument("--mesh-units", default="mm", help="length unit of STL, OBJ, PLY and OFF files (default mm; "
                                                        "the other formats carry their own)")
    imp.add_argument("--mesh-axis", metavar="AXIS[,PART=AXIS...]",
                     help="the meshes' insertion axis, turned onto z: x, y, z (default), -x, -y, -z or principal (the "
                          "long axis); for all parts and/or per part, e.g. z,screw=x")
    imp.add_argument("--name", help="dataset name (default: the folder's name)")
    options = ReaderOptions()
    table = imp.add_argument_group("generic tables (--format table)")
    table.add_argument("--columns", help="column mapping, e.g. time=t,pz=tcp_z,fz=force_z (p position, f force, "
                                         "r rotation vector; axes x, y, z)")
    table.add_argument("--time-unit", default=options.time_unit, choices=list(TIME_UNITS))
    table.add_argument("--position-unit", default=options.position_unit,
                       help="length unit of the positions of tables and HDF5 files (default m)")
    table.add_argument("--delimiter", default=options.delimiter, help="CSV delimiter (default ','; ' ' for any "
                                                                      "whitespace)")
    table.add_argument("--force-frame", default="base", choices=FRAMES,
                       help="frame of the force (tables, bags, HDF5): base (the robot's, default) or tool (a wrist "
                            "sensor)")
    streams = imp.add_argument_group("ROS bags (--format rosbag) and HDF5 files (--format hdf5)")
    streams.add_argument("--wrench-topic", default=options.wrench_topic, help="WrenchStamped topic")
    streams.add_argument("--pose-topic", default=options.pose_topic, help="PoseStamped topic of the TCP")
    streams.add_argument("--tf", metavar="PARENT,CHILD", help="take the TCP pose from /tf between these frames")
    for key in ("wrench_data", "wrench_time", "pose_data", "pose_time"):
        streams.add_argument(f"--{key.replace('_', '-')}", default=getattr(options, key),
                             help=f"HDF5 dataset name (default {getattr(options, key)})")
    streams.add_argument("--quaternion", default=options.quaternion, choices=("xyzw", "wxyz"),
                         help="HDF5 quaternion order (default xyzw)")
    cut = imp.add_argument_group("cutting each recording to one insertion")
    cut.add_argument("--axis", default=default.axis, choices=list("xyz"), help="insertion axis (default z)")
    cut.add_argument("--direction", type=int, choices=(1, -1),
                     help="way the tool moves along the axis while inserting (default -1 in the base frame, "
                          "+1 in the tool frame)")
    cut.add_argument("--frame", default=default.frame, choices=FRAMES, help="frame of the axis (default base)")
    cut.add_argument("--force-sign", type=int, default=default.force_sign, choices=(1, -1),
                     help="1: the force acts on the tool (UR's actual_TCP_force, default); -1: the tool's force")
    cut.add_argument("--contact-threshold", type=float, default=default.contact_threshold_n,
                     help=f"N the resisting force must exceed (default {default.contact_threshold_n:g})")
    cut.add_argument("--contact-min-duration", type=float, default=default.contact_min_s,
                     help=f"s it must stay above it (default {default.contact_min_s:g})")
    cut.add_argument("--approach", type=float, default=default.approach_s,
                     help=f"s kept before contact (default {default.approach_s:g})")
    cut.add_argument("--retreat", type=float, default=default.retreat_mm,
                     help=f"mm back from the deepest point where the retreat is cut (default {default.retreat_mm:g})")
    cut.add_argument("--bias-window", type=float, default=default.bias_s,
                     help=f"s at the start, in free space, whose mean force is the bias (default {default.bias_s:g})")
    imp.set_defaults(run=cmd_import)


def build_parser() -> argparse.ArgumentParser:
    from pipe.data.spec import INSERTION_AXES

    parser = argparse.ArgumentParser(prog="pipe", description="PIPE: contact models of assembly tasks from CAD.")
    kinds = parser.add_subparsers(dest="kind", required=True)
    data = kinds.add_parser("data", help="datasets: generate the synthetic one, check any one")
    verbs = data.add_subparsers(dest="verb", required=True)

    gen = verbs.add_parser("generate", help="write the synthetic dataset of the paper's 27 parts, or of a family")
    gen.add_argument("out", type=Path, help="output folder (a generated dataset there is replaced)")
    gen.add_argument("--seed", type=argument_type(SEED), default=0)
    chosen = gen.add_mutually_exclusive_group()
    chosen.add_argument("--parts", help="comma-separated part names (default: all 27)")
    chosen.add_argument("--family", help="parts of a parametric family instead: dsub, rect or pins (docs/synthetic.md)")
    gen.add_argument("--count", type=argument_type(WHOLE_FROM_1), help="how many parts of the family (default 100)")
    gen.set_defaults(run=cmd_generate)

    add_import_parser(verbs)

    check = verbs.add_parser("check", help="validate a dataset folder and summarise each part")
    check.add_argument("dir", type=Path)
    check.add_argument("--json", type=Path, help="also write the summary as JSON (for `dvc metrics show`)")
    check.set_defaults(run=cmd_check)

    cloud = verbs.add_parser("pointcloud", help="sample a mesh into the centred point cloud the encoder sees")
    cloud.add_argument("mesh", type=Path)
    cloud.add_argument("--points", type=argument_type(WHOLE_FROM_1), default=1024)
    cloud.add_argument("--units", default="auto", help="length unit of the mesh file, or 'auto' (default)")
    cloud.add_argument("--axis", default="z", choices=INSERTION_AXES,
                       help="the mesh's insertion axis, turned onto z (default z; principal: its long axis)")
    cloud.add_argument("--seed", type=argument_type(SEED), default=0)
    cloud.add_argument("--out", type=Path, help="write the points (n x 3, mm) as .npy")
    cloud.set_defaults(run=cmd_pointcloud)

    prep = verbs.add_parser("preprocess", help="sample every part's cloud and resample its trials once, into a "
                                               "folder that training reads with data.prepared=<folder>")
    prep.add_argument("dataset", type=Path)
    prep.add_argument("out", type=Path, help="output folder (preprocessed parts written there before are replaced)")
    prep.add_argument("--points", type=argument_type(WHOLE_FROM_1),
                      help="points per cloud (default: train.py's data.points)")
    prep.add_argument("--cloud-seed", type=argument_type(SEED),
                      help="seed of the cloud sampling (default: data.cloud_seed)")
    prep.add_argument("--rate-hz", type=argument_type(POSITIVE),
                      help="sample rate of the profiles (default: data.rate_hz)")
    prep.add_argument("--steady-samples", type=argument_type(WHOLE_FROM_0),
                      help="copies of the final value appended (default: data.steady_samples)")
    prep.set_defaults(run=cmd_preprocess)

    params = kinds.add_parser("params", help="compose the DVC pipeline's params.yaml from conf/, as `dvc exp run -S` "
                                             "does (after editing conf/)")
    params.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. encoder=dgcnn 'seeds=[0]'")
    params.add_argument("--out", type=Path, default=Path("params.yaml"), help="default: params.yaml")
    params.set_defaults(run=cmd_params)

    report = kinds.add_parser("report", help="summaries over finished runs")
    report_verbs = report.add_subparsers(dest="verb", required=True)
    curve = report_verbs.add_parser("curve", help="the learning curve: held-out FIT(F) against the number of "
                                                  "training parts, from learning-curve sweeps (README)")
    curve.add_argument("folders", type=Path, nargs="+", help="one sweep folder per family (its runs' subfolders)")
    curve.add_argument("--out", type=Path, required=True, help="folder for learning_curve.json, .md and .png")
    curve.set_defaults(run=cmd_curve)
    summary = report_verbs.add_parser("summary", help="one table over the domains of a pipeline's seeds runs, their "
                                                      "metrics and plot data (DVC's report stage)")
    summary.add_argument("runs", type=Path, help="the folder of the domains' evaluated runs "
                                                 "(evaluations/<domain>/results.json)")
    summary.add_argument("--params", type=Path, help="summarise only the domains this params.yaml lists")
    summary.add_argument("--out", type=Path, required=True, help="folder for metrics.json, results.md and plots/")
    summary.set_defaults(run=cmd_summary)

    kernels = kinds.add_parser("kernels", help="print shell lines that set the numeric libraries' kernels for the "
                                               "commands run after them, as train.py's kernels= does: "
                                               'eval "$(pipe kernels)" before an experiment script or a batch job')
    kernels.add_argument("choice", nargs="?", default="auto", choices=KERNEL_CHOICES,
                         help="auto (default: avx2 where the CPU has AVX2 and FMA), avx2, or native (unset them)")
    kernels.set_defaults(run=cmd_kernels)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except PipeError as err:
        if debugging():
            raise
        return fail(str(err))


if __name__ == "__main__":
    sys.exit(main())
