"""Issue 9, "an honest oracle": what the oracle's score on a generated family is made of, and how high any
prediction from a part's geometry can score (docs/experiments.md, "What the oracle's lead is made of").

The oracle identifies each test part's profiles on that part's own ten recordings and is scored on the same
ten: besides the part, it fits those trials' own conditions (misalignment, friction scale, contact offsets:
`pipe.synthetic.generate.draw_conditions`), which no recording's motion shows. Scored on the part's own
recordings, as every method is:
  own                 the oracle as the evaluation reports it
  twins=K             the same identification (starts, stopping rule, ridge) fitted on the pooled trials of
                      the part's K twins: the generator's same part, its trials drawn again from other streams
  expected_mean=D     no fit: each trial's noise-free force averaged over D draws of the unseen conditions,
                      with the trial's own speed, gap and overtravel (the motion its recording shows)
  expected_fit=D      the same draws weighted to maximise the expected FIT(F): the ceiling of any prediction
                      from the part and its motion, up to the draws' sampling error
  identified_expected_fit=D   the identification fitted on the expected_fit trials: about the best this
                      dynamic model can do from the part
The expectations do not depend on the seed (their rows carry none); the identifications' random starts do.
An `identified_expected_fit` row also holds, per part, the fit's FIT(F) on the expectation it was fitted to
(`fitted_on`), its force loss and whether it converged; `--only PART ...` runs some test parts alone.

`--domain dsub|pins|conn` takes a paper domain's test parts on the embedded dataset instead (its parts are the
catalogue's, simulated again the same way; rows labelled `paper <domain>`).
Rows (the domain's FIT(F) and each part's) are printed and appended to OUT as JSON lines; `--table`
summarises them. Usage (the family's test parts as the learning curve splits them; two worker processes):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/twin_oracle.py OUT.jsonl --family pins \
      --seeds 0 1 2 --twins 1 3
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/twin_oracle.py OUT.jsonl --family pins \
      --expected 32 --identify-expected --skip-own --seeds 0 1 2
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/twin_oracle.py OUT.jsonl --domain dsub \
      --expected 64 --identify-expected --twins 3 --skip-own --seeds 0 1 2
  python experiments/twin_oracle.py OUT.jsonl --table      # --parts: each part's FIT(F) too
"""
from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import zlib
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from common import append_row
from hydra import compose, initialize_config_module
from summarise import read_rows

from pipe.data.dataset import load_dataset
from pipe.data.prepared import PartData, PreparedDomain, PreprocessSettings
from pipe.data.preprocess import preprocess_trial
from pipe.evaluation.context import EvalContext
from pipe.evaluation.evaluate import evaluate_methods
from pipe.evaluation.identification import identify, with_fits
from pipe.evaluation.metrics import force_metrics
from pipe.model import ltv
from pipe.pipeline import build_model, load_domain
from pipe.synthetic.catalogue import CATALOGUE, Pin, Plug
from pipe.synthetic.families import family_parts
from pipe.synthetic.generate import FORCE_NOISE, draw_conditions, simulate_conditions, simulate_parts, write_dataset

TWIN_STREAMS = 1000     # twin k's trials are simulated with generator seed TWIN_STREAMS + k (the dataset's: 0)
EXPECTATION_STREAM = 2000   # the unseen conditions' draws of `expected_parts`


def family_config(family: str, seed: int, overrides: Sequence[str] = ()):
    """The learning curve's config for a family (its 100-part domain: the test parts do not change with it),
    with further Hydra overrides (e.g. `head=seat_gaussian`)."""
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    with initialize_config_module(config_module="pipe.conf", version_base="1.3"):
        return compose(config_name="config", overrides=[
            "data=family", f"data.generate.family={family}", "domain=curve", f"seed={seed}", *overrides])


