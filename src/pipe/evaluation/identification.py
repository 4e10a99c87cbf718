"""System identification from scratch: the dynamic model's parameter profiles fitted directly to one part's
own recordings, as classical identification does (the oracle, oracle_clean and gpr's targets).

Each part is fitted from several starts (`restarts`: the neutral profile, then random ones; see
`ParameterHead.free_profiles`), each start on its own, by L-BFGS with a strong Wolfe line search
(`torch.optim.LBFGS`) on the objective

    log(MSE + 1e-6 P) + ridge * mean(v^2)

with MSE the mean squared force error over the part's trials, P the mean squared target force and v the
free parameters (the unconstrained values of `free_profiles`, 0 at the neutral profile). This is a MAP
estimate with a Gaussian prior on v when the noise variance is unknown (profiling it out leaves the log of
the MSE), so `ridge` weighs alike in every domain, whatever the noise and the forces; 1e-6 P is a floor
for noise-free fits (within 0.1 % rms of the force counts as exact). The profiles are identifiable only in
part: mds2's four parameters matter up to a common factor, and the recordings constrain the static gain
b0 / a2 away from the deepest point only weakly; without the ridge a fit wanders along these shallow
valleys for thousands of evaluations into profiles whose static curves are off by orders of magnitude.
The ridge picks the solution nearest the neutral profile, which keeps the oracle's static curves
meaningful and gpr's targets comparable across parts (BENCHMARKS.md has the measurements).

The parameters are scaled by the part's own recordings (`DynamicModel.parameter_scales` of its trials' typical
force and depth), not by the training parts': the neutral profile, the random starts and the ridge's centre
are the part's own, so a part's fit does not depend on what PIPE was trained on (the oracle of a learning
curve is the same at every training-set size). With `cache` set, fits are stored in and reused from that
folder (`pipe.evaluation.fit_cache`).

Stopping rule, per start: every `check_every` L-BFGS iterations the lowest objective so far is compared with
the one at the previous check; the start has converged when it fell by less than `tolerance` (the MSE by
less than that share); otherwise it stops after `max_evaluations` loss-and-gradient evaluations. Each start
keeps the parameters of its lowest objective, and each part the start with the lowest objective of all; the
reported loss is the mean squared force error there.
"""

from __future__ import annotations

import math
import os
import zlib
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from pipe.data.batches import TrialBatch, collate_trials
from pipe.data.prepared import PartData, profile_scales
from pipe.data.preprocess import Profile
from pipe.errors import options_dataclass
from pipe.evaluation.context import EvalContext
from pipe.evaluation.fit_cache import fit_key, load_fit, store_fit
from pipe.model.interfaces import ParameterHead
from pipe.model.losses import masked_mse
from pipe.model.pipe_model import PIPEModel


@dataclass(frozen=True)
class IdentificationSettings:
    restarts: int = 3             # starts per part: the neutral profile and restarts - 1 random ones
    check_every: int = 20         # L-BFGS iterations between two convergence checks
    tolerance: float = 1e-4       # converged once check_every iterations lower the objective by less than this
    max_evaluations: int = 3000   # loss-and-gradient evaluations per start at most
    history: int = 20             # L-BFGS's memory: the last steps and gradient changes it keeps
    ridge: float = 0.1            # weight of the pull towards the neutral profile (see the module's docstring)
    cache: str | None = None      # a folder (relative: to the project root) to store fits in and reuse them
                                  # from; None: within the run only

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


def start_head(template: ParameterHead, name: str, seed: int, start: int) -> ParameterHead:
    """The free one-set head of a part's start: the neutral profile for start 0; for the others a random
    start from a generator of its own (seed, start, part name), so that a part starts alike whichever parts
    are identified with it. (torch's generator keeps 32 bits of a seed: numpy's SeedSequence mixes the
    three into them.)"""
    rows = torch.zeros(1, dtype=torch.long)
    if start == 0:
        return template.free_profiles(rows)
    entropy = np.random.SeedSequence([seed, start, zlib.crc32(name.encode())]).generate_state(1)[0]
    return template.free_profiles(rows, torch.Generator().manual_seed(int(entropy)))


