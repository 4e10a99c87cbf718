"""The markdown tables of docs/experiments.md from the scripts' JSON lines: per domain and variant, FIT(F)
of PIPE on the training parts (where the rows have them), on the validation parts (what chooses) and of
PIPE and `nearest` on the test parts, and PIPE minus `nearest` seed by seed, each as mean ± standard
deviation over the seeds (run folders).

usage: python experiments/summarise.py RESULTS.jsonl [...]
"""

from __future__ import annotations

import json
import statistics
import sys
from collections import defaultdict
from pathlib import Path

from pipe.training.force_choice import CANDIDATE_PREFIX


def spread(values: list[float]) -> str:
    return f"{statistics.mean(values):.2f} ± {statistics.stdev(values) if len(values) > 1 else 0.0:.2f}"


def domain_of(run: str) -> str:
    """A run folder's domain: runs/conn/seed_0 -> conn; a learning curve's seed folders, such as
    runs/curve/pins/train_20/seed_0 or runs/curve_defaults/rect/train_100/seed_0 -> pins/train_20, rect/train_100;
    a candidate's folder as its run's (runs/conn/seed_0/force_weight_0 -> conn)."""
    parts = Path(run).parts
    if parts[-1].startswith(CANDIDATE_PREFIX):
        parts = parts[:-1]
    return "/".join(parts[-3:-1]) if parts[-2].startswith("train_") else parts[-2]


def read_rows(path: str | Path) -> list[dict]:
    """The rows of a JSON lines file the scripts appended to (`common.append_row`), blank lines skipped; a
    missing file stops the script naming it."""
    if not Path(path).is_file():
        raise SystemExit(f"{path}: no such file of result rows")
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def main(paths: list[str]) -> None:
    rows = [row for path in paths for row in read_rows(path)]
    table: dict[str, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        table[domain_of(row["run"])][row["variant"]].append(row)
    for domain, variants in table.items():
        trained = all("train" in r for runs in variants.values() for r in runs)   # rows since the train column
        print(f"\n{domain}\n\n| variant | seeds |{' train: PIPE |' if trained else ''} val: PIPE | test: PIPE | "
              "test: nearest | test: PIPE - nearest |")
        print("| --- | --- |" + " --- |" * (5 if trained else 4))
        for variant, runs in variants.items():
            train = f" {spread([r['train']['pipe'] for r in runs])} |" if trained else ""
            print(f"| {variant} | {len(runs)} |{train} {spread([r['val']['pipe'] for r in runs])} | "
                  f"{spread([r['test']['pipe'] for r in runs])} | {spread([r['test']['nearest'] for r in runs])} | "
                  f"{spread([r['test']['pipe'] - r['test']['nearest'] for r in runs])} |")


if __name__ == "__main__":
    main(sys.argv[1:])
