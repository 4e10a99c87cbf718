"""PIPE and the baselines it is compared with, behind one interface (DESIGN section 5).

- pipe:     the trained model, from the part's latent code (and a band from its latent distribution).
- oracle:   the same dynamic model and profile structure fitted to the test part's own recordings from
            scratch, to convergence, best of several starts (classical system identification,
            `pipe.evaluation.identification`): an upper bound, since it uses the recordings PIPE does not need.
- oracle_clean: the oracle fitted to and scored against the noise-free force (synthetic data): its error
            is the model structure's alone.
- nearest:  PIPE's parameters for the training part nearest in latent space.
- gpr:      Gaussian-process regression from the latent code to the identified parameter profiles of the
            training parts (each identified like the oracle), the task-parameterised approach.
- blackbox: a neural network from latent code and depth to force, without the physical model.
- mean:     the mean training force over depth.

nearest, gpr and the blackbox read the part's code through the input PIPE's head reads (with code.sections or
code.slices on, the encoder's code, the cloud's cross-section and the mesh's slices together), or through any
other combination of them that has a clearly lower validation error (`CodeBaseline`).
"""

from __future__ import annotations

import copy
import itertools
import logging
import warnings
from abc import ABC, abstractmethod
from dataclasses import replace

import numpy as np
import torch
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel
from torch import nn

from pipe.data.batches import unpad
from pipe.data.prepared import PartData
from pipe.data.slices import SLICE_SIZE
from pipe.evaluation.context import EvalContext
from pipe.evaluation.identification import Identified, Request, identify
from pipe.model.pipe_model import PIPEModel
from pipe.model.sections import SECTION_SIZE
from pipe.model.uncertainty import BandSettings, ForceBands, conformal_offset, force_band
from pipe.registry import Registry

log = logging.getLogger(__name__)


class Method(ABC):
    """A way to predict a test part's force from what the evaluation context offers.

    Register a subclass with `@METHODS.register` (in a plugin package: a module named by a `pipe.plugins`
    entry point) and name it in `evaluation.baselines`.
    """

    name: str
    target = "force"       # the profile field it is scored against: the measured force, or "force_clean"

    def unavailable(self, ctx: EvalContext, parts: list[PartData]) -> str | None:
        """Why the method cannot run on these parts (e.g. data it needs is missing), or None."""
        return None

    def diagnostics(self, ctx: EvalContext, part: PartData) -> dict[str, float]:
        """Extra per-part figures for the results (e.g. an identification's final loss)."""
        return {}

    def identifications(self, ctx: EvalContext, parts: list[PartData]) -> list[Request]:
        """The system identifications (`identify`) the method will ask for to predict these parts, so that
        the evaluation fits every method's starts at once, in its worker processes."""
        return []

    def fit(self, ctx: EvalContext) -> None:
        """Learn whatever the method needs from the training parts."""

    @abstractmethod
    def predict(self, ctx: EvalContext, part: PartData) -> list[np.ndarray]:
        """Predicted force [N] of each of the part's trials, on the trial's own samples."""

    def predict_all(self, ctx: EvalContext, parts: list[PartData]) -> dict[str, list[np.ndarray]]:
        """`predict` for every part; override to share work between the parts (e.g. one batched fit)."""
        return {part.name: self.predict(ctx, part) for part in parts}

    def static_force(self, ctx: EvalContext, part: PartData, depth_max: float,
                     depth: np.ndarray) -> np.ndarray | None:
        """Predicted quasi-static force [N] at the given depths [mm] (trajectory reaching depth_max), if any."""
        return None

    def band(self, ctx: EvalContext, part: PartData) -> ForceBands | None:
        """The nominal prediction band of each of the part's trials, if the method gives one (after `fit`)."""
        return None


METHODS: Registry[type[Method]] = Registry("method")


@torch.no_grad()
def validation_errors(method: Method, ctx: EvalContext) -> np.ndarray:
    """The method's NMSE of the force (1 - FIT/100) on each of the validation parts' trials, in order."""
    return np.array([np.sum((p.force - f) ** 2) / np.sum((p.force - p.force.mean()) ** 2)
                     for part in ctx.val for p, f in zip(part.profiles, method.predict(ctx, part))])


