"""System identification's objective for one start as a function of the free head's flat parameters, forward
and adjoint in compiled pieces chained on float64 numpy arrays (`evaluation.identification.engine=compiled`).

The same objective as `pipe.evaluation.identification.fit_start`'s torch closure,

    log(E + 1e-6 P) + ridge * mean(v^2),

through the same model (the head's profiles times the parameter scales, held at their midpoints over each
period, the dynamic model's state space, the simulation from zero state, the masked squared force error),
but each piece is one compiled call (`ParameterHead.compiled`, `DynamicModel.state_space_arrays`,
`pipe.model.ltv_numba.simulate_arrays`) and the glue a few numpy operations: torch's per-operation cost,
about half of an evaluation on tensors of a few hundred numbers, is gone. Float64 throughout, so that
the optimiser's line search sees a smooth objective.
"""

from __future__ import annotations

import numpy as np

from pipe.data.batches import TrialBatch
from pipe.evaluation.force_error import trial_weights
from pipe.model.interfaces import CompiledProfiles, ParameterHead
from pipe.model.pipe_model import PIPEModel


class CompiledObjective:
    """objective(values) -> (objective, MSE, gradient) for one start's flat parameters `values` (float64)."""

    def __init__(self, model: PIPEModel, profiles: CompiledProfiles, batch: TrialBatch, ridge: float,
                 loss: str = "nmse") -> None:
        from pipe.model import ltv_numba  # numba: imported where identification runs, not with the module

        self.simulate, self.simulate_backward = ltv_numba.simulate_arrays, ltv_numba.simulate_arrays_backward
        self.model, self.profiles, self.ridge, self.dt = model, profiles, ridge, batch.dt
        depth = batch.depth.double().numpy()
        self.u = 0.5 * (depth[:, 1:] + depth[:, :-1])
        self.scale = model.theta_scale.double().numpy()
        self.force = batch.force.double().numpy()
        self.mask = batch.mask.numpy().astype(np.float64)
        self.count = float(self.mask.sum())
        self.weights = trial_weights(batch.force.double(), batch.mask, loss).numpy()[:, None]
        self.floor = 1e-6 * float(np.sum(self.weights * self.force ** 2 * self.mask))

    @classmethod
    def of(cls, model: PIPEModel, head: ParameterHead, batch: TrialBatch, ridge: float,
           loss: str = "nmse") -> CompiledObjective | None:
        """The objective of fitting `head` (a free head of one set) within `model`, or None where the head or
        the dynamic model offer no compiled form (or numba is missing): the torch engine fits it then."""
        if model.dynamics.state_space_arrays(np.ones((1, len(model.theta_scale)))) is None:
            return None
        try:
            profiles = head.compiled(batch.depth.double().numpy())
            return None if profiles is None else cls(model, profiles, batch, ridge, loss)
        except ImportError:
            return None

    @np.errstate(over="ignore", invalid="ignore", divide="ignore")
    def __call__(self, values: np.ndarray) -> tuple[float, float, np.ndarray]:
        """Where a line search tries a step whose simulation diverges, the objective is infinite or NaN:
        that start then ends where its objective was lowest (`fit_compiled` never keeps a non-finite one),
        so numpy's warnings of overflow, invalid values and division by zero are silenced here."""
        theta = self.profiles.forward(values) * self.scale
        held = 0.5 * (theta[:, 1:] + theta[:, :-1])
        a, b, state_space_backward = self.model.dynamics.state_space_arrays(held)
        x = self.simulate(a, b, self.u, self.dt)
        error = (x[:, :, 0] - self.force) * self.mask
        mse = float(np.dot(error.ravel(), error.ravel())) / self.count
        weighted = float(np.sum(self.weights * error ** 2))
        objective = np.log(weighted + self.floor) + self.ridge * float(np.dot(values, values)) / len(values)

        grad_x = np.zeros_like(x)
        grad_x[:, :, 0] = error * (2.0 * self.weights / (weighted + self.floor))
        grad_a, grad_b = self.simulate_backward(a, b, self.u, self.dt, x, grad_x)
        grad_held = state_space_backward(grad_a, grad_b)
        grad_theta = np.zeros_like(theta)
        grad_theta[:, 1:] += 0.5 * grad_held
        grad_theta[:, :-1] += 0.5 * grad_held
        grad = self.profiles.backward(grad_theta * self.scale) + (2.0 * self.ridge / len(values)) * values
        return float(objective), mse, grad
