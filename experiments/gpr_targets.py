"""Issue 9: how far gpr's targets and its test figure move when the identification starts a hair off its start.
gpr regresses each training part's profiles identified from the neutral start alone (`GPR.targets`). The same
code gave gpr other figures on two AMD hosts while PIPE and `nearest` repeated to the digit
(docs/experiments.md, "PIPE and gpr paired over the same folds"): its targets ended in other local minima. This
script measures on one host whether a start moved by `--eps` (each free parameter plus eps times a standard
normal draw of its own per perturbation and part; the free parameters are 0 at the neutral profile, of order 1
at the random starts) moves the targets and gpr's test FIT(F) as far. Perturbation 0 is the evaluation's own
neutral start: since 2026-12-02 the neutral profile moved by `evaluation.identification.neutral_jitter` with a
draw of the run's seed (the perturbations move it further), before then the neutral profile itself, which
`--neutral-jitter 0` gives (how the committed rows were measured). Each perturbation identifies the training
parts in a fit cache of its own (`--fits`, perturbation 0 in the folder itself), fits
gpr as the evaluation does (its kernel chosen on the run's validation parts) and scores it on the run's test
parts; `gpr_grid` is gpr choosing among the fixed length scales only, without the likelihood's optimum;
`gpr_1se` is gpr with its kernel chosen on the validation parts by the one-standard-error rule the baselines
choose their input by (the likelihood optimum unless another kernel is clearly better), scored on every draw's
targets; `consensus` is gpr on the mean over the neutral start and the perturbations of each target (log
profiles), a smoother target; `best` is gpr on each part's fit of the lowest objective among a group of
`--best-of` perturbed draws (disjoint groups: draws 1 to N, N+1 to 2N, ...), the identification's own rule for
choosing among starts, so that two groups tell whether that choice repeats where the draws differ, as a host's
rounding would make them. The test parts only score: nothing is chosen on them. One JSON line per run and
perturbation, one per run and group of draws for `best`, one per run for the consensus and for PIPE and
`nearest`, whose figures do not depend on the perturbation.
Results: docs/experiments.md, "gpr's targets under a perturbed start".
Usage (one thread, as the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/gpr_targets.py OUT.jsonl runs/dsub/seed_{0,1,2} \
      --neutral-jitter 0
  python experiments/gpr_targets.py OUT.jsonl --table
"""
from __future__ import annotations

import contextlib
import os
import statistics
import time
import zlib
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from common import append_row, kept_folder, load_encoder, load_head_stage, load_run, rows_parser
from omegaconf import OmegaConf
from profile_pretraining import FITS
from summarise import domain_of, read_rows, spread

from pipe.data.preprocess import Profile
from pipe.evaluation import identification
from pipe.evaluation.compiled_objective import CompiledObjective
from pipe.evaluation.context import EvalContext
from pipe.evaluation.evaluate import evaluate_methods
from pipe.evaluation.methods import GPR, METHODS, model_forces, one_standard_error_choice, validation_errors
from pipe.evaluation.metrics import fit_percent
from pipe.pipeline import build_model, latent_codes

NEUTRAL_START = identification.start_head


@contextlib.contextmanager
def perturbed_starts(eps: float, perturbation: int) -> Iterator[None]:
    """Every neutral start (start 0) moved by eps times a standard normal draw per free parameter, from a
    generator of its own per perturbation and part, on top of the identification's own jitter; perturbation
    0 leaves the starts as they are."""
    def start_head(template, name: str, seed: int, start: int, jitter: float = 0.0):
        head = NEUTRAL_START(template, name, seed, start, jitter)
        if start == 0 and perturbation > 0:
            entropy = np.random.SeedSequence([perturbation, zlib.crc32(name.encode())]).generate_state(1)[0]
            generator = torch.Generator().manual_seed(int(entropy))     # torch keeps 32 bits of a seed
            with torch.no_grad():
                for parameter in head.parameters():
                    parameter.add_(eps * torch.randn(parameter.shape, generator=generator))
        return head

    identification.start_head = start_head
    try:
        yield
    finally:
        identification.start_head = NEUTRAL_START


class GivenGPR(GPR):
    """gpr on given targets (the perturbations' mean, or each part's best) instead of one identification's."""

    name = "gpr_given"
    given: np.ndarray | None = None

    def targets(self, ctx):
        return self.given


class OneStandardErrorGPR(GPR):
    """gpr whose kernel the validation parts choose as the baselines choose their input: the likelihood optimum
    unless another kernel beats it by more than one standard error (`one_standard_error_choice`)."""

    name = "gpr_1se"

    def validation_choice(self, ctx, fitted):
        errors = []
        for gp in fitted:
            self.gp = gp
            errors.append(validation_errors(self, ctx))
        return one_standard_error_choice(errors)