def paper_config(domain: str, seed: int, overrides: Sequence[str] = ()):
    """The config of a paper domain (dsub, pins or conn) on the embedded dataset, generated from the catalogue,
    with further Hydra overrides."""
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    with initialize_config_module(config_module="pipe.conf", version_base="1.3"):
        return compose(config_name="config", overrides=[f"domain={domain}", f"seed={seed}", *overrides])


def run_config(family: str, domain: str | None, seed: int, overrides: Sequence[str] = ()):
    """A paper domain's config on the embedded dataset where `domain` names one, else the learning curve's for
    `family`."""
    return paper_config(domain, seed, overrides) if domain else family_config(family, seed, overrides)


def drawn_parts(generate) -> dict[str, Plug | Pin]:
    """The generator's parts of a dataset made by `pipe data generate` (`cfg.data.generate`): the family's
    `family_parts` where it names a family, else the catalogue of the embedded dataset; a dataset of
    recordings (no `generate`) has no generator to draw its parts again."""
    if generate is None:
        raise SystemExit("the dataset was not generated (data.generate is null): its parts cannot be drawn again")
    family = generate.get("family")
    return family_parts(family, generate.count, generate.seed) if family else CATALOGUE


def twin_parts(drawn: dict[str, Plug | Pin], test: list[PartData], settings: PreprocessSettings,
               stream: int) -> list[PartData]:
    """The test parts' twins: the generator's same parts (`drawn`, of `drawn_parts`), their trials simulated
    from generator seed `stream` (the dataset's own: its `generate.seed`)."""
    parts = {p.name: drawn[p.name] for p in test}
    return _read_back(parts, simulate_parts(parts, stream), test, settings, f"twins of stream {stream}")


def expected_parts(drawn: dict[str, Plug | Pin], seed: int, test: list[PartData], settings: PreprocessSettings,
                   draws: int) -> dict[str, list[PartData]]:
    """The test parts with each trial's force replaced by the generator's expectation of it given what the
    recording shows: the trial's own speed, gap and overtravel (its commanded motion) with the conditions no
    recording shows (misalignment, friction scale, contact offsets) drawn `draws` times from their
    distributions; written and read back as the dataset's. Two expectations of the same draws' noise-free
    forces: `mean`, their mean, which minimises the expected squared error; `fit`, their mean weighted by
    1 / (the draw's sum of squares about its mean, sensor noise included), which maximises the expected FIT
    (a trial's FIT divides its squared error by that sum, which the unseen conditions change too)."""
    parts = {p.name: drawn[p.name] for p in test}
    own = simulate_parts(parts, seed)
    expected: dict[str, list] = {"mean": [], "fit": []}
    for name, part in parts.items():
        rng = np.random.default_rng([EXPECTATION_STREAM, zlib.crc32(name.encode())])
        trials = [t for t in own if t.part == name]
        jobs = [(name, replace(draw_conditions(part, rng), speed=t.conditions.speed, gap=t.conditions.gap,
                               overtravel=t.conditions.overtravel, sensor_bias=0.0))
                for t in trials for _ in range(draws)]
        simulated = simulate_conditions({name: part}, jobs, {name: rng})
        for k, trial in enumerate(trials):
            alike = simulated[k * draws:(k + 1) * draws]
            forces = np.stack([t.force_clean for t in alike])
            spread = ((forces - forces.mean(axis=1, keepdims=True)) ** 2).sum(axis=1) + forces.shape[1] * FORCE_NOISE**2
            depth = np.mean([t.depth for t in alike], axis=0)
            for kind, weights in (("mean", np.ones(draws)), ("fit", 1.0 / spread)):
                force = weights @ forces / weights.sum()
                expected[kind].append(replace(trial, depth=depth, force=force, force_clean=force))
    return {kind: _read_back(parts, trials, test, settings, f"expected ({kind}) over {draws} draws")
            for kind, trials in expected.items()}