def validation_nmse(method: Method, ctx: EvalContext) -> float:
    """The method's mean NMSE of the force over the validation parts' trials: what the baselines choose
    their hyperparameters and stopping point by (never the test parts)."""
    return float(np.mean(validation_errors(method, ctx)))


def one_standard_error_choice(errors: list[np.ndarray]) -> int:
    """Which of the candidates to keep, given each one's errors on the same validation trials: the first (the
    default) unless others beat it by more than one standard error of their paired difference (after the
    one-standard-error rule of Hastie et al., The Elements of Statistical Learning, 7.10); then the one of
    the lowest mean error among those. Choosing the plain minimum among many candidates on one or two
    validation parts keeps whichever the noise favoured. The trials of a part are not independent, so this
    standard error understates the spread between parts: the rule is the least guard, not a test."""
    def clearly_better(candidate: np.ndarray) -> bool:
        difference = errors[0] - candidate
        return len(difference) > 1 and difference.mean() > difference.std(ddof=1) / np.sqrt(len(difference))

    better = [i for i in range(1, len(errors)) if clearly_better(errors[i])]
    return min(better, key=lambda i: errors[i].mean()) if better else 0


def code_blocks(ctx: EvalContext) -> dict[str, range]:
    """The columns of the latent code by what made them: the encoder's code, then the cloud's cross-section
    (code.sections) and the mesh's slices (code.slices) where the model appends them."""
    sizes = {"sections": SECTION_SIZE if ctx.model.sections is not None else 0,
             "slices": SLICE_SIZE if ctx.model.slices is not None else 0}
    sizes = {"code": ctx.latents.shape[1] - sum(sizes.values())} | sizes
    ends = list(itertools.accumulate(sizes.values()))
    return {name: range(end - size, end) for (name, size), end in zip(sizes.items(), ends) if size}


def code_inputs(ctx: EvalContext) -> dict[str, slice | torch.Tensor]:
    """The parts of the latent code a baseline may read, by name ("code+slices": those blocks of `code_blocks`
    side by side), the first what PIPE's head reads: every combination of the blocks, the larger first; a slice
    of the code where its columns are contiguous, else their indices."""
    blocks = code_blocks(ctx)
    inputs: dict[str, slice | torch.Tensor] = {}
    for size in range(len(blocks), 0, -1):
        for names in itertools.combinations(blocks, size):
            columns = [c for name in names for c in blocks[name]]
            start, end, width = columns[0], columns[-1] + 1, ctx.latents.shape[1]
            if columns != list(range(start, end)):
                inputs["+".join(names)] = torch.tensor(columns)
            else:
                inputs["+".join(names)] = slice(None) if (start, end) == (0, width) else slice(
                    start, end if end < width else None)
    return inputs


class CodeBaseline(Method):
    """A baseline that reads the parts' latent codes. `fit` fits one candidate on each of `code_inputs` and
    keeps what PIPE's head reads (the first) unless another input has a lower validation error by more than
    its standard error (`one_standard_error_choice`; without validation parts, the first), so that an input
    which helps PIPE's head but misleads the baseline does not handicap it."""

    inputs = "code"     # the chosen one of `code_inputs`

    @abstractmethod
    def fit_inputs(self, ctx: EvalContext) -> None:
        """Fit on the training parts, reading their codes through `self.code`."""

    def code(self, ctx: EvalContext, part: PartData) -> torch.Tensor:
        """The part of the part's latent code that the baseline reads."""
        return ctx.latent(part)[code_inputs(ctx)[self.inputs]]

    def standardised_already(self, ctx: EvalContext) -> torch.Tensor:
        """(columns read,) bool: True where the column is the cross-section's or the slices', which the model
        standardised over the same training parts with a floor on their spread (pipe.model.standardiser). A
        baseline keeps those as they are: standardising them again would undo the floor, and a column that the
        training parts do not vary (the number of regions 10 mm from the mating end over 5 training rect plugs)
        would be magnified a million-fold on a part that differs there."""
        columns = torch.arange(ctx.latents.shape[1])[code_inputs(ctx)[self.inputs]]
        encoder = code_blocks(ctx).get("code", range(0))
        return (columns < encoder.start) | (columns >= encoder.stop)

    def fit(self, ctx):
        names = list(code_inputs(ctx)) if ctx.val else list(code_inputs(ctx))[:1]
        candidates = []
        for name in names:
            candidate = copy.copy(self)
            candidate.inputs = name
            candidate.fit_inputs(ctx)
            candidates.append(candidate)
        chosen = candidates[0]
        if len(candidates) > 1:
            errors = [validation_errors(c, ctx) for c in candidates]
            chosen = candidates[one_standard_error_choice(errors)]
            log.info("%s reads %s (validation NMSE: %s)", self.name, chosen.inputs,
                     ", ".join(f"{name} {e.mean():.4f}" for name, e in zip(names, errors)))
        self.__dict__.update(chosen.__dict__)

    def diagnostics(self, ctx, part):
        """Where there was a choice, which inputs it reads (1 or 0; their mean over seeds is the share of the
        seeds that chose them)."""
        blocks = code_blocks(ctx)
        if len(blocks) == 1:
            return {}
        return {f"{self.name}_reads_{name}": float(name in self.inputs.split("+")) for name in blocks}


