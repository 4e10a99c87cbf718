"""The learning curve: every method's held-out FIT(F) against the number of training parts.

It reads the runs of a sweep over `domain.train_count` (README, "Learning curve"): each run a `seeds=` run
whose results.json holds every method's metrics as mean ± std over the seeds. One folder per family (the
sweep folder of its runs) gives one panel of the figure and one block of the table; `pipe report curve`
writes learning_curve.json, learning_curve.md and learning_curve.png. Beside each method's spread the table
gives PIPE's FIT(F) minus `nearest`'s seed by seed: the two share each seed's trained encoder and head, so
their difference is free of what the seed does to both. The JSON keeps each seed's FIT(F) too, so that a run
trained again can be compared with the curve seed by seed, and each seed's choice of stage 1's force weight
with every candidate's validation loss; the table shows the weight each seed kept, so that a reader sees
where the curve turns on that choice.
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.ticker import ScalarFormatter  # noqa: E402

from pipe.errors import PipeError  # noqa: E402
from pipe.evaluation.spread import Spread, spread, verdict  # noqa: E402
from pipe.files import atomic_path, write_text_atomically

Curve = dict[str, dict[str, dict[int, Spread]]]     # family -> method -> training parts -> FIT(F) over seeds
Paired = dict[str, dict[int, Spread]]               # family -> training parts -> PIPE minus nearest, per seed
PerSeed = dict[str, dict[str, dict[int, dict[str, float]]]]   # family -> method -> training parts -> seed -> FIT(F)
Choices = dict[str, dict[int, dict[str, dict]]]    # family -> training parts -> seed -> {chosen, objectives}
Run = tuple[str, int, dict]                        # family, training parts, the run's results.json
METRIC = "fit_F"
PAIRED_WITH = "nearest"
FLOOR = -25.0                   # [%] the figure's lowest FIT(F); lower points are left to the table


def _runs(folders: list[Path]) -> list[Run]:
    """(family, training parts, results.json) of every run in the sweep folders, a family per folder; refuses
    what is not a sweep of `seeds=` runs, or two runs of one family with as many training parts."""
    runs = []
    for folder in folders:
        documents = sorted(Path(folder).glob("*/results.json"))
        if not documents:
            raise PipeError("holds no run folder with a results.json (the output of a `seeds=` run); give the "
                            "sweep folder of a learning-curve multirun", folder)
        counts: set[int] = set()
        for document in documents:
            try:
                doc = json.loads(document.read_text())
            except json.JSONDecodeError as exc:
                raise PipeError(f"is not valid JSON ({exc})", document) from None
            if not isinstance(doc, dict) or "methods" not in doc or "parts" not in doc:
                raise PipeError("is not the results.json of a `seeds=` run (mean ± std over seeds)", document)
            count = int(doc["parts"]["train"])
            if count in counts:
                raise PipeError(f"two runs of the sweep have {count} training parts", document)
            counts.add(count)
            runs.append((Path(folder).name, count, doc))
    return runs


def read_curve(folders: list[Path], metric: str = METRIC) -> Curve:
    """The curve of each sweep folder (named by the folder): its runs' results.json, found in the folder's
    subfolders, by their number of training parts."""
    return _curve(_runs(folders), metric)


def _curve(runs: list[Run], metric: str) -> Curve:
    curve: Curve = {}
    for family, count, doc in runs:
        for method, metrics in doc["methods"].items():
            if metric in metrics:
                value = metrics[metric]
                curve.setdefault(family, {}).setdefault(method, {})[count] = Spread(value["mean"], value["std"],
                                                                                    value["n"])
    return curve


def read_paired(folders: list[Path], metric: str = METRIC) -> Paired:
    """PIPE's metric minus PAIRED_WITH's in each seed's run, as a spread over the seeds, per family and number
    of training parts (where at least two seeds have both)."""
    return paired_differences(read_per_seed(folders, metric))


def paired_differences(per_seed: PerSeed) -> Paired:
    """PIPE minus PAIRED_WITH seed by seed, as a spread over the seeds that have both (at least two)."""
    paired: Paired = {}
    for family, methods in per_seed.items():
        others = methods.get(PAIRED_WITH, {})
        for count, pipe in methods.get("pipe", {}).items():
            differences = [value - others[count][seed] for seed, value in pipe.items()
                           if seed in others.get(count, {})]
            if len(differences) >= 2:
                paired.setdefault(family, {})[count] = spread(differences)
    return paired


def read_per_seed(folders: list[Path], metric: str = METRIC) -> PerSeed:
    """Each seed's metric per family, method and number of training parts, as the runs' results.json hold it:
    what lets a run trained again be compared with the curve seed by seed."""
    return _per_seed(_runs(folders), metric)


def _per_seed(runs: list[Run], metric: str) -> PerSeed:
    found: PerSeed = {}
    for family, count, doc in runs:
        for seed, run in doc.get("per_seed", {}).items():
            for method, metrics in run.items():
                if metric in metrics:
                    found.setdefault(family, {}).setdefault(method, {}).setdefault(count, {})[seed] = metrics[metric]
    return found


def read_force_choices(folders: list[Path]) -> Choices:
    """Which stage-1 force weight each seed's validation parts kept, and every candidate's validation loss, per
    family and number of training parts (runs trained with one weight have none)."""
    return _force_choices(_runs(folders))


def _force_choices(runs: list[Run]) -> Choices:
    choices: Choices = {}
    for family, count, doc in runs:
        if doc.get("force_weight"):
            choices.setdefault(family, {})[count] = doc["force_weight"]
    return choices


def gap_closed(points: dict[str, dict[int, Spread]], count: int) -> float | None:
    """The share of the gap from `nearest` to the oracle that PIPE closes at `count` training parts."""
    try:
        pipe, nearest, oracle = (points[m][count].mean for m in ("pipe", "nearest", "oracle"))
    except KeyError:
        return None
    return (pipe - nearest) / (oracle - nearest) if oracle != nearest else None


def kept_weights(choice: dict[str, dict]) -> str:
    """The force weight each seed kept, in the seeds' order: e.g. "0, 1000, 1000"."""
    return ", ".join(f"{choice[seed]['chosen']:g}" for seed in sorted(choice, key=int))


