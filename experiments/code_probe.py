"""Issue 9, "why PIPE ties `nearest`": which of the part's parameters the encoder's codes hold.

For each finished run (a seed of `train.py`), every parameter the generator built the parts' meshes from
(`parameter_codes.shape_parameters`) and the plugs' hidden detent strength is predicted from the codes of the
run's encoder by a linear probe (ridge regression, its penalty chosen by leave-one-out on the training
parts, scikit-learn's RidgeCV), fitted on the training parts and scored on the test parts as R^2 (1: the
codes hold the parameter linearly; 0: no better than the training parts' mean). A parameter constant over
the training or the test parts is left out (R^2 needs a spread: read it on the learning curve's 20 test
parts, not on a paper domain's 1 to 3). Rows (per run: each parameter's R^2 on the test parts) are printed and
appended to OUT as JSON lines; `--table` gives each parameter's R^2 as mean ± std over the seeds. With
`--layer features` the probe reads the encoder's pooled features (PointNet's 512 channels after the max pool,
before the two small networks that map them to the code's mean and log-variance) instead of the codes; with
`--layer sections` the cloud's cross-section (code.sections: pipe.model.sections, standardised over the
training parts). Usage:
  python experiments/code_probe.py OUT.jsonl runs/curve_defaults/rect/train_100/seed_0 ... [--layer features]
  python experiments/code_probe.py OUT.jsonl --table
"""
from __future__ import annotations

import argparse
import os
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from common import append_row, kept_folder, load_encoder, load_run, pooled_features
from parameter_codes import generator_parts, hidden_parameters, shape_parameters
from sklearn.linear_model import RidgeCV
from summarise import domain_of, read_rows, spread

from pipe.data.batches import stack_clouds, stack_geometry
from pipe.model.sections import SectionCode
from pipe.pipeline import build_model

PENALTIES = np.logspace(-4, 3, 15)


def probe(codes_train: np.ndarray, codes_test: np.ndarray, values_train: np.ndarray,
          values_test: np.ndarray) -> float:
    """R^2 on the test parts of a ridge regression from the codes to one parameter, fitted on the training
    parts (the codes standardised over them; the penalty by leave-one-out)."""
    mean, std = codes_train.mean(0), codes_train.std(0) + 1e-12
    model = RidgeCV(alphas=PENALTIES).fit((codes_train - mean) / std, values_train)
    predicted = model.predict((codes_test - mean) / std)
    return float(1.0 - ((values_test - predicted) ** 2).sum() / ((values_test - values_train.mean()) ** 2).sum())


def run_row(run_dir: Path, layer: str) -> dict:
    """Each parameter's R^2 on the run's test parts, from its encoder's codes, its pooled features or the
    clouds' cross-sections (`layer`)."""
    folder = kept_folder(run_dir)       # the kept candidate's, where the run trained two force weights
    cfg, data, (encoder, head, dynamics) = load_run(folder)
    load_encoder(encoder, folder)
    train, test = data.splits["train"], data.splits["test"]
    model = build_model(cfg, data, (encoder, head, dynamics))
    clouds, slices = stack_geometry(train + test)
    with torch.no_grad():
        if layer == "sections":
            read = SectionCode.fitted(stack_clouds(train))(clouds)
        else:
            read = (model.latent_distribution(clouds, slices)[0] if layer == "codes"
                    else pooled_features(encoder, clouds))
    codes = read.double().numpy()
    generator = generator_parts(cfg)
    rows = [shape_parameters(generator[p.name]) | hidden_parameters(generator[p.name]) for p in train + test]
    r2 = {}
    for name in rows[0]:
        values = np.array([row[name] for row in rows])
        if values[: len(train)].std() > 1e-9 and values[len(train):].std() > 1e-9:
            r2[name] = probe(codes[: len(train)], codes[len(train):], values[: len(train)], values[len(train):])
    return {"run": str(run_dir), "layer": layer, "r2": r2}


def table(rows: list[dict]) -> str:
    """Per domain: each parameter's R^2 on the test parts, mean ± std over the seeds."""
    by_domain: dict[tuple[str, str], dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        for name, value in row["r2"].items():
            by_domain[(domain_of(row["run"]), row["layer"])][name].append(value)
    lines = ["| domain | layer | parameter | R^2 on the test parts | seeds |", "| --- | --- | --- | --- | --- |"]
    for (domain, layer), parameters in by_domain.items():
        for name, values in parameters.items():
            lines.append(f"| {domain} | {layer} | {name} | {spread(values)} | {len(values)} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="JSON lines file the rows are appended to (read with --table)")
    ap.add_argument("runs", nargs="*", help="finished seed folders of train.py")
    ap.add_argument("--layer", choices=("codes", "features", "sections"), default="codes",
                    help="what the probe reads")
    ap.add_argument("--table", action="store_true", help="summarise OUT's rows instead of running")
    args = ap.parse_args()
    if args.table:
        print(table(read_rows(args.out)))
        return
    for run in args.runs:
        append_row(args.out, run_row(Path(run), args.layer))


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