@torch.no_grad()
def model_forces(ctx: EvalContext, model: PIPEModel, z: torch.Tensor, part: PartData) -> list[np.ndarray]:
    """The force of each of the part's trials from `model` at latent code z (latent,)."""
    batch = ctx.batch(part)
    return unpad(model(z.expand(len(batch.part), -1), batch.depth, batch.dt).numpy(), part)


@torch.no_grad()
def model_static_force(model: PIPEModel, z: torch.Tensor, depth_max: float, depth: np.ndarray) -> np.ndarray:
    p = torch.as_tensor(depth, dtype=torch.float32)[None]
    return model.static_force(z[None], torch.tensor([depth_max]), p)[0].numpy()


@METHODS.register
class PIPE(Method):
    """PIPE's prediction from the part's mean latent code, with a band from its latent distribution
    (`pipe.model.uncertainty`) calibrated on the validation parts."""

    name = "pipe"

    def fit(self, ctx):
        self.settings = BandSettings.from_config(ctx.settings.get("band"))
        self.offset = 0.0
        if ctx.logvars is None or not ctx.val:
            log.info("PIPE's band is left uncalibrated: %s", "no validation parts" if ctx.logvars is not None
                     else "no latent distributions")
            return
        bands = [self._latent_band(ctx, part) for part in ctx.val]
        flat = lambda arrays: np.concatenate([a for band in arrays for a in band])   # noqa: E731
        self.offset = conformal_offset(flat(b[0] for b in bands), flat(b[1] for b in bands),
                                       flat([p.force for p in part.profiles] for part in ctx.val), self.settings.level)

    def _latent_band(self, ctx: EvalContext, part: PartData) -> tuple[list[np.ndarray], list[np.ndarray]]:
        batch = ctx.batch(part)
        lower, upper = force_band(ctx.model, ctx.latent(part), ctx.logvar(part), batch.depth, batch.dt, self.settings)
        return unpad(lower.numpy(), part), unpad(upper.numpy(), part)

    def band(self, ctx, part):
        if ctx.logvars is None:
            return None
        return ForceBands(self.settings.level, self.offset, *self._latent_band(ctx, part))

    def predict(self, ctx, part):
        return model_forces(ctx, ctx.model, ctx.latent(part), part)

    def static_force(self, ctx, part, depth_max, depth):
        return model_static_force(ctx.model, ctx.latent(part), depth_max, depth)


@METHODS.register
class Oracle(Method):
    name = "oracle"

    def identifications(self, ctx, parts):
        return [Request(parts, self.target)]

    def _identified(self, ctx: EvalContext, part: PartData) -> Identified:
        return identify(ctx, [part], self.target)[0]

    def predict(self, ctx, part):
        return model_forces(ctx, self._identified(ctx, part).model, ctx.latent(part), part)

    def static_force(self, ctx, part, depth_max, depth):
        return model_static_force(self._identified(ctx, part).model, ctx.latent(part), depth_max, depth)

    def diagnostics(self, ctx, part):
        fitted = self._identified(ctx, part)
        return {"id_loss": fitted.loss, "id_evals": float(fitted.evaluations), "id_converged": float(fitted.converged)}