def curve_markdown(curve: Curve, paired: Paired | None = None, choices: Choices | None = None) -> str:
    """One table per family: each method's FIT(F) mean ± std per number of training parts, PIPE's verdict
    against it at the largest number, PIPE minus `nearest` seed by seed (`paired`), the force weight each
    seed kept (`choices`), and the share of the nearest-to-oracle gap PIPE closes at the largest number."""
    lines = []
    for family, points in curve.items():
        counts = sorted({n for values in points.values() for n in values})
        largest = counts[-1]
        lines += [f"### {family}: held-out FIT(F) [%], mean ± std over seeds, by number of training parts", "",
                  "| method | " + " | ".join(str(n) for n in counts) + f" | PIPE vs it at {largest} |",
                  "|" + " --- |" * (len(counts) + 2)]
        for method, values in points.items():
            judged = "-" if method == "pipe" or largest not in values or largest not in points.get("pipe", {}) \
                else verdict(points["pipe"][largest], values[largest], METRIC)
            lines.append(f"| {method} | " + " | ".join(str(values[n]) if n in values else "-" for n in counts)
                         + f" | {judged} |")
        differences = (paired or {}).get(family, {})
        if differences:
            lines.append(f"| pipe - {PAIRED_WITH}, seed by seed | "
                         + " | ".join(f"{differences[n].mean:+.2f} ± {differences[n].std:.2f}" if n in differences
                                      else "-" for n in counts) + " | - |")
        kept = (choices or {}).get(family, {})
        if kept:
            lines.append("| force weight kept, seed by seed | "
                         + " | ".join(kept_weights(kept[n]) if n in kept else "-" for n in counts) + " | - |")
        closed = gap_closed(points, largest)
        if differences:
            lines += ["", f"pipe - {PAIRED_WITH}, seed by seed: PIPE's FIT(F) minus `{PAIRED_WITH}`'s in each seed's "
                          "run (both predict with that seed's encoder and head), mean ± std over the seeds."]
        if kept:
            lines += ["", "force weight kept: stage 1's force weight whose stage 2 reached the lowest validation loss "
                          "in each seed's run (learning_curve.json holds every candidate's loss)."]
        if closed is not None:
            lines += ["", f"At {largest} training parts PIPE closes {closed:.1%} of the gap between `nearest` and "
                          "the oracle (of their means)."]
        lines.append("")
    return "\n".join(lines)


