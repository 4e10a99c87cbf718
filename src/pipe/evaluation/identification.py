"""System identification from scratch: the dynamic model's parameter profiles fitted directly to one part's
own recordings, as classical identification does (the oracle, oracle_clean and gpr's targets).

Each part is fitted from several starts (`restarts`: the neutral profile, then random ones; see
`ParameterHead.free_profiles`), each start on its own, by L-BFGS (see the engines below) on the objective

    log(E + 1e-6 P) + ridge * mean(v^2)

with E the force error under `loss`, P the target force's power weighed alike and v the free parameters
(the unconstrained values of `free_profiles`, 0 at the neutral profile). With `loss=nmse` (the default since
2026-11-30) E is each trial's squared error over its force's squared deviation from its mean, averaged over
the trials: 1 - FIT(F) / 100, the figure the oracle is scored by, as stage 2's `stages.head.loss=nmse`
trains PIPE. With `loss=mse` (before) E is the mean squared force error over the part's trials, in which a
trial whose force varies more weighs more: on a pin whose one trial of ten varied 30 times more than the
others, that fit scored 15 % FIT(F) where PIPE's prediction scored 55 (docs/experiments.md, "The oracle
fitted to what it is scored by"). This is a MAP estimate with a Gaussian prior on v when the noise
variance is unknown (each trial's in proportion to its force's variance under nmse; profiling it out
leaves the log of E), so `ridge` weighs alike in every domain, whatever the noise and the forces; 1e-6 P is
a floor for noise-free fits (within 0.1 % rms of the force counts as exact). The profiles are identifiable only in
part: mds2's four parameters matter up to a common factor, and the recordings constrain the static gain
b0 / a2 away from the deepest point only weakly; without the ridge a fit wanders along these shallow
valleys for thousands of evaluations into profiles whose static curves are off by orders of magnitude.
The ridge picks the solution nearest the neutral profile, which keeps the oracle's static curves
meaningful and gpr's targets comparable across parts (BENCHMARKS.md has the measurements).

Two engines fit a start (`engine`): "compiled" (the default), scipy's L-BFGS-B (`scipy.optimize.minimize`,
memory `history`, its own line search) on the objective in float64, forward and gradient in compiled pieces
(`pipe.evaluation.compiled_objective`) where the head and the dynamic model offer them (the Gaussian head,
mds1 and mds2), the torch engine elsewhere; and "torch", `torch.optim.LBFGS` with a strong Wolfe line search
on the torch model in float32 (the default until 2026-11-26), about 2.5x slower. The two reach fits of the
same quality by different steps, in different local minima (BENCHMARKS.md), so not the same fits.

The parameters are scaled by the part's own recordings (`DynamicModel.parameter_scales` of its trials' typical
force and depth), not by the training parts': the neutral profile, the random starts and the ridge's centre
are the part's own, so a part's fit does not depend on what PIPE was trained on (the oracle of a learning
curve is the same at every training-set size). With `cache` set, fits are stored in and reused from that
folder (`pipe.evaluation.fit_cache`).

With `via_mse` (the default) and a loss other than mse, every start is fitted twice: directly on `loss`, and on
the pooled MSE first, then continued on `loss` from where that fit ended. The two objectives lead the same
start into different basins, and neither path finds the deepest alone: on a rect plug every direct nmse start
ended at 79 % FIT(F) and one start continued from its pooled fit at 95 %, while on another plug the direct
path was the deeper by 3 points (docs/experiments.md, "The oracle fitted to what it is scored by").

The neutral start is moved by a hair (`neutral_jitter`, 1e-6 times a standard normal draw per free value, from
the run's seed and the part's name; 0 until 2026-12-02). At the neutral profile every local model's amplitude
is 1, so each parameter's profile is flat whatever the sections and widths, and the objective's gradient in
those values is zero but for the machine's rounding: L-BFGS-B's first steps there followed that rounding, so
gpr, whose targets are fitted from that start alone, scored 76.6 % on dsub on one host and 73.3 on another,
at "± 0.00" over the seeds. Moved, the start's first steps follow the draw, and gpr's seed spread shows how far
its targets' basins move its figure (docs/experiments.md, "gpr's targets under a perturbed start").

The starts are independent: `identify_all` fits every start of every part it is asked for at once, in
`workers` processes (by default one per thread of the run). Each start runs on one thread wherever it runs,
so the fits do not depend on the number of workers.

Stopping rule, per start: every `check_every` L-BFGS iterations the lowest objective so far is compared with
the one at the previous check; the start has converged when it fell by less than `tolerance` (the MSE by
less than that share), or (compiled engine) when L-BFGS-B finds no lower objective; otherwise it stops
after `max_evaluations` loss-and-gradient evaluations (per objective, where a start is continued). Each start
keeps the parameters of its lowest objective, and each part the start with the lowest objective of all; the
reported loss is the mean squared force error there.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import pickle
import warnings
import zlib
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import scipy.optimize
import torch
from joblib import Parallel, delayed
from joblib.externals.loky.process_executor import TerminatedWorkerError

from pipe.data.batches import TrialBatch, collate_trials
from pipe.data.prepared import PartData, profile_scales
from pipe.data.preprocess import Profile
from pipe.errors import PipeError, options_dataclass
from pipe.evaluation.compiled_objective import CompiledObjective
from pipe.evaluation.context import EvalContext
from pipe.evaluation.fit_cache import fit_key, load_fit, store_fit
from pipe.evaluation.force_error import trial_weights
from pipe.model import ltv
from pipe.model.interfaces import ParameterHead
from pipe.model.losses import FORCE_LOSSES
from pipe.model.pipe_model import PIPEModel
from pipe.threads import threads_set_to

ENGINES = ("torch", "compiled")


@dataclass(frozen=True)
class IdentificationSettings:
    restarts: int = 12            # starts per part: the neutral profile and restarts - 1 random ones
    check_every: int = 20         # L-BFGS iterations between two convergence checks
    tolerance: float = 1e-4       # converged once check_every iterations lower the objective by less than this
    max_evaluations: int = 10000  # loss-and-gradient evaluations per start at most: a guard against a start
                                  # that never settles, not the stopping rule (BENCHMARKS.md)
    history: int = 20             # L-BFGS's memory: the last steps and gradient changes it keeps
    ridge: float = 0.1            # weight of the pull towards the neutral profile (see the module's docstring)
    cache: str | None = None      # a folder (relative: to the project root) to store fits in and reuse them
                                  # from; None: within the run only
    workers: int | None = None    # processes fitting starts at once; None: the run's torch threads
    engine: str = "compiled"      # "compiled" or "torch" (see the module's docstring)
    loss: str = "nmse"            # the force error fitted: "nmse" (each trial alike, as FIT(F)) or "mse"
    via_mse: bool = True          # each start also fitted on mse first, then continued on `loss` (see above)
    neutral_jitter: float = 1e-6  # the neutral start's free values moved by this times a draw of the run's seed
                                  # (see the module's docstring); 0: the neutral profile itself

    def __post_init__(self) -> None:
        if self.engine not in ENGINES:
            raise PipeError(f"unknown evaluation.identification.engine {self.engine!r}; known: {list(ENGINES)}")
        jitter = self.neutral_jitter
        if isinstance(jitter, bool) or not (isinstance(jitter, (int, float)) and math.isfinite(jitter) and jitter >= 0):
            raise PipeError("evaluation.identification.neutral_jitter must be a finite number, 0 or more, not "
                            f"{jitter!r}")
        if self.loss not in FORCE_LOSSES:
            raise PipeError(f"unknown evaluation.identification.loss {self.loss!r}; known: {list(FORCE_LOSSES)}")

    @classmethod
    def from_config(cls, values: dict[str, Any] | None) -> IdentificationSettings:
        return options_dataclass(cls, values, "evaluation.identification")


@dataclass
class Identified:
    model: PIPEModel     # PIPE's encoder and dynamic model with the part's identified profiles as head
    loss: float          # the kept start's mean squared force error [N^2] where its objective was lowest
    evaluations: int     # loss-and-gradient evaluations that start took until it converged (or the cap)
    converged: bool


class _OutOfEvaluations(Exception):
    """Raised by the loss closure once a start has used `max_evaluations`."""


def start_head(template: ParameterHead, name: str, seed: int, start: int, jitter: float = 0.0) -> ParameterHead:
    """The free one-set head of a part's start: for start 0 the neutral profile, each free value moved by
    `jitter` times a standard normal draw (`neutral_jitter`); for the others a random start. Each draw comes
    from a generator of its own (seed, start, part name), so that a part starts alike whichever parts are
    identified with it. (torch's generator keeps 32 bits of a seed: numpy's SeedSequence mixes the three
    into them.)"""
    rows = torch.zeros(1, dtype=torch.long)
    entropy = np.random.SeedSequence([seed, start, zlib.crc32(name.encode())]).generate_state(1)[0]
    generator = torch.Generator().manual_seed(int(entropy))
    if start > 0:
        return template.free_profiles(rows, generator)
    head = template.free_profiles(rows)
    if jitter > 0:
        with torch.no_grad():
            for parameter in head.parameters():
                parameter.add_(jitter * torch.randn(parameter.shape, generator=generator))
    return head


class StartFit(NamedTuple):
    objective: float     # the lowest objective reached: log(E + 1e-6 P) plus the ridge term
    loss: float          # the mean squared force error there [N^2]
    evaluations: int
    converged: bool      # the stopping rule was met before max_evaluations


def fit_start(model: PIPEModel, head: ParameterHead, batch: TrialBatch,
              settings: IdentificationSettings) -> StartFit:
    """Fit one start's free head to a part's trials in place, on the configured engine and on one thread
    whatever the caller's count (the same arithmetic in every process; on two numba threads the simulation's
    parallel loop over a part's ~10 trials made a compiled evaluation 7x slower); it ends where its
    objective was lowest."""
    with threads_set_to(1):
        if settings.engine == "compiled":
            objective = CompiledObjective.of(model, head, batch, settings.ridge, settings.loss)
            if objective is not None:
                return fit_compiled(objective, head, settings)
        return fit_torch(model, head, batch, settings)


def fit_compiled(objective: CompiledObjective, head: ParameterHead, settings: IdentificationSettings) -> StartFit:
    """The compiled engine: scipy's L-BFGS-B on the float64 objective, the stopping rule checked in its
    iteration callback; the head's parameters end at the lowest objective it evaluated."""
    start = torch.nn.utils.parameters_to_vector(head.parameters()).detach().double().numpy()
    best = (math.inf, math.inf, start)
    evaluations, iterations, previous = 0, 0, math.inf

    def objective_and_gradient(values: np.ndarray) -> tuple[float, np.ndarray]:
        nonlocal best, evaluations
        if evaluations >= settings.max_evaluations:
            raise _OutOfEvaluations
        evaluations += 1
        value, mse, gradient = objective(values)
        if value < best[0]:
            best = (value, mse, values.copy())
        return value, gradient

    def check(intermediate_result: scipy.optimize.OptimizeResult) -> None:
        nonlocal iterations, previous
        iterations += 1
        if iterations % settings.check_every == 0:
            if previous - best[0] < settings.tolerance:
                raise StopIteration
            previous = best[0]

    converged = True     # the stopping rule, or L-BFGS-B finds no lower objective
    options = {"maxcor": settings.history, "maxfun": 2 * settings.max_evaluations,
               "maxiter": 2 * settings.max_evaluations, "ftol": 0.0, "gtol": 0.0}
    try:
        scipy.optimize.minimize(objective_and_gradient, start, jac=True, method="L-BFGS-B", callback=check,
                                options=options)
    except _OutOfEvaluations:
        converged = False
    torch.nn.utils.vector_to_parameters(torch.from_numpy(best[2]).float(), head.parameters())
    head.eval().requires_grad_(False)
    return StartFit(best[0], best[1], evaluations, converged)