class GridGPR(GPR):
    """gpr choosing among the fixed length scales alone (`GPR.LENGTH_SCALES`), without the likelihood's optimum."""

    name = "gpr_grid"

    @staticmethod
    def kernels(dims: int) -> list:
        return GPR.kernels(dims)[1:]


VARIANTS = ("gpr_1se", "gpr_grid")     # scored on every draw's targets beside gpr


def given_gpr(ctx: EvalContext, test: list, targets: np.ndarray) -> float:
    """gpr's test FIT(F) on these targets, fitted as the evaluation fits gpr."""
    GivenGPR.given = targets
    return evaluate_methods(ctx, test, ["gpr_given"])["gpr_given"].domain["fit_F"]


def objective(ctx: EvalContext, part, identified) -> float:
    """The identification's objective at a part's fit (what it keeps the lowest of), evaluated afresh."""
    settings = identification.IdentificationSettings.from_config(ctx.settings["identification"])
    trials = [Profile(p.time, p.depth, p.force) for p in part.profiles]
    job = identification.part_jobs(ctx, part.name, trials, replace(settings, restarts=1))[0]
    head = identified.model.head
    values = torch.nn.utils.parameters_to_vector(head.parameters()).detach().double().numpy()
    return CompiledObjective.of(job.model, head, job.batch, settings.ridge, settings.loss)(values)[0]


def own_fit(ctx: EvalContext, part, identified) -> float:
    """FIT(F) [%] of a training part's identified profiles on its own trials, mean over the trials."""
    forces = model_forces(ctx, identified.model, ctx.latent(part), part)
    return float(np.mean([fit_percent(p.force, f) for p, f in zip(part.profiles, forces)]))


def perturb_run(run: Path, out: str, eps: float, perturbations: int, best_of: int, fits: str,
                neutral_jitter: float | None) -> None:
    candidate = kept_folder(run)
    cfg, data, components = load_run(candidate)
    load_encoder(components[0], candidate)
    model = build_model(cfg, data, components)
    load_head_stage(model, candidate / "checkpoints/head/best.ckpt")     # for PIPE's figure beside gpr's
    model.eval()
    latents, _, index = latent_codes(model, data)
    settings = OmegaConf.to_container(cfg.evaluation, resolve=True)
    if neutral_jitter is not None:
        settings["identification"]["neutral_jitter"] = neutral_jitter
    train, val, test = data.splits["train"], data.splits["val"], data.splits["test"]

    def context(perturbation: int = 0) -> EvalContext:
        settings["identification"]["cache"] = fits if perturbation == 0 else f"{fits}/perturbed_{eps:g}_{perturbation}"
        return EvalContext(model, latents, index, train, 1.0 / cfg.data.rate_hz, cfg.seed, settings, val=val)

    others = evaluate_methods(context(), test, ["pipe", "nearest"])
    append_row(out, {"run": str(run), "kind": "reference", **{m: r.domain["fit_F"] for m, r in others.items()}})
    all_targets, objectives = [], []
    for perturbation in range(perturbations + 1):
        start = time.perf_counter()
        ctx = context(perturbation)
        with perturbed_starts(eps, perturbation):
            results = evaluate_methods(ctx, test, ["gpr", *VARIANTS])
        result = results["gpr"]
        targets = GPR().targets(ctx)     # the fits evaluate_methods made, from the context's cache
        all_targets.append(targets)
        fitted = identification.identify(ctx, train, restarts=1)
        objectives.append([objective(ctx, p, f) for p, f in zip(train, fitted)])
        append_row(out, {"run": str(run), "kind": "perturbation", "perturbation": perturbation, "eps": eps,
                         "gpr": result.domain["fit_F"], **{v: results[v].domain["fit_F"] for v in VARIANTS},
                         "test_parts": {p: m["fit_F"] for p, m in result.per_part.items()},
                         "length_scale": next(iter(result.per_part.values()))["gpr_length_scale"],
                         "own_fit": {p.name: own_fit(ctx, p, f) for p, f in zip(train, fitted)},
                         "objective": dict(zip([p.name for p in train], objectives[-1])),
                         "targets": targets.tolist(), "seconds": time.perf_counter() - start})
    append_row(out, {"run": str(run), "kind": "consensus", "perturbations": perturbations, "eps": eps,
                     "gpr": given_gpr(context(), test, np.mean(all_targets, axis=0))})
    for first in range(1, perturbations - best_of + 2, best_of):     # disjoint groups of perturbed draws
        draws = list(range(first, first + best_of))
        chosen = [min(draws, key=lambda d: objectives[d][i]) for i in range(len(train))]
        targets = np.stack([all_targets[d][i] for i, d in enumerate(chosen)])
        append_row(out, {"run": str(run), "kind": "best", "draws": draws, "eps": eps,
                         "chosen": dict(zip([p.name for p in train], chosen)),
                         "gpr": given_gpr(context(), test, targets)})


