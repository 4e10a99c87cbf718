"""Issue 9: stage 1's force weight chosen on the validation parts, at each size of the learning curve.

Given learning curves trained with different `stages.vae.force_weight` values (each a folder of
<family>/train_<n>/seed_<k> runs, as scripts/learning_curve.sh writes them, or of <domain>/seed_<k> runs of
the paper domains), every seed's run is chosen among the candidates by stage 2's best validation loss
(training.json's `objective`, `head/val_loss` on the validation parts: the loss that selects PIPE's
checkpoint and that `hparams_search=force_weight` minimises), never by a test metric. Two rules:
  per seed   each seed keeps its own lowest-objective candidate (what one `train.py` run per candidate
             and seed, then the lower loss, gives); the spread includes the choice's own noise
  per size   every seed keeps the candidate with the lowest objective averaged over the seeds (what a
             `seeds=` run per candidate, then the lower mean, gives)
and the chosen runs' held-out FIT(F) of PIPE and `nearest` (metrics.json) as mean ± std over the seeds,
PIPE's verdict against the first candidate's (the default) by the spread rule.

usage: python experiments/force_selection.py OUT.json 0=runs/curve_default1t 1000=runs/curve_force \
           [--plot curve.png --oracle runs/curve_force_oracle]
With --plot, the choice per size's learning curve as `pipe report curve` draws one (PIPE chosen, each
candidate's PIPE, `nearest` of the chosen runs, the oracle of --oracle's runs at every size).
A candidate may name several folders, the first that holds a finished run is read:
0=runs/curve_plain,runs/curve_default1t
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from pipe.evaluation.curve import Curve, plot_curve
from pipe.evaluation.spread import Spread, spread, verdict


def read_run(run: Path) -> dict[str, float]:
    metrics = json.loads((run / "metrics.json").read_text())
    return {"objective": json.loads((run / "training.json").read_text())["objective"],
            "pipe": metrics["test"]["fit_F"], "nearest": metrics["baselines"]["nearest"]["fit_F"]}


def finished(run: Path) -> bool:
    return (run / "training.json").is_file() and (run / "metrics.json").is_file()


def sort_key(domain: str) -> tuple[str, int]:
    """rect/train_50 before rect/train_100; a paper domain (conn) by its name."""
    family, _, size = domain.partition("/train_")
    return family, int(size) if size else 0


def cells(folders: dict[str, list[Path]], seeds: list[int]) -> dict[str, dict[str, list[dict]]]:
    """domain -> candidate -> the seeds' runs, where every candidate has every seed. A domain is a seed folder's
    parent within a candidate's folder: rect/train_50 for a learning curve's, conn for a `seeds=` run's."""
    domains = {str(run.parent.relative_to(folder)) for paths in folders.values() for folder in paths
               for run in folder.glob("**/seed_*") if finished(run)}
    table = {}
    for domain in sorted(domains, key=sort_key):
        runs = {label: [next((folder / domain / f"seed_{seed}" for folder in paths
                              if finished(folder / domain / f"seed_{seed}")), None) for seed in seeds]
                for label, paths in folders.items()}
        if all(run is not None for seed_runs in runs.values() for run in seed_runs):
            table[domain] = {label: [read_run(run) for run in seed_runs] for label, seed_runs in runs.items()}
    return table


def select(candidates: dict[str, list[dict]]) -> dict[str, tuple[list[str], list[dict]]]:
    """The two rules' choices: rule -> (the chosen candidate per seed, the chosen runs)."""
    labels = list(candidates)
    seeds = range(len(candidates[labels[0]]))
    per_seed = [min(labels, key=lambda label: candidates[label][k]["objective"]) for k in seeds]
    best = min(labels, key=lambda label: statistics.fmean(run["objective"] for run in candidates[label]))
    return {"per seed": (per_seed, [candidates[label][k] for k, label in zip(seeds, per_seed)]),
            "per size": ([best] * len(seeds), candidates[best])}


