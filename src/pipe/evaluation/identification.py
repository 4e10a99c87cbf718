"""System identification from scratch: the dynamic model's parameter profiles fitted directly to one part's
own recordings, as classical identification does (the oracle, oracle_clean and gpr's targets).

Each part is fitted from several starts (`restarts`: the neutral profile, then random ones; see
`ParameterHead.free_profiles`), all parts and starts in one batched simulation per Adam step. Every
(part, start) set has its own parameters and its own loss (the mean squared force error over its trials),
and Adam updates every parameter from its own gradient alone, so the joint fit takes each set's own steps.

Stopping rule, per set: its learning rate halves after `patience` steps without an improvement of its loss
by more than `tolerance` times the loss (or times 1e-3 of the mean squared target force, whichever is
larger: a noise-free fit approaching zero loss converges too); it has converged once the rate has halved
`decays` times, and it then leaves the batch; the fit ends when every set has converged or after
`max_steps`. Each set keeps the parameters of its lowest loss, and each part the start with the lowest
loss of all.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, fields, replace
from typing import Any

import torch

from pipe.data.batches import TrialBatch, collate_trials
from pipe.data.prepared import PartData
from pipe.data.preprocess import Profile
from pipe.errors import PipeError
from pipe.evaluation.context import EvalContext
from pipe.model.interfaces import ParameterHead
from pipe.model.pipe_model import PIPEModel


@dataclass(frozen=True)
class IdentificationSettings:
    restarts: int = 3          # starts per part: the neutral profile and restarts - 1 random ones
    lr: float = 0.02           # Adam's initial learning rate
    patience: int = 50         # steps without a relative improvement of `tolerance` before the rate halves
    tolerance: float = 1e-3
    decays: int = 4            # a set has converged once its rate has halved this often
    max_steps: int = 3000

    @classmethod
    def from_config(cls, values: dict[str, Any] | None) -> IdentificationSettings:
        values = dict(values or {})
        unknown = set(values) - {f.name for f in fields(cls)}
        if unknown:
            raise PipeError(f"unknown evaluation.identification option(s) {sorted(unknown)}; "
                            f"known: {[f.name for f in fields(cls)]}")
        return cls(**values)


@dataclass
class Identified:
    model: PIPEModel     # PIPE's encoder and dynamic model with the part's identified profiles as head
    loss: float          # the kept start's lowest mean squared force error [N^2]
    iterations: int      # Adam steps that start took until it converged (or max_steps)
    converged: bool


def _one_set(head: ParameterHead, template: ParameterHead, index: int) -> ParameterHead:
    """A one-set free head holding set `index` of `head` (the sets lie along every parameter's first axis)."""
    single = template.free_profiles(torch.zeros(1, dtype=torch.long))
    with torch.no_grad():
        for mine, theirs in zip(single.parameters(), head.parameters()):
            mine.copy_(theirs[index:index + 1])
    return single.eval().requires_grad_(False)


def _starts(template: ParameterHead, rows: torch.Tensor, names: list[str], seed: int, restarts: int) -> ParameterHead:
    """The free head of every (start, part) set, set k * parts + i for start k of part i: the neutral profile
    for start 0; for the others, each part's random start from its own generator (seed, start, part name),
    so that a part starts alike whichever parts it is fitted with."""
    head = template.free_profiles(rows)
    with torch.no_grad():
        for k in range(1, restarts):
            for i, name in enumerate(names):
                generator = torch.Generator().manual_seed((seed * 1000 + k) * 2**32 + zlib.crc32(name.encode()))
                drawn = template.free_profiles(torch.zeros(1, dtype=torch.long), generator)
                for mine, theirs in zip(head.parameters(), drawn.parameters()):
                    mine[k * len(names) + i] = theirs[0]
    return head


def _rows(batch: TrialBatch, keep: torch.Tensor) -> TrialBatch:
    return TrialBatch(batch.part[keep], batch.depth[keep], batch.force[keep], batch.mask[keep], batch.dt)


def _fit(ctx: EvalContext, parts: list[PartData], profiles: list[list[Profile]],
         settings: IdentificationSettings) -> list[Identified]:
    template, count_parts = ctx.model.head, len(parts)
    owner = torch.tensor([i for i, trials in enumerate(profiles) for _ in trials])      # part of each trial
    row_set = torch.cat([owner + k * count_parts for k in range(settings.restarts)])   # set of each row
    sets = settings.restarts * count_parts
    head = _starts(template, row_set, [p.name for p in parts], ctx.seed, settings.restarts).train()
    joint = ctx.model.with_head(head)
    every_row = collate_trials([(0, p) for _ in range(settings.restarts) for trials in profiles for p in trials])
    samples = torch.zeros(sets).index_add_(0, row_set, every_row.mask.sum(1).float())
    power = torch.zeros(sets).index_add_(0, row_set, (every_row.force.pow(2) * every_row.mask).sum(1)) / samples
    optimiser = torch.optim.Adam(head.parameters(), lr=settings.lr, fused=True)

    best, reference = torch.full((sets,), torch.inf), torch.full((sets,), torch.inf)
    waited, halvings, iterations = (torch.zeros(sets, dtype=torch.long) for _ in range(3))
    kept = [p.detach().clone() for p in head.parameters()]
    fitting = None
    with torch.enable_grad():
        for _ in range(settings.max_steps):
            active = halvings < settings.decays
            if not active.any():
                break
            if fitting is None or not torch.equal(active, fitting):    # simulate the unconverged sets only
                fitting = active
                keep = active[row_set]
                head.rows = row_set[keep]
                batch = _rows(every_row, keep)
                z = torch.zeros(len(head.rows), template.latent_dim)
            optimiser.zero_grad()
            error = ((joint(z, batch.depth, batch.dt) - batch.force).pow(2) * batch.mask).sum(1)
            loss = torch.zeros(sets).index_add_(0, head.rows, error) / samples
            loss.sum().backward()
            current = torch.where(active, loss.detach(), torch.inf)
            improved = current < best
            best = torch.where(improved, current, best)
            for store, p in zip(kept, head.parameters()):
                store[improved] = p.detach()[improved]
            margin = settings.tolerance * torch.maximum(reference, 1e-3 * power)
            progress = current < torch.where(reference.isinf(), torch.inf, reference - margin)
            reference = torch.where(progress, current, reference)
            waited = torch.where(progress, 0, waited + active.long())
            stalled = waited >= settings.patience
            halvings += stalled.long()
            waited[stalled] = 0
            iterations += active.long()
            rate = torch.where(halvings < settings.decays, 0.5 ** halvings.float(), 0.0)
            before = [p.detach().clone() for p in head.parameters()]
            optimiser.step()
            with torch.no_grad():      # each set's own learning rate: scale its share of the update
                for p, old in zip(head.parameters(), before):
                    p.copy_(old + rate.view(-1, *([1] * (p.dim() - 1))) * (p - old))
    with torch.no_grad():
        for p, v in zip(head.parameters(), kept):
            p.copy_(v)
    results = []
    for i in range(count_parts):
        k = int(best[i::count_parts].argmin()) * count_parts + i
        results.append(Identified(ctx.model.with_head(_one_set(head, template, k)), float(best[k]),
                                  int(iterations[k]), bool(halvings[k] >= settings.decays)))
    return results


def identify(ctx: EvalContext, parts: list[PartData], target: str = "force",
             restarts: int | None = None) -> list[Identified]:
    """Each part's profiles identified from scratch on its own trials' `target` ("force", or "force_clean",
    the noise-free force of synthetic data), from `restarts` starts (default: the configured number);
    cached per part, target and number of starts in the context."""
    settings = IdentificationSettings.from_config(ctx.settings.get("identification"))
    if restarts is not None:
        settings = replace(settings, restarts=restarts)
    fits = ctx.cache.setdefault(f"identified_{target}_{settings.restarts}", {})
    todo = list({p.name: p for p in parts if p.name not in fits}.values())
    if todo:
        profiles = [[Profile(p.time, p.depth, getattr(p, target)) for p in part.profiles] for part in todo]
        for part, fitted in zip(todo, _fit(ctx, todo, profiles, settings)):
            fits[part.name] = fitted
    return [fits[p.name] for p in parts]