def over_draws(neutral: list[dict], moved: list[list[dict]], column: str) -> str:
    """Two cells: the column at the neutral start over the runs, and over the perturbed draws the runs' means
    (in brackets the std over a run's draws, averaged over the runs, and the lowest and highest figure)."""
    if any(column not in r for r in neutral):
        return "- | -"
    single = [r[column] for rs in moved for r in rs]
    within = statistics.fmean(statistics.stdev(r[column] for r in rs) if len(rs) > 1 else 0.0 for rs in moved)
    means = [statistics.fmean(r[column] for r in rs) for rs in moved]
    return (f"{spread([r[column] for r in neutral])} | "
            f"{spread(means)} ({within:.2f}; {min(single):.2f}, {max(single):.2f})")


def table(rows: list[dict]) -> str:
    """Per domain: gpr's test FIT(F) at the neutral start and over the perturbed starts (mean ± std over the runs of
    each run's mean; in brackets the std over a run's draws, averaged over the runs, and the lowest and highest
    single figure), the consensus, PIPE and `nearest`, and gpr on each group's best fits, each of VARIANTS as
    gpr, and how far the perturbed targets lie from the neutral start's (rms of the log profiles' difference,
    median over the runs, parts and perturbations; in brackets the largest) and what they fit of their own part
    (the largest drop of own FIT(F) from the neutral start's)."""
    lines = ["| domain | PIPE | `nearest` | gpr, neutral start | "
             "gpr, perturbed starts (std over the draws; lowest, highest) | gpr, consensus | gpr, best of each group | "
             + "".join(f"{v}, neutral start | {v}, perturbed starts | " for v in VARIANTS)
             + "targets' rms change (largest) | largest own-FIT(F) change |", "| --- |" + " --- |" * 12]
    by_domain: dict[str, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        by_domain[domain_of(row["run"])][row["kind"]].append(row)
    for domain, kinds in by_domain.items():
        runs = defaultdict(list)
        for row in kinds["perturbation"]:
            runs[row["run"]].append(row)
        neutral = [next(r for r in rs if r["perturbation"] == 0) for rs in runs.values()]
        moved = [[r for r in rs if r["perturbation"] > 0] for rs in runs.values()]
        changes, own = [], []
        for base, others in zip(neutral, moved):
            for r in others:
                difference = np.asarray(r["targets"]) - np.asarray(base["targets"])
                changes.extend(np.sqrt(np.mean(difference**2, axis=1)))
                own.extend(r["own_fit"][p] - base["own_fit"][p] for p in base["own_fit"])
        groups = defaultdict(list)
        for row in kinds["best"]:
            groups[tuple(row["draws"])].append(row["gpr"])
        best = "; ".join(f"{spread(v)} (draws {k[0]}-{k[-1]})" for k, v in groups.items()) or "-"
        lines.append(
            f"| {domain} | {spread([r['pipe'] for r in kinds['reference']])} | "
            f"{spread([r['nearest'] for r in kinds['reference']])} | {over_draws(neutral, moved, 'gpr')} | "
            f"{spread([r['gpr'] for r in kinds['consensus']])} | {best} | "
            + "".join(f"{over_draws(neutral, moved, v)} | " for v in VARIANTS)
            + f"{statistics.median(changes):.3f} ({max(changes):.3f}) | {max(own, key=abs):+.2f} |")
    return "\n".join(lines)


def main() -> None:
    ap = rows_parser(__doc__)
    ap.add_argument("--eps", type=float, default=1e-6, help="size of the start's perturbation (default 1e-6)")
    ap.add_argument("--perturbations", type=int, default=4, help="perturbed starts per run (default 4)")
    ap.add_argument("--best-of", type=int, default=4, help="perturbed draws per group whose lowest objective "
                    "per part gives gpr's `best` targets (default 4)")
    ap.add_argument("--neutral-jitter", type=float, default=None, help="the evaluation's jitter of the neutral "
                    "start (evaluation.identification.neutral_jitter; default: the run's; 0: the neutral profile)")
    ap.add_argument("--fits", default=FITS, help="folder for the identified profiles (relative: to the project root)")
    args = ap.parse_args()
    for variant in (GivenGPR, OneStandardErrorGPR, GridGPR):   # registered when the script runs, not on import
        METHODS.register(variant)
    if args.table:
        print(table(read_rows(args.out)))
        return
    for run in args.runs:
        perturb_run(Path(run), args.out, args.eps, args.perturbations, args.best_of, args.fits, args.neutral_jitter)


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