def plot_curve(curve: Curve, path: Path) -> None:
    """One panel per family: every method's FIT(F) against the number of training parts (log scale), the
    seeds' standard deviation as error bars, cut at FLOOR."""
    fig, axes = plt.subplots(1, len(curve), figsize=(5.5 * len(curve), 4.2), squeeze=False)
    for ax, (family, points) in zip(axes[0], curve.items()):
        for method, values in points.items():
            counts = sorted(values)
            ax.errorbar(counts, [values[n].mean for n in counts], yerr=[values[n].std for n in counts], capsize=3,
                        marker="o", ms=4, lw=2.0 if method == "pipe" else 1.0, color="k" if method == "pipe" else None,
                        ls="-" if method in ("pipe", "oracle") else "--", label=method)
        lowest = min(v.mean - v.std for values in points.values() for v in values.values())
        if lowest < FLOOR:              # e.g. `mean` on a few parts: it would squeeze the methods that matter
            ax.set_ylim(bottom=FLOOR, top=ax.get_ylim()[1])
            ax.text(0.02, 0.02, f"below {FLOOR:.0f} %: see the table", transform=ax.transAxes, fontsize=7)
        ax.set_xscale("log")
        ax.set_xticks(sorted({n for values in points.values() for n in values}))
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.minorticks_off()
        ax.set_xlabel("training parts")
        ax.set_ylabel("held-out FIT(F) [%]")
        ax.set_title(family)
        ax.grid(alpha=0.3)
    axes[0, -1].legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as temporary:
        fig.savefig(temporary, dpi=110)
    plt.close(fig)


def write_curve(folders: list[Path], out: Path) -> list[Path]:
    """learning_curve.json (per family: each method's FIT(F), PIPE minus `nearest` seed by seed, each seed's
    FIT(F) and each seed's force-weight choice, by number of training parts), .md and .png in `out` from the
    sweep folders."""
    runs = _runs(folders)
    curve, per_seed, choices = _curve(runs, METRIC), _per_seed(runs, METRIC), _force_choices(runs)
    paired = paired_differences(per_seed)
    out.mkdir(parents=True, exist_ok=True)
    by_count = lambda values: {str(n): {"mean": v.mean, "std": v.std, "n": v.n}   # noqa: E731
                               for n, v in sorted(values.items())}
    write_text_atomically(out / "learning_curve.json", json.dumps(
        {family: {"fit_F": {method: by_count(values) for method, values in points.items()},
                  f"pipe_minus_{PAIRED_WITH}": by_count(paired.get(family, {})),
                  "fit_F_per_seed": {method: {str(n): seeds for n, seeds in sorted(values.items())}
                                     for method, values in per_seed.get(family, {}).items()},
                  "force_weight_per_seed": {str(n): choice for n, choice in sorted(choices.get(family, {}).items())}}
         for family, points in curve.items()}, indent=2) + "\n")
    write_text_atomically(out / "learning_curve.md", curve_markdown(curve, paired, choices))
    plot_curve(curve, out / "learning_curve.png")
    return [out / f"learning_curve.{ext}" for ext in ("json", "md", "png")]