class StartFit(NamedTuple):
    objective: float     # the lowest objective reached: log(MSE + 1e-6 P) plus the ridge term
    loss: float          # the mean squared force error there [N^2]
    evaluations: int
    converged: bool      # the stopping rule was met before max_evaluations


def fit_start(model: PIPEModel, head: ParameterHead, batch: TrialBatch,
              settings: IdentificationSettings) -> StartFit:
    """Fit one start's free head to a part's trials in place; it ends where its objective was lowest."""
    joint = model.with_head(head.train())
    z = torch.zeros(len(batch.part), head.latent_dim)
    power = float(batch.force[batch.mask].pow(2).mean())
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
        mse = masked_mse(joint(z, batch.depth, batch.dt), batch.force, batch.mask)
        values = torch.cat([p.reshape(-1) for p in head.parameters()])
        loss = torch.log(mse + 1e-6 * power) + settings.ridge * values.pow(2).mean()
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


def _identify_part(ctx: EvalContext, part: PartData, trials: list[Profile],
                   settings: IdentificationSettings) -> Identified:
    batch = collate_trials([(0, p) for p in trials])
    scaled = ctx.model.with_head(ctx.model.head, ctx.model.dynamics.parameter_scales(*profile_scales(trials)))
    heads = [start_head(ctx.model.head, part.name, ctx.seed, start) for start in range(settings.restarts)]
    fits = [fit_start(scaled, head, batch, settings) for head in heads]
    best = min(range(len(fits)), key=lambda k: fits[k].objective)
    return Identified(scaled.with_head(heads[best]), fits[best].loss, fits[best].evaluations,
                      fits[best].converged)


def _identify_cached(ctx: EvalContext, part: PartData, trials: list[Profile], target: str,
                     settings: IdentificationSettings) -> Identified:
    """`_identify_part`, through the folder `settings.cache` where one is set."""
    if settings.cache is None:
        return _identify_part(ctx, part, trials, settings)
    folder = Path(os.environ.get("PROJECT_ROOT", ".")) / settings.cache   # a relative folder: from the root
    decisive = {name: value for name, value in asdict(settings).items() if name != "cache"}
    seed = ctx.seed if settings.restarts > 1 else None      # the neutral start alone draws nothing
    key = fit_key(part.name, trials, target, decisive, seed, ctx.dt, ctx.model.head, ctx.model.dynamics)
    stored = load_fit(folder, part.name, key)
    if stored is not None:
        head = ctx.model.head.free_profiles(torch.zeros(1, dtype=torch.long))
        head.load_state_dict(stored["head"])
        head.eval().requires_grad_(False)
        return Identified(ctx.model.with_head(head, stored["theta_scale"]), stored["loss"], stored["evaluations"],
                          stored["converged"])
    fitted = _identify_part(ctx, part, trials, settings)
    store_fit(folder, part.name, key, {"head": fitted.model.head.state_dict(), "theta_scale": fitted.model.theta_scale,
                                       "loss": fitted.loss, "evaluations": fitted.evaluations,
                                       "converged": fitted.converged})
    return fitted


def identify(ctx: EvalContext, parts: list[PartData], target: str = "force",
             restarts: int | None = None) -> list[Identified]:
    """Each part's profiles identified from scratch on its own trials' `target` ("force", or "force_clean",
    the noise-free force of synthetic data), from `restarts` starts (default: the configured number);
    cached per part, target and number of starts in the context."""
    settings = IdentificationSettings.from_config(ctx.settings.get("identification"))
    if restarts is not None:
        settings = replace(settings, restarts=restarts)
    fits = ctx.cache.setdefault(f"identified_{target}_{settings.restarts}", {})
    for part in parts:
        if part.name not in fits:
            trials = [Profile(p.time, p.depth, getattr(p, target)) for p in part.profiles]
            fits[part.name] = _identify_cached(ctx, part, trials, target, settings)
    return [fits[p.name] for p in parts]