def _read_back(parts: dict, trials: list, test: list[PartData], settings: PreprocessSettings,
               command: str) -> list[PartData]:
    """The test parts with these simulated trials instead of their own, written as a dataset and read back as
    the dataset's (the same rounding, zeroing and resampling); each keeps its part's cloud."""
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder) / "parts"
        root.mkdir()
        write_dataset(root, parts, command, trials)
        loaded = load_dataset(root, parts=list(parts)).parts
        return [replace(part, profiles=[preprocess_trial(t, settings.rate_hz, settings.steady_samples)
                                        for t in loaded[part.name].trials],
                        static_curves=[t.static for t in loaded[part.name].trials]) for part in test]


def identification_context(cfg, data: PreparedDomain, parts: list[PartData], seed: int,
                           workers: int) -> EvalContext:
    """A context to identify `parts` in as the oracle does, on `workers` processes and without the fits' folder:
    the config's untrained model (the oracle's free profiles read only its structure) and zero codes."""
    model = build_model(cfg, data).eval()
    settings = {**dict(cfg.evaluation), "identification": {**dict(cfg.evaluation.identification),
                                                            "workers": workers, "cache": None}}
    return EvalContext(model, torch.zeros(len(parts), model.head.latent_dim), {p.name: i for i, p in enumerate(parts)},
                       data.splits["train"], 1.0 / cfg.data.rate_hz, seed, settings)


def pooled(twins: list[list[PartData]]) -> list[PartData]:
    """Each part with the trials of all its twins (lists of the same parts in the same order), in order."""
    return [replace(same[0], profiles=[p for twin in same for p in twin.profiles],
                    static_curves=[s for twin in same for s in twin.static_curves]) for same in zip(*twins)]


def only_parts(parts: list[PartData], names: list[str], family: str, what: str = "a test part") -> list[PartData]:
    """The `parts` (the test parts, or `what` they are) named in `names`, in their order; a name that is not
    among them is refused."""
    if unknown := set(names) - {p.name for p in parts}:
        raise SystemExit(f"--only {', '.join(sorted(unknown))}: not {what} of {family}")
    return [p for p in parts if p.name in names]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="JSON lines file the rows are appended to")
    ap.add_argument("--family", default="pins")
    ap.add_argument("--domain", choices=("dsub", "pins", "conn"), default=None,
                    help="a paper domain's test parts on the embedded dataset instead of a family's")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--twins", type=int, nargs="*", default=[], help="numbers of twins pooled per fit")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--expected", type=int, default=0, metavar="DRAWS",
                    help="also score the generator's expected force over DRAWS draws of the unseen conditions")
    ap.add_argument("--identify-expected", action="store_true",
                    help="with --expected: also the oracle identified on the FIT-weighted expectation")
    ap.add_argument("--skip-own", action="store_true", help="leave out the oracle on the parts' own recordings")
    ap.add_argument("--only", nargs="+", default=None, metavar="PART", help="these test parts alone")
    ap.add_argument("--table", action="store_true", help="print the table of the rows in OUT and stop")
    ap.add_argument("--parts", action="store_true", help="with --table: each part's FIT(F) per fit too")
    args = ap.parse_args()
    if args.identify_expected and not args.expected:
        ap.error("--identify-expected needs --expected DRAWS")
    if args.table:
        rows = read_rows(args.out)
        print(table(rows) + ("\n\n" + part_table(rows) if args.parts else ""))
        return
    label = f"paper {args.domain}" if args.domain else args.family
    cfg = run_config(args.family, args.domain, args.seeds[0])
    ltv.set_backend(cfg.simulator)
    data = load_domain(cfg)
    test = data.splits["test"]
    if args.only is not None:
        test = only_parts(test, args.only, label)
    drawn = drawn_parts(cfg.data.generate)
    preprocessing = PreprocessSettings.from_config(cfg.data)
    twins = [twin_parts(drawn, test, preprocessing, TWIN_STREAMS + k) for k in range(max(args.twins, default=0))]
    expected = {}
    if args.expected:
        expected = expected_parts(drawn, cfg.data.generate.seed, test, preprocessing, args.expected)
        for kind, guesses in expected.items():
            per_part = {part.name: float(np.mean([force_metrics(p.force, e.force, 1.0 / cfg.data.rate_hz)["fit_F"]
                                                  for p, e in zip(part.profiles, guess.profiles)]))
                        for part, guess in zip(test, guesses)}
            row = {"family": label, "seed": None, "fit": f"expected_{kind}={args.expected}",
                   "fit_F": float(np.mean(list(per_part.values()))), "parts": per_part}
            append_row(args.out, row)
            print(label, row["fit"], f"{row['fit_F']:.2f}", flush=True)
    for seed in args.seeds:
        cfg = run_config(args.family, args.domain, seed)
        ctx = identification_context(cfg, data, test, seed, args.workers)
        fits = {} if args.skip_own else {"own": None}
        for count in args.twins:
            fitted = identify(replace(ctx, cache={}), pooled(twins[:count]))
            fits[f"twins={count}"] = {part.name: fit for part, fit in zip(test, fitted)}
        if args.identify_expected:
            fitted = identify(replace(ctx, cache={}), expected["fit"])
            fits[f"identified_expected_fit={args.expected}"] = {part.name: fit for part, fit in zip(test, fitted)}
        for name, fitted in fits.items():
            scored = ctx if fitted is None else with_fits(ctx, fitted)
            result = evaluate_methods(scored, test, ["oracle"])["oracle"]
            row = {"family": label, "seed": seed, "fit": name, "fit_F": result.domain["fit_F"],
                   "parts": {p: m["fit_F"] for p, m in result.per_part.items()}}
            if name.startswith("identified_expected"):       # also: its FIT(F) on what it was fitted to
                fitted_on = evaluate_methods(scored, expected["fit"], ["oracle"])["oracle"]
                row |= {"fitted_on": {p: m["fit_F"] for p, m in fitted_on.per_part.items()},
                        "loss": {p: fit.loss for p, fit in fitted.items()},
                        "converged": {p: fit.converged for p, fit in fitted.items()}}
            append_row(args.out, row)
            print(label, seed, name, f"{row['fit_F']:.2f}", flush=True)


