"""Where one system-identification evaluation (the loss and gradient an L-BFGS step asks for) spends its time,
on a conn test part's trials (10 trials of up to 487 samples), from the neutral start, as
`pipe.evaluation.identification.fit_start` computes it:

- the whole evaluation at the part's length, and with the trials cut to 100 and 10 samples (what does not
  grow with the samples is the fixed cost of torch's autograd and Python);
- its parts: the Gaussian head's profile Theta(p_z) (forward + backward), the discretisation and the
  recurrence of the compiled simulator;
- the same evaluation on the compiled engine (`engine=compiled`, float64: `CompiledObjective`) and its
  pieces: the free profiles' forward and backward, the state space, the simulation's forward and backward;
- the starts of three parts (two starts each) fitted one after another (`fit_jobs` with one worker, what the
  evaluation does with `workers=1`; every start runs on one thread) and in two worker processes
  (`workers=2`, the default on 2 cores; their start-up included).

    python benchmarks/identification_step.py [--repeats 200]
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path

from timing import median_seconds

ROOT = Path(__file__).resolve().parents[1]


def median_ms(fn, repeats: int) -> float:
    return median_seconds(fn, repeats) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=200)
    args = parser.parse_args()
    os.environ.setdefault("PROJECT_ROOT", str(ROOT))
    import torch
    from identification_setup import identification_setup

    from pipe.data.batches import collate_trials
    from pipe.data.prepared import profile_scales
    from pipe.data.preprocess import Profile
    from pipe.evaluation.identification import StartJob, fit_jobs, part_jobs, start_head
    from pipe.model import ltv
    from pipe.model.losses import masked_mse

    setup = identification_setup("conn")
    test, ctx, settings, dynamics = setup.test, setup.ctx, setup.settings, setup.dynamics
    jobs = [(part, [Profile(p.time, p.depth, p.force) for p in part.profiles]) for part in test]
    part, trials = jobs[0]
    batch = collate_trials([(0, p) for p in trials])
    scaled = ctx.model.with_head(ctx.model.head, ctx.model.dynamics.parameter_scales(*profile_scales(trials)))
    free = start_head(ctx.model.head, part.name, 0, 0)
    joint = scaled.with_head(free.train())
    z = torch.zeros(len(batch.part), free.latent_dim)

    def evaluation(samples: int) -> None:
        depth, force, mask = (t[:, :samples] for t in (batch.depth, batch.force, batch.mask))
        for p in free.parameters():
            p.grad = None
        mse = masked_mse(joint(z, depth, batch.dt), force, mask)
        values = torch.cat([p.reshape(-1) for p in free.parameters()])
        (torch.log(mse + 1e-6) + settings.ridge * values.pow(2).mean()).backward()

    samples = batch.depth.shape[1]
    print(f"{part.name}: {len(trials)} trials of up to {samples} samples; median of {args.repeats}, "
          f"{torch.get_num_threads()} torch threads")
    print("| part of one evaluation (forward + backward) | ms |")
    print("| --- | --- |")
    for length in (samples, 100, 10):
        ms = median_ms(lambda length=length: evaluation(length), args.repeats)
        print(f"| the whole evaluation, {length} samples | {ms:.2f} |")

    depth_max = batch.depth.abs().amax(dim=1)

    def profile() -> None:
        free.zero_grad(set_to_none=True)
        joint.profile(z, depth_max)(batch.depth).sum().backward()

    with torch.no_grad():
        theta = joint.profile(z, depth_max)(batch.depth)
        a, b = dynamics.state_space(ltv.midpoints(theta))
    leaves = [t.clone().requires_grad_() for t in (a, b)]
    u = ltv.midpoints(batch.depth)
    phi, gamma = (t.detach() for t in ltv.discretize(a, b, batch.dt))
    steps = [t.clone().requires_grad_() for t in (phi, gamma)]
    parts = {"Theta(p_z) of the Gaussian head": profile,
             "discretisation (compiled)": lambda: sum(t.sum() for t in ltv.discretize(*leaves, batch.dt)).backward(),
             "recurrence (compiled)": lambda: ltv.recurrence(*steps, u).sum().backward()}
    for name, fn in parts.items():
        print(f"| {name} | {median_ms(fn, args.repeats):.2f} |")

    import numpy as np

    from pipe.evaluation.compiled_objective import CompiledObjective

    objective = CompiledObjective.of(scaled, free, batch, settings.ridge)
    values = torch.cat([p.detach().reshape(-1) for p in free.parameters()]).double().numpy()
    theta = objective.profiles.forward(values) * objective.scale
    held = 0.5 * (theta[:, 1:] + theta[:, :-1])
    a, b, _ = dynamics.state_space_arrays(held)
    x = objective.simulate(a, b, objective.u, batch.dt)
    grad_theta, grad_x = np.ones_like(theta), np.ones_like(x)
    pieces = {"compiled engine: the whole evaluation (float64)": lambda: objective(values),
              "compiled engine: free profiles, forward": lambda: objective.profiles.forward(values),
              "compiled engine: free profiles, backward": lambda: objective.profiles.backward(grad_theta),
              "compiled engine: state space (numpy)": lambda: dynamics.state_space_arrays(held),
              "compiled engine: simulation, forward": lambda: objective.simulate(a, b, objective.u, batch.dt),
              "compiled engine: simulation, backward": lambda: objective.simulate_backward(
                  a, b, objective.u, batch.dt, x, grad_x)}
    for name, fn in pieces.items():
        print(f"| {name} | {median_ms(fn, args.repeats):.2f} |")

    two = replace(settings, restarts=2)

    def start_jobs() -> list[StartJob]:
        return [job for part, trials in jobs for job in part_jobs(ctx, part.name, trials, two)]

    print("\n| three parts, two starts each | seconds |")
    print("| --- | --- |")
    for workers in (1, 2):
        start = time.perf_counter()
        fit_jobs(start_jobs(), workers)
        print(f"| fit_jobs, {workers} worker(s) of one thread | {time.perf_counter() - start:.2f} |")

if __name__ == "__main__":
    main()