@METHODS.register
class OracleClean(Oracle):
    name = "oracle_clean"
    target = "force_clean"

    def unavailable(self, ctx, parts):
        if any(p.force_clean is None for part in parts for p in part.profiles):
            return "the dataset has no noise-free force (F_z_clean)"
        return None


@METHODS.register
class Nearest(CodeBaseline):
    name = "nearest"

    def fit_inputs(self, ctx):
        pass            # nothing to learn: it looks the training parts up

    def _nearest(self, ctx: EvalContext, part: PartData) -> torch.Tensor:
        """The whole latent code of the training part whose code (as read) is nearest to the part's."""
        read = torch.stack([self.code(ctx, p) for p in ctx.train])
        nearest = ctx.train[int(torch.cdist(self.code(ctx, part)[None], read)[0].argmin())]
        return ctx.latent(nearest)

    def predict(self, ctx, part):
        return model_forces(ctx, ctx.model, self._nearest(ctx, part), part)

    def static_force(self, ctx, part, depth_max, depth):
        return model_static_force(ctx.model, self._nearest(ctx, part), depth_max, depth)


@METHODS.register
class GPR(CodeBaseline):
    """Latent code -> log of each identified parameter profile sampled at `grid` fractions of max depth.

    Each training part is identified from scratch like the oracle, but from the neutral start only: the
    regression needs profiles that are comparable across parts, and the best of random starts lands
    different parts in different local minima. The kernel's length scale is chosen on the validation parts
    (`validation_nmse`) among the marginal-likelihood optimum and a fixed grid; without validation parts, by
    leaving each training part out in turn (`leave_one_out_nmse`). It standardises the encoder's
    code by the training parts' mean and std, and reads the rest as the model standardised it
    (`standardised_already`)."""

    name = "gpr"
    grid = np.linspace(0.0, 1.0, 21)
    LENGTH_SCALES = (0.25, 0.5, 1.0, 2.0, 4.0)

    def identifications(self, ctx, parts):
        return [Request(ctx.train, restarts=1)]

    def targets(self, ctx: EvalContext) -> np.ndarray:
        """(training parts, P * G): the regression's outputs, the log of each training part's identified
        profiles at `grid` fractions of its trials' mean max depth, parameter by parameter."""
        targets = []
        for part, identified in zip(ctx.train, identify(ctx, ctx.train, restarts=1)):
            depth_max = float(np.mean([np.abs(p.depth).max() for p in part.profiles]))
            depth = torch.tensor(self.grid * depth_max, dtype=torch.float32)[None]
            theta = identified.model.profile(ctx.latent(part)[None], torch.tensor([depth_max]))(depth)  # (1, G, P)
            targets.append(np.log(theta[0].numpy()).T.ravel())
        return np.stack(targets)

    def fit_inputs(self, ctx):
        x = np.stack([self.code(ctx, part).numpy() for part in ctx.train])
        self.mean, self.std = x.mean(0), x.std(0) + 1e-9
        kept = self.standardised_already(ctx).numpy()
        self.mean[kept], self.std[kept] = 0.0, 1.0
        self.num_parameters = len(ctx.model.dynamics.parameter_names)
        inputs, outputs = (x - self.mean) / self.std, self.targets(ctx)
        kernels = self.kernels(x.shape[1])
        if not ctx.val and len(ctx.train) < 3:    # nothing to choose by: the marginal-likelihood optimum alone
            kernels = kernels[:1]
        fitted = [self.regression(kernel, ctx.seed, inputs, outputs) for kernel in kernels]
        if ctx.val:                 # the kernel of the lowest validation error
            self.gp = fitted[self.validation_choice(ctx, fitted)]
        else:                       # or of the lowest error on each training part left out in turn
            scores = [self.leave_one_out_nmse(ctx, kernel, inputs, outputs) if len(kernels) > 1 else 0.0
                      for kernel in kernels]
            self.gp = fitted[int(np.argmin(scores))]
        self.length_scale = float(self.gp.kernel_.k1.k2.length_scale) / np.sqrt(x.shape[1])

    def validation_choice(self, ctx: EvalContext, fitted: list[GaussianProcessRegressor]) -> int:
        """Which fitted kernel to keep: the one of the lowest mean validation NMSE."""
        scores = []
        for gp in fitted:
            self.gp = gp
            scores.append(validation_nmse(self, ctx))
        return int(np.argmin(scores))

    @staticmethod
    def regression(kernel, seed: int, inputs: np.ndarray, outputs: np.ndarray) -> GaussianProcessRegressor:
        """The kernel's regression fitted to the inputs. sklearn's ConvergenceWarning that a hyperparameter
        ended at its bound is silenced: each candidate kernel is compared with the others on held-out parts,
        so an optimum at a bound is a candidate like any other, and a run printed a dozen of these warnings."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            return GaussianProcessRegressor(kernel, normalize_y=True, random_state=seed).fit(inputs, outputs)

    def leave_one_out_nmse(self, ctx: EvalContext, kernel, inputs: np.ndarray, outputs: np.ndarray) -> float:
        """The mean NMSE of the force over the training parts' trials, each part predicted by the kernel's
        regression fitted (hyperparameters included) to the other training parts: how gpr chooses its length
        scale where there are no validation parts (a leave-one-part-out cross-validation). There the marginal
        likelihood alone can drive the amplitude and length scale to their bounds, so that gpr predicts the
        training parts' mean profile for every part (docs/experiments.md, "gpr with the present identification
        over the same folds"). The codes' standardisation stays the one over all training parts: it reads no
        recording."""
        errors = []
        for i, part in enumerate(ctx.train):
            others = np.arange(len(ctx.train)) != i
            self.gp = self.regression(kernel, ctx.seed, inputs[others], outputs[others])
            errors.append(validation_errors(self, replace(ctx, val=[part])))
        return float(np.mean(np.concatenate(errors)))

    @staticmethod
    def kernels(dims: int) -> list:
        """Candidate kernels on standardised codes: all hyperparameters by maximum marginal likelihood, or the
        RBF length scale fixed at each of LENGTH_SCALES times sqrt(dims) (amplitude and noise by likelihood)."""
        free = ConstantKernel() * RBF(length_scale=np.sqrt(dims)) + WhiteKernel(1e-2)
        return [free, *(ConstantKernel() * RBF(length_scale=f * np.sqrt(dims), length_scale_bounds="fixed")
                        + WhiteKernel(1e-2) for f in GPR.LENGTH_SCALES)]

    def diagnostics(self, ctx, part):
        return super().diagnostics(ctx, part) | {"gpr_length_scale": self.length_scale}

    def _theta(self, ctx: EvalContext, part: PartData, depth: np.ndarray, depth_max: float) -> torch.Tensor:
        log_grid = self.gp.predict(((self.code(ctx, part).numpy() - self.mean) / self.std)[None])[0]
        log_grid = log_grid.reshape(self.num_parameters, len(self.grid))
        u = np.abs(depth) / depth_max
        theta = np.stack([np.exp(np.interp(u, self.grid, row)) for row in log_grid], -1)
        return torch.as_tensor(theta, dtype=torch.float32)

    @torch.no_grad()
    def predict(self, ctx, part):
        out = []
        for profile in part.profiles:
            theta = self._theta(ctx, part, profile.depth, np.abs(profile.depth).max())[None]
            depth = torch.as_tensor(profile.depth, dtype=torch.float32)[None]
            out.append(ctx.model.dynamics(theta, depth, ctx.dt)[0].numpy())
        return out

    @torch.no_grad()
    def static_force(self, ctx, part, depth_max, depth):
        p = torch.as_tensor(depth, dtype=torch.float32)[None]
        return ctx.model.dynamics.static_force(self._theta(ctx, part, depth, depth_max)[None], p)[0].numpy()


@METHODS.register
class BlackBox(CodeBaseline):
    """An MLP f(z, p_z) -> F trained on every sample of the training trials (MSE); no dynamics, no physics.
    Its inputs are standardised (the encoder's code by the training parts' mean and std, the rest as the model
    standardised it, `standardised_already`; depth and force by their scales), and it keeps the weights of its
    lowest validation error, checked every `CHECK_EVERY` steps. With `blackbox_clip` each input is clipped to
    the range the training samples span, so that on a part unlike every training part the MLP does not
    extrapolate in a straight line (docs/experiments.md, "Why the blackbox collapses on a few held-out parts");
    an input inside that range is left as it is (the validation parts, clipped too, may still keep another
    step or input)."""

    name = "blackbox"
    CHECK_EVERY = 100

    def fit_inputs(self, ctx):
        force_scale, depth_scale = ctx.scales
        self.scales = (force_scale, depth_scale)
        codes = torch.stack([self.code(ctx, part) for part in ctx.train])
        self.code_mean, self.code_std = codes.mean(0), codes.std(0) + 1e-6
        kept = self.standardised_already(ctx)
        self.code_mean[kept], self.code_std[kept] = 0.0, 1.0
        with torch.random.fork_rng(devices=[]):   # its initial weights from the run's seed, not from what the
            torch.manual_seed(ctx.seed)            # process drew before (a training in this process, or none)
            self.net = nn.Sequential(nn.Linear(codes.shape[1] + 1, 128), nn.ReLU(), nn.Linear(128, 128), nn.ReLU(),
                                     nn.Linear(128, 128), nn.ReLU(), nn.Linear(128, 1))
        self.bounds = None
        inputs = torch.cat([self._inputs(ctx, part, p.depth) for part in ctx.train for p in part.profiles])
        if ctx.settings.get("blackbox_clip", False):
            self.bounds = (inputs.amin(0), inputs.amax(0))
        force = torch.cat([torch.as_tensor(p.force, dtype=torch.float32) for part in ctx.train
                           for p in part.profiles])
        generator = torch.Generator().manual_seed(ctx.seed)
        optimiser = torch.optim.Adam(self.net.parameters(), lr=1e-3, fused=True)
        steps = ctx.settings.get("blackbox_steps", 2000)
        best, self.best_step, kept = np.inf, steps, None
        for step in range(1, steps + 1):
            rows = torch.randint(len(inputs), (1024,), generator=generator)
            optimiser.zero_grad()
            with torch.enable_grad():
                loss = (self.net(inputs[rows])[:, 0] - force[rows] / force_scale).pow(2).mean()
                loss.backward()
            optimiser.step()
            if ctx.val and (step % self.CHECK_EVERY == 0 or step == steps):
                score = validation_nmse(self, ctx)
                if score < best:
                    best, self.best_step, kept = score, step, copy.deepcopy(self.net.state_dict())
        if kept is not None:
            self.net.load_state_dict(kept)
        self.net.eval().requires_grad_(False)

    def _inputs(self, ctx: EvalContext, part: PartData, depth: np.ndarray) -> torch.Tensor:
        p = torch.as_tensor(depth, dtype=torch.float32)
        code = (self.code(ctx, part) - self.code_mean) / self.code_std
        inputs = torch.cat([code.expand(len(p), -1), (p / self.scales[1])[:, None]], 1)
        return inputs if self.bounds is None else inputs.clamp(*self.bounds)

    @torch.no_grad()
    def _force(self, ctx: EvalContext, part: PartData, depth: np.ndarray) -> np.ndarray:
        return self.net(self._inputs(ctx, part, depth))[:, 0].numpy() * self.scales[0]

    def diagnostics(self, ctx, part):
        return super().diagnostics(ctx, part) | {"blackbox_steps": float(self.best_step)}

    def predict(self, ctx, part):
        return [self._force(ctx, part, p.depth) for p in part.profiles]

    def static_force(self, ctx, part, depth_max, depth):
        return self._force(ctx, part, depth)


@METHODS.register
class MeanProfile(Method):
    """The mean force of all training samples in 0.1 mm depth bins, looked up at the test depth."""

    name = "mean"
    bin_mm = 0.1

    def fit(self, ctx):
        depth = np.concatenate([p.depth for part in ctx.train for p in part.profiles])
        force = np.concatenate([p.force for part in ctx.train for p in part.profiles])
        edges = np.arange(0.0, depth.max() + self.bin_mm, self.bin_mm)
        which = np.clip(np.digitize(depth, edges) - 1, 0, len(edges) - 2)
        counts = np.bincount(which, minlength=len(edges) - 1)
        sums = np.bincount(which, weights=force, minlength=len(edges) - 1)
        centres = 0.5 * (edges[:-1] + edges[1:])
        filled = counts > 0
        self.depth, self.force = centres[filled], sums[filled] / counts[filled]

    def predict(self, ctx, part):
        return [np.interp(p.depth, self.depth, self.force) for p in part.profiles]

    def static_force(self, ctx, part, depth_max, depth):
        return np.interp(depth, self.depth, self.force)