def fit_torch(model: PIPEModel, head: ParameterHead, batch: TrialBatch, settings: IdentificationSettings) -> StartFit:
    """The torch engine: `torch.optim.LBFGS` with a strong Wolfe line search on the float32 torch model."""
    joint = model.with_head(head.train())
    z = torch.zeros(len(batch.part), head.latent_dim)
    weights = trial_weights(batch.force, batch.mask, settings.loss)[:, None]
    floor = 1e-6 * float((weights * batch.force.pow(2) * batch.mask).sum())
    optimiser = torch.optim.LBFGS(head.parameters(), lr=1.0, max_iter=settings.check_every,
                                  history_size=settings.history, line_search_fn="strong_wolfe")
    best_loss, best_mse, evaluations = math.inf, math.inf, 0
    kept = [p.detach().clone() for p in head.parameters()]

    def closure() -> torch.Tensor:
        nonlocal best_loss, best_mse, evaluations
        if evaluations >= settings.max_evaluations:
            raise _OutOfEvaluations
        evaluations += 1
        optimiser.zero_grad()
        error = torch.where(batch.mask, joint(z, batch.depth, batch.dt) - batch.force, 0.0)
        mse = error.pow(2).sum() / batch.mask.sum()
        values = torch.cat([p.reshape(-1) for p in head.parameters()])
        loss = torch.log((weights * error.pow(2)).sum() + floor) + settings.ridge * values.pow(2).mean()
        loss.backward()
        if loss.item() < best_loss:
            best_loss, best_mse = loss.item(), mse.item()
            for store, p in zip(kept, head.parameters()):
                store.copy_(p.detach())
        return loss

    converged, previous = False, math.inf
    with torch.enable_grad():
        try:
            while not converged:
                optimiser.step(closure)
                converged = previous - best_loss < settings.tolerance
                previous = best_loss
        except _OutOfEvaluations:
            pass
    with torch.no_grad():
        for p, v in zip(head.parameters(), kept):
            p.copy_(v)
    head.eval().requires_grad_(False)
    return StartFit(best_loss, best_mse, evaluations, converged)