def table(rows: list[dict]) -> str:
    """Per family and fit: the oracle's FIT(F) on the test parts' own recordings, mean ± std over the seeds, and
    the median over every test part and seed (one part's extrapolation can pull the mean far down)."""
    fits: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for row in rows:
        fits[(row["family"], row["fit"])].append(row)
    lines = ["| family | fitted on | FIT(F) % | median over the parts | seeds |", "| --- | --- | --- | --- | --- |"]
    for (family, fit), found in fits.items():
        values = [row["fit_F"] for row in found]
        spread = statistics.stdev(values) if len(values) > 1 else 0.0
        median = statistics.median(v for row in found for v in row["parts"].values())
        lines.append(f"| {family} | {fit} | {statistics.fmean(values):.2f} ± {spread:.2f} | {median:.2f} | "
                     f"{len(values)} |")
    return "\n".join(lines)


def part_table(rows: list[dict]) -> str:
    """Each test part's FIT(F) per fit, mean over the seeds (where the oracle's lead on its own recordings is)."""
    values: dict[tuple[str, str], dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        for part, fit_f in row["parts"].items():
            values[(row["family"], part)][row["fit"]].append(fit_f)
    fits = list(dict.fromkeys(row["fit"] for row in rows))
    lines = ["| family | part | " + " | ".join(fits) + " |", "| --- | --- |" + " --- |" * len(fits)]
    for (family, part), by_fit in sorted(values.items()):      # a part of two domains once per domain
        lines.append(f"| {family} | {part} | " + " | ".join(f"{statistics.fmean(by_fit[f]):.2f}" if by_fit[f] else ""
                                                 for f in fits) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
