"""The learning curve: every method's held-out FIT(F) against the number of training parts.

It reads the runs of a sweep over `domain.train_count` (README, "Learning curve"): each run a `seeds=` run
whose results.json holds every method's metrics as mean ± std over the seeds. One folder per family (the
sweep folder of its runs) gives one panel of the figure and one block of the table; `pipe report curve`
writes learning_curve.json, learning_curve.md and learning_curve.png.
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.ticker import ScalarFormatter  # noqa: E402

from pipe.errors import PipeError  # noqa: E402
from pipe.evaluation.spread import Spread, verdict  # noqa: E402

Curve = dict[str, dict[str, dict[int, Spread]]]     # family -> method -> training parts -> FIT(F) over seeds
METRIC = "fit_F"


def read_curve(folders: list[Path], metric: str = METRIC) -> Curve:
    """The curve of each sweep folder (named by the folder): its runs' results.json, found in the folder's
    subfolders, by their number of training parts."""
    curve: Curve = {}
    for folder in folders:
        documents = sorted(Path(folder).glob("*/results.json"))
        if not documents:
            raise PipeError("holds no run folder with a results.json (the output of a `seeds=` run); give the "
                            "sweep folder of a learning-curve multirun", folder)
        family = curve.setdefault(Path(folder).name, {})
        for document in documents:
            try:
                doc = json.loads(document.read_text())
            except json.JSONDecodeError as exc:
                raise PipeError(f"is not valid JSON ({exc})", document) from None
            if not isinstance(doc, dict) or "methods" not in doc or "parts" not in doc:
                raise PipeError("is not the results.json of a `seeds=` run (mean ± std over seeds)", document)
            count = int(doc["parts"]["train"])
            for method, metrics in doc["methods"].items():
                if count in family.get(method, {}):
                    raise PipeError(f"two runs of the sweep have {count} training parts", document)
                if metric in metrics:
                    value = metrics[metric]
                    family.setdefault(method, {})[count] = Spread(value["mean"], value["std"], value["n"])
    return curve


def gap_closed(points: dict[str, dict[int, Spread]], count: int) -> float | None:
    """The share of the gap from `nearest` to the oracle that PIPE closes at `count` training parts."""
    try:
        pipe, nearest, oracle = (points[m][count].mean for m in ("pipe", "nearest", "oracle"))
    except KeyError:
        return None
    return (pipe - nearest) / (oracle - nearest) if oracle != nearest else None


def curve_markdown(curve: Curve) -> str:
    """One table per family: each method's FIT(F) mean ± std per number of training parts, PIPE's verdict
    against it at the largest number, and the share of the nearest-to-oracle gap PIPE closes there."""
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
        closed = gap_closed(points, largest)
        if closed is not None:
            lines += ["", f"At {largest} training parts PIPE closes {closed:.0%} of the gap between `nearest` and "
                          "the oracle (of their means)."]
        lines.append("")
    return "\n".join(lines)


def plot_curve(curve: Curve, path: Path) -> None:
    """One panel per family: every method's FIT(F) against the number of training parts (log scale), the
    seeds' standard deviation as error bars."""
    fig, axes = plt.subplots(1, len(curve), figsize=(5.5 * len(curve), 4.2), squeeze=False)
    for ax, (family, points) in zip(axes[0], curve.items()):
        for method, values in points.items():
            counts = sorted(values)
            ax.errorbar(counts, [values[n].mean for n in counts], yerr=[values[n].std for n in counts], capsize=3,
                        marker="o", ms=4, lw=2.0 if method == "pipe" else 1.0, color="k" if method == "pipe" else None,
                        ls="-" if method in ("pipe", "oracle") else "--", label=method)
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
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_curve(folders: list[Path], out: Path) -> list[Path]:
    """learning_curve.json, .md and .png in `out` from the sweep folders."""
    curve = read_curve(folders)
    out.mkdir(parents=True, exist_ok=True)
    (out / "learning_curve.json").write_text(json.dumps(
        {family: {method: {str(n): {"mean": v.mean, "std": v.std, "n": v.n} for n, v in sorted(values.items())}
                  for method, values in points.items()} for family, points in curve.items()}, indent=2) + "\n")
    (out / "learning_curve.md").write_text(curve_markdown(curve))
    plot_curve(curve, out / "learning_curve.png")
    return [out / f"learning_curve.{ext}" for ext in ("json", "md", "png")]