class StartJob(NamedTuple):
    """One start of one part: what a worker process needs to fit it."""
    model: PIPEModel              # the part's parameter scales, head structure and dynamic model (no encoder)
    head: ParameterHead           # the start's free head, fitted in place
    batch: TrialBatch
    settings: IdentificationSettings
    first: str | None = None      # a loss the start is fitted on before `settings.loss` (via_mse), or None


def fit_job(job: StartJob) -> tuple[dict[str, torch.Tensor], StartFit]:
    """A start fitted (`fit_start`; on `job.first` first, then continued on the settings' loss): its head's
    state and its fit, with the evaluations of both fits."""
    before = 0
    if job.first is not None:
        before = fit_start(job.model, job.head, job.batch, replace(job.settings, loss=job.first)).evaluations
        job.head.train().requires_grad_(True)
    fit = fit_start(job.model, job.head, job.batch, job.settings)
    return job.head.state_dict(), fit._replace(evaluations=before + fit.evaluations)


def _fit_pickled(job: bytes, backend: str) -> bytes:
    """One job in a worker process, on the launching process's simulator backend."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TBB threading layer.*")   # shown once by the launching process
        ltv.set_backend(backend)
        return pickle.dumps(fit_job(pickle.loads(job)))


def fit_jobs(jobs: list[StartJob], workers: int) -> list[tuple[dict[str, torch.Tensor], StartFit]]:
    """Every job's fit, in `workers` worker processes or, with one worker or one job, here. The workers are
    joblib's loky processes: fresh interpreters (the compiled kernels' OpenMP thread pool is not safe to
    fork), kept for the next call in this process (their start-up, about 3 s, is paid once), stopped on
    Ctrl-C, and a worker that dies (killed, out of memory) fails the call instead of leaving it waiting. The
    jobs travel pickled with their tensors' data (not through torch's shared memory, which the started
    processes of trainer=ddp had to work around)."""
    if workers <= 1 or len(jobs) <= 1 or multiprocessing.current_process().daemon:   # a daemon starts none
        return [fit_job(job) for job in jobs]
    backend = ltv.get_backend()
    try:
        fits = Parallel(n_jobs=min(workers, len(jobs)), backend="loky", batch_size=1)(
            delayed(_fit_pickled)(pickle.dumps(job), backend) for job in jobs)
    except TerminatedWorkerError as error:
        raise PipeError("a worker process fitting the system identification's starts ended without its result "
                        f"({str(error).splitlines()[0]}): killed, or out of memory? Run again, with "
                        "evaluation.identification.workers=1 to fit every start in this process") from None
    return [pickle.loads(fit) for fit in fits]


class _Pending(NamedTuple):
    fits: dict[str, Identified]   # where the part's fit goes (the context's cache for its target and starts)
    part: PartData
    trials: list[Profile]
    settings: IdentificationSettings
    stored_as: tuple[Path, str] | None    # the cache folder and key to store the fit under


class Request(NamedTuple):
    """Parts to identify on their trials' `target`, from `restarts` starts (None: the configured number)."""
    parts: list[PartData]
    target: str = "force"
    restarts: int | None = None


