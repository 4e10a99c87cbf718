"""System identification of many parts at once: each part keeps its own head and its own loss, and all of
them share one batched simulation per optimiser step (the oracle and gpr baselines fit every test or
training part this way).

Adam updates every parameter from its own gradient alone, and the sum of the per-part losses gives each
head exactly the gradient of its own part's loss, so the joint fit takes the same steps as fitting the
parts one by one, in one simulator call per step instead of one per part.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from pipe.data.batches import collate_trials
from pipe.data.prepared import PartData
from pipe.evaluation.context import EvalContext
from pipe.model.interfaces import ParameterHead, ParameterProfile
from pipe.model.losses import masked_mse
from pipe.model.pipe_model import PIPEModel


class PartHeads(ParameterHead):
    """One head per part, each applied to its own contiguous block of rows (`counts` rows per part)."""

    def __init__(self, heads: list[ParameterHead], counts: list[int]) -> None:
        super().__init__(heads[0].latent_dim, heads[0].num_parameters)
        self.heads = nn.ModuleList(heads)
        self.counts = counts

    def forward(self, z: torch.Tensor, depth_max: torch.Tensor) -> ParameterProfile:
        blocks = zip(self.heads, z.split(self.counts), depth_max.split(self.counts))
        profiles = [head(zs, ds) for head, zs, ds in blocks]
        return lambda depth: torch.cat([p(d) for p, d in zip(profiles, depth.split(self.counts))])


def identify(ctx: EvalContext, parts: list[PartData]) -> list[PIPEModel]:
    """Each part's head fitted to the part's own trials (its latent code fixed) for `oracle_steps` Adam
    steps at `oracle_lr`, starting from PIPE's head; cached per part in the context."""
    fits = ctx.cache.setdefault("identified", {})
    todo = list({p.name: p for p in parts if p.name not in fits}.values())
    if todo:
        heads = [copy.deepcopy(ctx.model.head).train().requires_grad_(True) for _ in todo]
        counts = [len(p.profiles) for p in todo]
        batch = collate_trials([(ctx.index[p.name], profile) for p in todo for profile in p.profiles])
        joint = ctx.model.with_head(PartHeads(heads, counts))
        z = ctx.latents[batch.part]
        optimiser = torch.optim.Adam(joint.head.parameters(), lr=ctx.settings.get("oracle_lr", 1e-3),
                                     fused=True)     # one fused update for all the heads' parameters
        with torch.enable_grad():
            for _ in range(ctx.settings.get("oracle_steps", 200)):
                optimiser.zero_grad()
                force = joint(z, batch.depth, batch.dt)
                loss = sum(masked_mse(f, m, k) for f, m, k in
                           zip(force.split(counts), batch.force.split(counts), batch.mask.split(counts)))
                loss.backward()
                optimiser.step()
        for part, head in zip(todo, heads):
            fits[part.name] = ctx.model.with_head(head.eval().requires_grad_(False))
    return [fits[p.name] for p in parts]