def selection_curve(rows: list[dict], oracles: dict[str, Spread]) -> Curve:
    """The learning curve of the choice per size as `pipe report curve` draws one: PIPE of the chosen runs, each
    candidate's PIPE, `nearest` of the chosen runs, and a family's oracle (which reads no code) at every size."""
    curve: Curve = {}
    for row in rows:
        family, _, size = row["domain"].partition("/train_")
        if not size:                    # a paper domain: no curve
            continue
        points = curve.setdefault(family, {"pipe": {}})
        count = int(size)
        points["pipe"][count] = spread(row["per size"]["pipe"])
        for label, values in row["candidates"].items():
            points.setdefault(f"pipe, force_weight={label}", {})[count] = spread(values["pipe"])
        points.setdefault("nearest", {})[count] = spread(row["per size"]["nearest"])
        if family in oracles:
            points.setdefault("oracle", {})[count] = oracles[family]
    return curve


def read_oracles(folder: Path | None) -> dict[str, Spread]:
    """family -> the oracle's FIT(F) over the seeds, from the results.json of a curve folder's runs."""
    oracles = {}
    for document in sorted(folder.glob("*/train_*/results.json")) if folder else []:
        value = json.loads(document.read_text())["methods"]["oracle"]["fit_F"]
        oracles[document.parent.parent.name] = Spread(value["mean"], value["std"], value["n"])
    return oracles


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="JSON file of every cell's numbers")
    parser.add_argument("candidates", nargs="+", help="WEIGHT=FOLDER[,FOLDER...], the default first")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--plot", type=Path, help="PNG of the choice per size's learning curve")
    parser.add_argument("--oracle", type=Path, help="a curve folder whose runs hold the oracle, drawn at every size")
    args = parser.parse_args()
    if any("=" not in candidate for candidate in args.candidates) or len(args.candidates) < 2:
        parser.error("give at least two candidates as WEIGHT=FOLDER[,FOLDER...], e.g. 0=runs/a 1000=runs/b")
    folders = {label: [Path(p) for p in paths.split(",")]
               for label, paths in (candidate.split("=", 1) for candidate in args.candidates)}
    default = next(iter(folders))
    table = cells(folders, args.seeds)
    if not table:
        parser.error(f"no domain has a finished run (training.json and metrics.json) of seeds {args.seeds} in "
                     "every candidate's folders")
    rows = []
    for domain, candidates in table.items():
        row = {"domain": domain,
               "candidates": {label: {key: [run[key] for run in runs] for key in ("objective", "pipe", "nearest")}
                              for label, runs in candidates.items()}}
        for rule, (chosen, runs) in select(candidates).items():
            pipe = spread([run["pipe"] for run in runs])
            row[rule] = {"chosen": chosen, "pipe": [run["pipe"] for run in runs],
                         "nearest": [run["nearest"] for run in runs],
                         "verdict": verdict(pipe, spread(row["candidates"][default]["pipe"]), "fit_F")}
        rows.append(row)
    args.out.write_text(json.dumps(rows, indent=1) + "\n")
    if args.plot:
        plot_curve(selection_curve(rows, read_oracles(args.oracle)), args.plot)
    labels = list(folders)
    print("| domain | " + " | ".join(f"objective, {label}" for label in labels) + " | "
          + " | ".join(f"PIPE, {label}" for label in labels)
          + " | chosen per seed | PIPE, chosen per seed | nearest, chosen per seed | chosen per size"
          " | PIPE, chosen per size |")
    print("| --- " * (6 + 2 * len(labels)) + "|")
    for row in rows:
        cand = row["candidates"]
        objective = " | ".join(f"{statistics.fmean(cand[label]['objective']):.4f}" for label in labels)
        pipe = " | ".join(str(spread(cand[label]["pipe"])) for label in labels)
        seed_rule, size_rule = row["per seed"], row["per size"]
        print(f"| {row['domain']} | {objective} | {pipe} | {', '.join(seed_rule['chosen'])} | "
              f"{spread(seed_rule['pipe'])} ({seed_rule['verdict']}) | {spread(seed_rule['nearest'])} | "
              f"{size_rule['chosen'][0]} | {spread(size_rule['pipe'])} ({size_rule['verdict']}) |")


if __name__ == "__main__":
    main()