def _settings(ctx: EvalContext, restarts: int | None) -> IdentificationSettings:
    settings = IdentificationSettings.from_config(ctx.settings.get("identification"))
    return settings if restarts is None else replace(settings, restarts=restarts)


def _cache_key(target: str, restarts: int) -> str:
    return f"identified_{target}_{restarts}"


def _fits(ctx: EvalContext, target: str, settings: IdentificationSettings) -> dict[str, Identified]:
    return ctx.cache.setdefault(_cache_key(target, settings.restarts), {})


def with_fits(ctx: EvalContext, fits: dict[str, Identified], target: str = "force") -> EvalContext:
    """The context with a fresh cache holding `fits` (by part name) as the identification of the trials'
    `target` from the configured number of starts: the oracle (or oracle_clean) of that context scores them
    instead of fitting its own. For fits made elsewhere (an experiment's own starts, twins, other data)."""
    return replace(ctx, cache={_cache_key(target, _settings(ctx, None).restarts): fits})


def _stored(ctx: EvalContext, part: PartData, trials: list[Profile], target: str,
            settings: IdentificationSettings) -> tuple[Identified | None, tuple[Path, str] | None]:
    """The part's fit from the folder `settings.cache` where one is set and holds it, and where to store it."""
    if settings.cache is None:
        return None, None
    folder = Path(os.environ.get("PROJECT_ROOT", ".")) / settings.cache   # a relative folder: from the root
    decisive = {name: value for name, value in asdict(settings).items() if name not in ("cache", "workers")}
    draws = settings.restarts > 1 or settings.neutral_jitter > 0
    seed = ctx.seed if draws else None      # the neutral profile alone draws nothing
    key = fit_key(part.name, trials, target, decisive, seed, ctx.dt, ctx.model.head, ctx.model.dynamics)
    stored = load_fit(folder, part.name, key)
    if stored is None:
        return None, (folder, key)
    head = ctx.model.head.free_profiles(torch.zeros(1, dtype=torch.long))
    head.load_state_dict(stored["head"])
    head.eval().requires_grad_(False)
    return Identified(ctx.model.with_head(head, stored["theta_scale"]), stored["loss"], stored["evaluations"],
                      stored["converged"]), None


def part_jobs(ctx: EvalContext, name: str, trials: list[Profile], settings: IdentificationSettings) -> list[StartJob]:
    """The starts of one part's identification: its trials in one batch, the dynamic model scaled by the part's
    own recordings, one free head per start (`start_head`), and with `via_mse` (where the loss is not mse)
    each start's second job, fitted on mse first, next to it."""
    batch = collate_trials([(0, p) for p in trials])
    scales = ctx.model.dynamics.parameter_scales(*profile_scales(trials))
    simulator = PIPEModel(None, ctx.model.head, ctx.model.dynamics).with_head(ctx.model.head, scales)
    firsts = [None, "mse"] if settings.via_mse and settings.loss != "mse" else [None]
    return [StartJob(simulator, start_head(ctx.model.head, name, ctx.seed, start, settings.neutral_jitter), batch,
                     settings, first)
            for start in range(settings.restarts) for first in firsts]


def identify_all(ctx: EvalContext, requests: list[Request]) -> None:
    """Identify every requested part that the context's cache (and the folder `cache`) does not hold yet,
    all their starts at once, into the context's cache; `identify` then returns them."""
    pending: list[_Pending] = []
    for request in requests:
        settings = _settings(ctx, request.restarts)
        fits = _fits(ctx, request.target, settings)
        for part in request.parts:
            if part.name in fits or any(p.fits is fits and p.part.name == part.name for p in pending):
                continue
            trials = [Profile(p.time, p.depth, getattr(p, request.target)) for p in part.profiles]
            if settings.loss == "nmse" and any(np.ptp(t.force) == 0 for t in trials):
                raise PipeError(f"evaluation.identification.loss=nmse divides each trial's error by its force's "
                                f"variance, but a trial of {part.name} has a constant {request.target}: use "
                                "evaluation.identification.loss=mse, or check the data (pipe data check)")
            stored, stored_as = _stored(ctx, part, trials, request.target, settings)
            if stored is not None:
                fits[part.name] = stored
            else:
                pending.append(_Pending(fits, part, trials, settings, stored_as))
    jobs = [part_jobs(ctx, item.part.name, item.trials, item.settings) for item in pending]
    if not jobs:
        return
    results = iter(fit_jobs([job for starts in jobs for job in starts], _settings(ctx, None).workers
                            or torch.get_num_threads()))
    for item, starts in zip(pending, jobs):
        fitted = [(job, next(results)) for job in starts]
        job, (state, fit) = min(fitted, key=lambda start: start[1][1].objective)
        job.head.load_state_dict(state)
        job.head.eval().requires_grad_(False)
        identified = Identified(ctx.model.with_head(job.head, job.model.theta_scale), fit.loss, fit.evaluations,
                                fit.converged)
        if item.stored_as is not None:
            folder, key = item.stored_as
            store_fit(folder, item.part.name, key,
                      {"head": job.head.state_dict(), "theta_scale": identified.model.theta_scale,
                       "loss": fit.loss, "evaluations": fit.evaluations, "converged": fit.converged})
        item.fits[item.part.name] = identified


def identify(ctx: EvalContext, parts: list[PartData], target: str = "force",
             restarts: int | None = None) -> list[Identified]:
    """Each part's profiles identified from scratch on its own trials' `target` ("force", or "force_clean",
    the noise-free force of synthetic data), from `restarts` starts (default: the configured number);
    cached per part, target and number of starts in the context."""
    identify_all(ctx, [Request(parts, target, restarts)])
    fits = _fits(ctx, target, _settings(ctx, restarts))
    return [fits[p.name] for p in parts]
