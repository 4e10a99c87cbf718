"""Each evaluated method on a tiny problem whose answer is known."""

from __future__ import annotations

import math
import os
from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import compose_config

from pipe.data.dataset import StaticCurve, load_dataset
from pipe.data.prepared import PartData, PreprocessSettings, prepare_part
from pipe.data.preprocess import PointCloud, Profile
from pipe.data.spec import load_spec
from pipe.errors import PipeError
from pipe.evaluation import identification
from pipe.evaluation.context import EvalContext
from pipe.evaluation.evaluate import evaluate_methods
from pipe.evaluation.identification import IdentificationSettings, identify, start_head
from pipe.evaluation.methods import METHODS, code_inputs, one_standard_error_choice, validation_errors, validation_nmse
from pipe.model.pipe_model import PIPEModel
from pipe.model.sections import SECTION_SIZE, SectionCode
from pipe.pipeline import build_components
from pipe.plugins.encoder.pointnet import PointNetVAE
from pipe.plugins.head.gaussian import GaussianHead
from pipe.plugins.head.seat_gaussian import SeatGaussianHead
from pipe.plugins.model.mds2 import MDS2
from pipe.synthetic import generate_dataset

DT = 0.01
TIME = np.arange(0, 2.0, DT)
DEPTH = 6.0 * np.clip(TIME / 1.4, 0, 1)


def part(name: str, gain: float, trials: int = 3, noise: float = 0.0) -> PartData:
    """A part whose force is simulated by mds2 itself with constant parameters and static gain `gain`, away
    from the neutral profile (which has a2 = 1 and mds2's 0.02 s time constant: a1 / a2 = 0.04); with
    `noise`, the measured force has Gaussian noise of that standard deviation [N] and the clean one not."""
    theta = torch.tensor([2e-3, 0.1, 2.0, 2.0 * gain]).expand(1, len(TIME), 4)
    force = MDS2()(theta, torch.tensor(DEPTH, dtype=torch.float32)[None], DT)[0].numpy()
    cloud = PointCloud(np.zeros((16, 3), np.float32), np.zeros(3), "volume")
    static = StaticCurve(DEPTH[:: 10].copy(), gain * DEPTH[:: 10])
    rng = np.random.default_rng(len(name))
    profiles = [Profile(TIME, DEPTH, force + noise * rng.standard_normal(len(TIME)), force) for _ in range(trials)]
    return PartData(name, cloud, profiles, [static] * trials)


IDENTIFICATION = {"restarts": 2, "max_evaluations": 1500}


pytestmark = pytest.mark.usefixtures("compiled_simulator")   # conftest.py


@pytest.fixture
def ctx():
    torch.manual_seed(0)
    train = [part("a", 1.0), part("b", 3.0)]
    test = part("t", 2.0)
    model = PIPEModel(PointNetVAE(num_points=16), GaussianHead(32, 4), MDS2(), force_scale=10.0, depth_scale=6.0)
    latents = torch.tensor([[0.0] * 32, [1.0] * 32, [0.45] * 32])
    context = EvalContext(model, latents, {"a": 0, "b": 1, "t": 2}, train, DT, seed=0,
                          settings={"identification": dict(IDENTIFICATION), "blackbox_steps": 1500})
    return context, test


def fit_of(measured: np.ndarray, predicted: np.ndarray) -> float:
    return 100 * (1 - np.sum((measured - predicted) ** 2) / np.sum((measured - measured.mean()) ** 2))


@pytest.mark.parametrize("ridge, engine", [(0.0, "torch"), (0.1, "torch"), (0.0, "compiled"), (0.1, "compiled")])
def test_oracle_recovers_the_simulating_parameters_from_scratch(ctx, ridge, engine):
    """On noise-free data simulated by the model itself (parameters away from the neutral profile): FIT(F)
    above 99 %, and the parameters that the force determines recovered, whatever PIPE's head has learnt:
    the static gain b0 / a2 at every depth within 5 %, with and without the ridge (the shallowest depth, where
    the force is smallest, is determined least: fits whose force differs by under a millinewton rms put it
    at 1.99 or 2.09), and the time constants a1 / a2 and a0 / a2 at the deepest point,
    where the stop excites the dynamics (along the slow ramp the force barely depends on them; mds2's
    parameters are known up to a common factor)."""
    context, test = ctx
    context.settings["identification"] |= {"ridge": ridge, "engine": engine}
    with torch.no_grad():                       # the oracle does not start from PIPE: spoil PIPE's head
        for p in context.model.head.parameters():
            p.add_(torch.randn_like(p))
    oracle = METHODS["oracle"]()
    forces = oracle.predict(context, test)
    assert min(fit_of(p.force, f) for p, f in zip(test.profiles, forces)) > 99.0
    static = oracle.static_force(context, test, 6.0, np.array([2.0, 4.0, 6.0]))
    np.testing.assert_allclose(static, [4.0, 8.0, 12.0], rtol=0.05)   # the static gain b0 / a2 = 2
    fitted = identify(context, [test])[0]
    assert fitted.converged and 20 < fitted.evaluations < IDENTIFICATION["max_evaluations"]   # it improved
    depth = torch.linspace(0.5, 6.0, 12)[None]
    a0, a1, a2, b0 = fitted.model.profile(context.latent(test)[None], torch.tensor([6.0]))(depth)[0].T
    np.testing.assert_allclose((b0 / a2).numpy(), 2.0, rtol=0.05)
    assert float(a1[-1] / a2[-1]) == pytest.approx(0.05, rel=0.05)     # s
    assert float(a0[-1] / a2[-1]) == pytest.approx(1e-3, rel=0.15)     # s^2


def test_oracle_with_the_seat_head_fits_on_torch_and_recovers_the_simulating_force():
    """The seat-frame head offers no compiled form: the compiled engine identifies it on torch, from scratch,
    to the force the model itself simulated (FIT(F) above 99 %, static gain within 5 %)."""
    torch.manual_seed(0)
    model = PIPEModel(PointNetVAE(num_points=16), SeatGaussianHead(32, 4), MDS2(), force_scale=10.0, depth_scale=6.0)
    test = part("t", 2.0)
    context = EvalContext(model, torch.zeros(1, 32), {"t": 0}, [part("a", 1.0)], DT, seed=0,
                          settings={"identification": IDENTIFICATION | {"engine": "compiled"}})
    oracle = METHODS["oracle"]()
    forces = oracle.predict(context, test)
    assert min(fit_of(p.force, f) for p, f in zip(test.profiles, forces)) > 99.0
    static = oracle.static_force(context, test, 6.0, np.array([2.0, 4.0, 6.0]))
    np.testing.assert_allclose(static, [4.0, 8.0, 12.0], rtol=0.05)


def test_oracle_clean_fits_the_noise_free_force_and_is_scored_against_it(ctx):
    context, _ = ctx
    noisy = part("n", 2.0, noise=1.0)
    context.index["n"] = 2
    results = evaluate_methods(context, [noisy], ["oracle", "oracle_clean"])
    assert results["oracle_clean"].domain["fit_F"] > 99.0          # the model structure is exact here
    assert results["oracle"].domain["fit_F"] < 98.0                # the noise caps what any fit scores
    clean_fit = identify(context, [noisy], "force_clean")[0]
    assert clean_fit.loss < 1e-3 < 0.8 < identify(context, [noisy])[0].loss   # noise variance 1 N^2


@pytest.mark.parametrize("engine", ["torch", "compiled"])
@pytest.mark.parametrize("loss, k", [("mse", 1.6), ("nmse", (4 + 1 / 4) / (4 + 1 / 16))])
def test_the_oracle_fits_every_trial_alike_under_nmse(ctx, engine, loss, k):
    """Regression (the oracle below PIPE on some pins): four trials of static gain 1 and one of 4, which no
    one profile fits. Each trial's force is its gain g times one response f, so the best profile predicts
    k f, with k the mean of the gains weighted by each trial's weight: 1.6 under the pooled MSE (the objective
    until 2026-11-30), (4 + 1/4) / (4 + 1/16) under each trial's error over its force's variance. A trial's
    FIT(F) is then 1 - r (k - g)^2 / g^2, with r = |f|^2 / |f - mean f|^2: -54 % and 53 % here."""
    context, _ = ctx
    four, one = part("m", 1.0, trials=4), part("m", 4.0, trials=1)
    mixed = PartData("m", four.cloud, four.profiles + one.profiles, four.static_curves + one.static_curves)
    context.index["m"] = 2
    context.settings["identification"] |= {"ridge": 0.0, "engine": engine, "loss": loss}
    f = four.profiles[0].force
    r = np.sum(f ** 2) / np.sum((f - f.mean()) ** 2)
    expected = 100 * np.mean([1 - r * (k - g) ** 2 / g ** 2 for g in (1.0, 1.0, 1.0, 1.0, 4.0)])
    assert evaluate_methods(context, [mixed], ["oracle"])["oracle"].domain["fit_F"] == pytest.approx(expected, abs=0.1)


def test_with_fits_has_the_oracle_score_given_fits_instead_of_its_own(ctx):
    """A fit of part a (static gain 1, simulated by mds2 itself: fitted to within 1 %) handed to the oracle of
    part t (gain 2, the same response doubled): a trial's FIT(F) is then 1 - |f|^2 / (4 |f - mean f|^2), for
    the oracle and for oracle_clean alike; the context's own cache is left as it was."""
    context, test = ctx
    a = context.train[0]
    fitted = identify(context, [a])[0]
    cached = dict(context.cache)
    f = a.profiles[0].force
    expected = 100 * (1 - np.sum(f ** 2) / (4 * np.sum((f - f.mean()) ** 2)))
    given = identification.with_fits(context, {"t": fitted})
    assert evaluate_methods(given, [test], ["oracle"])["oracle"].domain["fit_F"] == pytest.approx(expected, abs=0.5)
    clean = identification.with_fits(context, {"t": fitted}, "force_clean")
    scored = evaluate_methods(clean, [test], ["oracle_clean"])["oracle_clean"].domain["fit_F"]
    assert scored == pytest.approx(expected, abs=0.5)
    assert context.cache == cached and given.cache is not context.cache


def test_oracle_clean_is_left_out_without_a_noise_free_force(ctx):
    context, test = ctx
    test.profiles[:] = [Profile(p.time, p.depth, p.force) for p in test.profiles]
    context.settings["identification"]["max_evaluations"] = 2
    assert set(evaluate_methods(context, [test], ["pipe", "oracle", "oracle_clean"])) == {"pipe", "oracle"}


@pytest.mark.parametrize("engine", ["torch", "compiled"])
def test_identification_stops_at_max_evaluations_and_reports_it(ctx, engine):
    context, test = ctx
    context.settings["identification"] |= {"max_evaluations": 7, "restarts": 1, "engine": engine,
                                           "via_mse": False}
    fitted = identify(context, [test])[0]
    assert fitted.evaluations == 7 and not fitted.converged
    assert fitted.loss == pytest.approx(
        float(((fitted.model(context.latent(test)[None].expand(3, -1), context.batch(test).depth, DT)
                - context.batch(test).force) ** 2).mean()), rel=1e-4)      # the kept start's lowest loss


def test_unknown_identification_option_is_refused(ctx):
    context, test = ctx
    context.settings["identification"]["steps"] = 10
    with pytest.raises(PipeError, match=r"unknown evaluation.identification option\(s\) \['steps'\]"):
        identify(context, [test])


def test_an_unknown_identification_loss_is_refused(ctx):
    context, test = ctx
    context.settings["identification"]["loss"] = "mae"
    with pytest.raises(PipeError, match=r"loss 'mae'; known: \['mse', 'nmse'\]"):
        identify(context, [test])


def test_via_mse_continues_each_start_from_its_mse_fit_and_keeps_the_lowest_objective(ctx):
    """With via_mse each start has a second job: fitted on mse, then continued on nmse from there, the same
    fit to the bit as doing the two by hand, with both fits' evaluations; the part keeps the job of lowest
    objective among all of them."""
    context, test = ctx
    settings = identification.IdentificationSettings(restarts=2, max_evaluations=40)
    trials = [Profile(p.time, p.depth, p.force) for p in test.profiles]
    jobs = identification.part_jobs(context, test.name, trials, settings)
    assert [job.first for job in jobs] == [None, "mse", None, "mse"]
    assert len(identification.part_jobs(context, test.name, trials, replace(settings, via_mse=False))) == 2
    assert len(identification.part_jobs(context, test.name, trials, replace(settings, loss="mse"))) == 2
    state, fit = identification.fit_job(jobs[3])
    by_hand = identification.part_jobs(context, test.name, trials, settings)[3]
    warm = identification.fit_start(by_hand.model, by_hand.head, by_hand.batch, replace(settings, loss="mse"))
    by_hand.head.train().requires_grad_(True)
    then = identification.fit_start(by_hand.model, by_hand.head, by_hand.batch, settings)
    assert fit == then._replace(evaluations=warm.evaluations + then.evaluations)
    assert all(torch.equal(state[k], v) for k, v in by_hand.head.state_dict().items())
    fits = [identification.fit_job(job)[1] for job in identification.part_jobs(context, test.name, trials, settings)]
    context.settings["identification"] |= {"restarts": 2, "max_evaluations": 40}
    kept = identify(context, [test])[0]
    assert kept.loss == min(fits, key=lambda f: f.objective).loss


def test_a_constant_force_trial_is_refused_under_nmse_naming_its_part(ctx):
    context, test = ctx
    test.profiles[1] = Profile(TIME, DEPTH, np.full(len(TIME), 2.0))
    with pytest.raises(PipeError, match="a trial of t has a constant force: use evaluation.identification.loss=mse"):
        identify(context, [test])
    context.settings["identification"] |= {"loss": "mse", "max_evaluations": 5, "restarts": 1}
    assert identify(context, [test])[0].evaluations == 5


def test_an_unknown_identification_engine_is_refused(ctx):
    context, test = ctx
    context.settings["identification"]["engine"] = "jax"
    with pytest.raises(PipeError, match=r"engine 'jax'; known: \['torch', 'compiled'\]"):
        identify(context, [test])


def test_the_compiled_engine_fits_on_torch_where_the_head_offers_no_compiled_form(ctx, monkeypatch):
    """A head without `compiled` (a plugin that does not write one) is fitted by the torch engine, the same
    fit to the bit as engine=torch."""
    context, test = ctx
    context.settings["identification"] |= {"max_evaluations": 30, "restarts": 1, "engine": "torch", "via_mse": False}
    on_torch = identify(context, [test])[0]
    context.cache.clear()
    context.settings["identification"]["engine"] = "compiled"
    monkeypatch.setattr(identification.CompiledObjective, "of", lambda *args: None)
    fallback = identify(context, [test])[0]
    assert (fallback.loss, fallback.evaluations) == (on_torch.loss, on_torch.evaluations)


def test_the_compiled_engine_lowers_the_objective_as_the_torch_engine_does(ctx):
    """Both engines fit the same objective: on a part whose force the model can produce, each ends near
    zero error from the neutral start."""
    context, test = ctx
    context.settings["identification"] |= {"restarts": 1, "ridge": 0.0}
    fits = {}
    for engine in ("torch", "compiled"):
        context.cache.clear()
        context.settings["identification"]["engine"] = engine
        fits[engine] = identify(context, [test])[0]
    power = float(np.mean([np.mean(p.force ** 2) for p in test.profiles]))
    assert all(fit.converged and fit.loss < 1e-4 * power for fit in fits.values())


def test_a_head_without_free_profiles_is_refused_clearly(ctx):
    from pipe.model.interfaces import ParameterHead

    class Fixed(ParameterHead):
        def forward(self, z, depth_max):
            return lambda depth: torch.ones(*depth.shape, self.num_parameters)

    context, test = ctx
    context.model = context.model.with_head(Fixed(32, 4))
    with pytest.raises(PipeError, match="the head Fixed offers no free profiles .* leave them out of evaluation"):
        identify(context, [test])


@pytest.mark.parametrize("engine", ["torch", "compiled"])
def test_starts_fitted_in_worker_processes_equal_those_fitted_here(ctx, engine):
    """`workers`: the starts of several parts fitted in two started processes give every part the fit, the
    loss and the evaluation count it gets here (each start runs on one thread wherever it runs)."""
    context, test = ctx
    context.settings["identification"] |= {"max_evaluations": 60, "engine": engine}
    parts = [*context.train, test]
    here = identify(context, parts)
    context.cache.clear()
    context.settings["identification"]["workers"] = 2
    there = identify(context, parts)
    for a, b in zip(here, there):
        assert (a.loss, a.evaluations, a.converged) == (b.loss, b.evaluations, b.converged)
        for x, y in zip(a.model.head.parameters(), b.model.head.parameters()):
            torch.testing.assert_close(x, y, rtol=0, atol=0)
        torch.testing.assert_close(a.model.theta_scale, b.model.theta_scale, rtol=0, atol=0)


def test_a_start_fits_alike_whatever_blas_threads_the_launching_process_has(ctx):
    """scipy's L-BFGS-B rounds differently on two OpenBLAS threads than on one: a start fitted in the launching
    process, where OpenBLAS takes every core by default, ended elsewhere than the same start in a worker
    process, which joblib limits to its share of the cores (on dsub26 from the embedded dataset: 84.2857 %
    against 84.2854). The fit runs on one BLAS thread wherever it runs."""
    from threadpoolctl import threadpool_limits

    context, test = ctx
    settings = identification.IdentificationSettings(restarts=2, via_mse=False)
    trials = [Profile(p.time, p.depth, p.force) for p in test.profiles]
    fits = {}
    for threads in (1, 2):
        with threadpool_limits(limits=threads, user_api="blas"):
            fits[threads] = identification.fit_jobs(identification.part_jobs(context, test.name, trials, settings), 1)
    for (state_one, fit_one), (state_two, fit_two) in zip(fits[1], fits[2]):
        assert fit_one == fit_two
        for name in state_one:
            torch.testing.assert_close(state_one[name], state_two[name], rtol=0, atol=0)


def test_the_blas_libraries_run_on_the_threads_set_and_get_theirs_back():
    from threadpoolctl import threadpool_info, threadpool_limits

    from pipe.threads import threads_set_to

    def blas_threads() -> set[int]:
        return {lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}

    with threadpool_limits(limits=2, user_api="blas"):
        with threads_set_to(1):
            assert blas_threads() == {1}
        assert blas_threads() == {2}


class KillsItsWorker:
    """Unpickled in a worker process, it ends that process at once, as an out-of-memory kill would."""

    def __reduce__(self):
        return (os._exit, (3,))


@pytest.mark.timeout(300)
def test_a_worker_process_that_dies_fails_the_fit_clearly_and_the_next_fit_works(ctx):
    """A killed worker used to leave the evaluation waiting for ever (multiprocessing.Pool loses its task)."""
    context, test = ctx
    settings = identification.IdentificationSettings(restarts=2, max_evaluations=10, via_mse=False)
    trials = [Profile(p.time, p.depth, p.force) for p in test.profiles]
    jobs = identification.part_jobs(context, test.name, trials, settings)
    doomed = [jobs[0], jobs[1]._replace(head=KillsItsWorker())]
    with pytest.raises(PipeError, match="ended without its result.*workers=1"):
        identification.fit_jobs(doomed, 2)
    fits = identification.fit_jobs(identification.part_jobs(context, test.name, trials, settings), 2)
    assert [fit.evaluations for _, fit in fits] == [10, 10]


def test_a_daemon_process_fits_its_starts_itself(ctx, monkeypatch):
    """Python forbids a daemon process to start processes (AssertionError "daemonic processes are not allowed
    to have children"): there the starts are fitted in the process itself, whatever `workers` says."""
    context, test = ctx
    context.settings["identification"] |= {"max_evaluations": 20, "workers": 2, "via_mse": False}

    class Daemon:
        daemon = True

    def no_processes(*args, **kwargs):
        raise AssertionError("a daemon started processes")

    monkeypatch.setattr(identification.multiprocessing, "current_process", lambda: Daemon())
    monkeypatch.setattr(identification, "Parallel", no_processes)
    assert identify(context, [*context.train, test])[0].evaluations == 20


def test_identifying_parts_together_equals_one_by_one(ctx):
    """A part's random starts do not depend on the other parts: fitting parts together gives each the fit
    it gets alone. Trials of different lengths are padded to one batch and masked."""
    context, test = ctx
    context.settings["identification"]["max_evaluations"] = 40
    short = part("s", 1.5, trials=2)
    short.profiles[:] = [Profile(TIME[:120], DEPTH[:120], p.force[:120]) for p in short.profiles]
    context.index["s"] = 2
    parts = [*context.train, test, short]
    together = identify(context, parts)
    alone = []
    for p in parts:
        context.cache.clear()
        alone.append(identify(context, [p])[0])
    for p, a, b in zip(parts, together, alone):
        batch = context.batch(p)
        z = context.latent(p).expand(len(batch.part), -1)
        with torch.no_grad():
            force_together, force_alone = a.model(z, batch.depth, DT), b.model(z, batch.depth, DT)
        assert (force_together - force_alone).abs().max() <= 1e-3 * force_alone.abs().max()   # float32 sums
        assert a.evaluations == b.evaluations and a.loss == pytest.approx(b.loss, rel=1e-3)      # of other lengths


def test_each_start_draws_its_own_random_profile():
    """Start 0 is the neutral profile, moved by `jitter` times a standard normal draw; a random start and the
    jitter's draw depend on the seed, the start and the part's name alone (torch's generator keeps only 32
    bits of a seed: seeds that differ above them must still differ)."""
    head = GaussianHead(32, 4)

    def values(name, seed, start, jitter=0.0):
        return torch.cat([p.detach().ravel() for p in start_head(head, name, seed, start, jitter).parameters()])

    assert torch.equal(values("a", 0, 0), torch.zeros_like(values("a", 0, 0)))
    assert torch.equal(values("a", 0, 1), values("a", 0, 1))
    for other in (values("a", 0, 2), values("a", 1, 1), values("b", 0, 1)):
        assert not torch.allclose(values("a", 0, 1), other)
    jittered = values("a", 0, 0, 1e-6)
    assert torch.equal(values("a", 0, 0, 1e-6), jittered)
    assert 0.5 < float(jittered.std() / 1e-6) < 1.5 and jittered.abs().max() < 1e-5     # 1e-6 x N(0, 1)
    for other in (values("a", 1, 0, 1e-6), values("b", 0, 0, 1e-6), values("a", 2**40, 0, 1e-6)):
        assert not torch.equal(jittered, other)
    assert torch.equal(values("a", 0, 1, 1e-6), values("a", 0, 1))     # a random start takes no jitter


def test_a_negative_non_finite_or_non_numeric_jitter_is_refused_naming_the_option():
    for bad in (-1e-6, "small", True, float("nan"), float("inf")):
        message = "evaluation.identification.neutral_jitter must be a finite number, 0 or more"
        with pytest.raises(PipeError, match=message):
            IdentificationSettings.from_config({"neutral_jitter": bad})


def test_the_ridge_pulls_the_identified_profiles_towards_the_neutral_one(ctx):
    """The ridge trades a little of the fit for profiles nearer the neutral one (unconstrained values 0). The
    force is noisy: on exact data both fits reach the objective's floor (1e-6 P), where their order is rounding."""
    context, _ = ctx
    far = part("f", 8.0, noise=0.3)            # a static gain of 8: b0 far above its scale
    context.index["f"] = 2
    fits = {}
    for ridge in (0.0, 1.0):
        context.cache.clear()
        context.settings["identification"] |= {"ridge": ridge, "restarts": 1, "max_evaluations": 300}
        fitted = identify(context, [far])[0]
        fits[ridge] = (fitted.loss, torch.cat([p.ravel() for p in fitted.model.head.parameters()]).norm())
    assert fits[0.0][0] < fits[1.0][0] and fits[1.0][1] < fits[0.0][1]


def test_nearest_uses_the_closest_training_part(ctx):
    context, test = ctx
    got = METHODS["nearest"]().predict(context, test)[0]      # latent 0.45 is nearer to a (0) than to b (1)
    batch = context.batch(test)
    with torch.no_grad():
        expected = context.model(context.latents[[0]], batch.depth[:1], DT)[0].numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-6)


def test_gpr_reproduces_a_training_part_at_its_own_latent(ctx):
    context, _ = ctx
    gpr = METHODS["gpr"]()
    gpr.fit(context)
    train_a = context.train[0]
    identified = identify(context, [train_a], restarts=1)[0].model
    depth = np.array([1.5, 3.0, 4.5, 6.0])
    theta_gpr = gpr._theta(context, train_a, depth, 6.0)
    theta_id = identified.profile(context.latent(train_a)[None], torch.tensor([6.0]))(
        torch.tensor(depth, dtype=torch.float32)[None])[0]
    np.testing.assert_allclose(theta_gpr.numpy(), theta_id.numpy(), rtol=0.05)


@pytest.fixture
def with_validation(ctx, monkeypatch):
    """The context with a validation part, and a record of every validation score a baseline computes."""
    from pipe.evaluation import methods

    context, test = ctx
    context.val = [part("v", 2.5)]
    context.index["v"] = 3
    context.latents = torch.cat([context.latents, torch.full((1, 32), 0.7)])
    scores = []
    original = methods.validation_nmse
    monkeypatch.setattr(methods, "validation_nmse", lambda m, c: scores.append(original(m, c)) or scores[-1])
    return context, scores, original


def test_gpr_takes_the_kernel_with_the_lowest_validation_error(with_validation):
    context, scores, validation_nmse = with_validation
    gpr = METHODS["gpr"]()
    gpr.fit(context)
    assert len(scores) == 1 + len(gpr.LENGTH_SCALES)          # the likelihood optimum and the fixed grid
    assert validation_nmse(gpr, context) == pytest.approx(min(scores))
    if int(np.argmin(scores)) > 0:
        assert gpr.length_scale == pytest.approx(gpr.LENGTH_SCALES[int(np.argmin(scores)) - 1])


def test_gpr_without_validation_parts_takes_the_kernel_of_the_lowest_leave_one_part_out_error(ctx, monkeypatch):
    """Each candidate kernel is fitted to the training parts but one and scored on that one, for every part;
    the kernel of the lowest mean error over those folds is kept, fitted to all of them."""
    from pipe.evaluation import methods

    context, _ = ctx
    context.train.append(part("c", 5.0))
    context.index["c"] = 3
    context.latents = torch.cat([context.latents, torch.full((1, 32), 2.0)])
    folds = []
    original = methods.validation_errors
    monkeypatch.setattr(methods, "validation_errors",
                        lambda m, c: folds.append(([p.name for p in c.val], len(m.gp.X_train_), original(m, c)))
                        or folds[-1][2])
    gpr = METHODS["gpr"]()
    gpr.fit(context)
    kernels = 1 + len(gpr.LENGTH_SCALES)
    assert [names for names, _, _ in folds] == [["a"], ["b"], ["c"]] * kernels   # each part left out once
    assert all(fitted_to == 2 for _, fitted_to, _ in folds)                     # fitted to the two others
    scores = [np.mean(np.concatenate([e for _, _, e in folds[3 * k: 3 * k + 3]])) for k in range(kernels)]
    assert len(gpr.gp.X_train_) == 3                                             # kept: fitted to all three
    best = int(np.argmin(scores))
    if best > 0:
        assert gpr.length_scale == pytest.approx(gpr.LENGTH_SCALES[best - 1])
    assert gpr.gp.kernel == gpr.kernels(32)[best]


def test_gpr_with_two_training_parts_and_no_validation_part_takes_the_likelihood_optimum(ctx):
    context, _ = ctx
    gpr = METHODS["gpr"]()
    gpr.fit(context)
    assert gpr.gp.kernel == gpr.kernels(32)[0]


def test_gpr_fits_a_kernel_that_ends_at_a_bound_without_sklearns_warning():
    """Outputs that do not vary drive the amplitude to its lower bound: sklearn warns (a dozen such warnings
    filled the main run's output); the regression gpr compares on held-out parts does not."""
    import warnings

    from sklearn.exceptions import ConvergenceWarning
    from sklearn.gaussian_process import GaussianProcessRegressor

    inputs, outputs = np.linspace(0.0, 1.0, 8)[:, None], np.ones((8, 2))
    kernel = METHODS["gpr"].kernels(1)[0]
    with pytest.warns(ConvergenceWarning):          # the reference: sklearn alone warns on these data
        GaussianProcessRegressor(kernel, normalize_y=True, random_state=0).fit(inputs, outputs)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)
        fitted = METHODS["gpr"].regression(kernel, 0, inputs, outputs)
    assert fitted.predict(inputs) == pytest.approx(outputs)


def test_blackbox_keeps_the_weights_of_its_lowest_validation_error(with_validation):
    context, scores, validation_nmse = with_validation
    context.settings["blackbox_steps"] = 450
    blackbox = METHODS["blackbox"]()
    blackbox.fit(context)
    assert len(scores) == 5                                    # steps 100, 200, 300, 400 and the last, 450
    assert blackbox.best_step == [100, 200, 300, 400, 450][int(np.argmin(scores))]
    assert validation_nmse(blackbox, context) == pytest.approx(min(scores))


def test_blackbox_learns_a_static_map(ctx):
    context, test = ctx
    blackbox = METHODS["blackbox"]()
    blackbox.fit(context)
    a = context.train[0]
    static = blackbox.static_force(context, a, 6.0, np.array([2.0, 4.0, 6.0]))
    np.testing.assert_allclose(static, [2.0, 4.0, 6.0], atol=0.6)     # part a: F = 1 N/mm * p (static)


def test_blackbox_clip_holds_its_inputs_to_the_training_range_and_changes_nothing_inside_it(ctx):
    """The training codes are all 0 and all 1, the depths 0 to 6 mm. A test part whose code lies at 5 is
    predicted, clipped, as the training part whose code is all 1 (the same depths), and a depth of 12 mm as 6
    mm; unclipped the network extrapolates to other values. The network is the same either way (no
    validation parts: the same steps from the same seed), so the training parts' forces are equal to the bit."""
    context, test = ctx
    context.settings["blackbox_steps"] = 200
    context.latents[context.index["t"]] = 5.0
    plain = METHODS["blackbox"]()
    plain.fit(context)
    context.settings["blackbox_clip"] = True
    clipped = METHODS["blackbox"]()
    clipped.fit(context)
    a, b = context.train
    for part in (a, b):
        np.testing.assert_array_equal(clipped.predict(context, part)[0], plain.predict(context, part)[0])
    np.testing.assert_array_equal(clipped.predict(context, test)[0], plain.predict(context, b)[0])
    assert np.abs(plain.predict(context, test)[0] - plain.predict(context, b)[0]).max() > 0.1
    deep = clipped.static_force(context, a, 6.0, np.array([6.0, 12.0]))
    assert deep[1] == pytest.approx(deep[0], rel=1e-6)       # the same input (float32 rounding of the batch)
    assert plain.static_force(context, a, 6.0, np.array([12.0]))[0] != deep[1]


def test_blackbox_does_not_depend_on_what_the_process_drew_before(ctx):
    """Its initial weights come from the run's seed: an evaluation after a training in the same process
    and one in a process of its own (phase=evaluate) fit the same network; another seed, another network."""
    context, test = ctx
    context.settings["blackbox_steps"] = 30
    fitted = []
    for drawn_before in (0, 1):
        torch.manual_seed(drawn_before)
        torch.rand(1000)
        blackbox = METHODS["blackbox"]()
        blackbox.fit(context)
        fitted.append(blackbox.predict(context, test)[0])
    np.testing.assert_array_equal(fitted[0], fitted[1])
    context.seed = 1
    blackbox = METHODS["blackbox"]()
    blackbox.fit(context)
    assert not np.array_equal(blackbox.predict(context, test)[0], fitted[0])


def add_sections(context: EvalContext) -> None:
    """Give the context a model that appends the cross-section to the code, and a validation part. The
    encoder's code places the test part (0.45) nearest to a (0) and the validation part (0.7) nearest to b (1),
    their cross-sections the other way round."""
    context.model = PIPEModel(context.model.encoder, GaussianHead(32 + SECTION_SIZE, 4), MDS2(), force_scale=10.0,
                              depth_scale=6.0, sections=SectionCode())
    context.val = [part("v", 2.5)]
    context.index["v"] = 3
    code = torch.tensor([[0.0], [1.0], [0.45], [0.7]]).expand(4, 32)
    sections = torch.tensor([[1.0], [0.0], [0.3], [0.9]]).expand(4, SECTION_SIZE)
    context.latents = torch.cat([code, sections], 1)
    context.settings["blackbox_steps"] = 200


@pytest.fixture
def with_sections(ctx):
    add_sections(ctx[0])
    return ctx


def test_code_inputs_split_the_code_where_the_cross_section_begins(ctx):
    context, _ = ctx
    assert code_inputs(context) == {"code": slice(None)}
    add_sections(context)
    assert code_inputs(context) == {"code+sections": slice(None), "code": slice(0, 32), "sections": slice(32, None)}


def test_one_standard_error_choice_keeps_the_first_unless_another_is_clearly_better():
    """By hand, against [0.4, 0.5, 0.6] (mean 0.5): [0.2, 0.3, 0.4] is better on every trial (difference 0.2,
    standard error 0); [0.1, 0.6, 0.5] has a lower mean, 0.4, but its differences 0.3, -0.1, 0.1 have mean 0.1
    and standard error 0.2 / sqrt(3) = 0.115; [0.3, 0.45, 0.5] (mean 0.417; differences 0.1, 0.05, 0.1: mean
    0.083, standard error 0.017) is clearly better, so it is kept before the lower but unclear 0.4."""
    default = np.array([0.4, 0.5, 0.6])
    clear, unclear = np.array([0.3, 0.45, 0.5]), np.array([0.1, 0.6, 0.5])
    assert one_standard_error_choice([default, np.array([0.2, 0.3, 0.4])]) == 1
    assert one_standard_error_choice([default, unclear]) == 0
    assert one_standard_error_choice([default, unclear, clear]) == 2
    assert one_standard_error_choice([default, clear, np.array([0.2, 0.3, 0.4])]) == 2   # both clear: the lower
    assert one_standard_error_choice([default, default + 0.1]) == 0
    assert one_standard_error_choice([default]) == 0
    assert one_standard_error_choice([np.array([0.5]), np.array([0.1])]) == 0    # one trial: no error to judge by


def test_a_lower_but_unclear_validation_error_leaves_the_head_s_input(with_sections, monkeypatch):
    """The code alone has the lowest mean validation error (0.4 against 0.5), but not by more than its
    standard error (the hand-computed case above), so nearest keeps reading what the head reads; the plain
    minimum would take the code."""
    from pipe.evaluation import methods

    context, test = with_sections
    errors = {"code+sections": [0.4, 0.5, 0.6], "code": [0.1, 0.6, 0.5], "sections": [0.5, 0.6, 0.7]}
    monkeypatch.setattr(methods, "validation_errors", lambda method, ctx: np.array(errors[method.inputs]))
    nearest = METHODS["nearest"]()
    nearest.fit(context)
    assert nearest.inputs == "code+sections"
    errors["code"] = [0.3, 0.45, 0.5]                            # clearly better now
    nearest.fit(context)
    assert nearest.inputs == "code"


@pytest.mark.parametrize("noise", [0.0, 0.3])
@pytest.mark.parametrize("name", ["nearest", "gpr", "blackbox"])
def test_baselines_read_what_the_head_reads_unless_another_input_is_clearly_better(with_sections, name, noise):
    """Fitted on each input alone (the reference), then left to choose: of the inputs that beat the head's
    input (the first) by more than the paired differences' standard error over the validation trials, it
    reads the one of the lowest mean error, else the head's input, and says so in its diagnostics. With noise the
    validation part's trials differ, so the standard error is not zero."""
    context, test = with_sections
    context.val = [part("v", 2.5, trials=4, noise=noise)]
    errors = {}
    for inputs in code_inputs(context):
        alone = METHODS[name]()
        alone.inputs = inputs
        alone.fit_inputs(context)
        errors[inputs] = validation_errors(alone, context)
    first = "code+sections"

    def clearly_better(inputs: str) -> bool:
        difference = errors[first] - errors[inputs]
        return difference.mean() > difference.std(ddof=1) / math.sqrt(len(difference))

    better = [inputs for inputs in errors if inputs != first and clearly_better(inputs)]
    chosen = METHODS[name]()
    chosen.fit(context)
    assert chosen.inputs == (min(better, key=lambda inputs: errors[inputs].mean()) if better else first)
    assert validation_nmse(chosen, context) == pytest.approx(errors[chosen.inputs].mean())
    diagnostics = chosen.diagnostics(context, test)
    assert diagnostics[f"{name}_reads_code"] == float(chosen.inputs != "sections")
    assert diagnostics[f"{name}_reads_sections"] == float(chosen.inputs != "code")


@pytest.mark.parametrize("inputs, nearest", [("code", 0), ("sections", 1), ("code+sections", 1)])
def test_nearest_measures_distance_on_what_it_reads_and_predicts_from_the_whole_code(with_sections, inputs,
                                                                                     nearest):
    """Test part: code 0.45, cross-section 0.3; a: 0 and 1; b: 1 and 0 (32 and 25 values each), so b is
    nearer by the whole code (squared distances 6.5 + 12.25 against 9.7 + 2.25)."""
    context, test = with_sections
    method = METHODS["nearest"]()
    method.inputs = inputs
    batch = context.batch(test)
    with torch.no_grad():
        expected = context.model(context.latents[[nearest]], batch.depth[:1], DT)[0].numpy()
    np.testing.assert_allclose(method.predict(context, test)[0], expected, rtol=1e-6)


def test_without_validation_parts_the_baselines_read_what_the_head_reads(with_sections):
    context, test = with_sections
    context.val = []
    for name in ("nearest", "gpr", "blackbox"):
        method = METHODS[name]()
        method.fit(context)
        assert method.inputs == "code+sections"


def test_baselines_keep_the_model_s_standardisation_of_the_cross_section(with_sections):
    """The model standardised the cross-section over the training parts, with a floor on a column's spread. A
    column the training parts do not vary (0 in a and b) but the test part does (8) reaches the blackbox and
    gpr as 8, not as 8 / 1e-6, and the blackbox's force stays within reach of the training forces; they
    standardise the encoder's code alone (0 and 1 in a and b, 0.45 in the test part)."""
    context, test = with_sections
    context.latents[:, 32] = torch.tensor([0.0, 0.0, 8.0, 0.0])
    sections = [8.0] + [0.3] * (SECTION_SIZE - 1)
    blackbox = METHODS["blackbox"]()
    blackbox.inputs = "code+sections"
    blackbox.fit_inputs(context)
    read = blackbox._inputs(context, test, np.array([3.0]))[0, :-1].numpy()
    np.testing.assert_allclose(read, [-0.05 / math.sqrt(0.5)] * 32 + sections, rtol=1e-4)   # std with ddof 1
    assert np.abs(blackbox.predict(context, test)[0]).max() < 1e3       # the training forces reach 18 N
    gpr = METHODS["gpr"]()
    gpr.inputs = "code+sections"
    gpr.fit_inputs(context)
    read = (gpr.code(context, test).numpy() - gpr.mean) / gpr.std
    np.testing.assert_allclose(read, [-0.1] * 32 + sections, rtol=1e-4)                      # numpy's std, ddof 0


def test_mean_is_the_average_training_force_over_depth(ctx):
    context, test = ctx
    mean = METHODS["mean"]()
    mean.fit(context)
    expected = 0.5 * (context.train[0].profiles[0].force + context.train[1].profiles[0].force)
    moving = DEPTH < 5.9                   # the hold at 6 mm collects every sample of both parts' holds
    got = mean.predict(context, test)[0]
    assert np.abs(got - expected)[moving].max() < 0.15 * expected.max()


def test_evaluation_scores_every_method_and_the_static_curve(ctx):
    context, test = ctx
    context.settings["identification"]["max_evaluations"] = 50
    context.settings["blackbox_steps"] = 50
    results = evaluate_methods(context, [test], list(METHODS))
    assert set(results) == set(METHODS)
    for result in results.values():
        assert {"fit_F", "fit_dF", "rms", "rms_rel", "static_rms"} <= set(result.domain)
    assert results["oracle"].domain["rms"] < results["mean"].domain["rms"]


def test_unknown_baseline_is_refused(ctx):
    context, test = ctx
    with pytest.raises(PipeError, match="unknown method"):
        evaluate_methods(context, [test], ["pipe", "kriging"])


def test_reconstruction_metrics_of_a_perfect_and_a_shifted_reconstruction():
    from pipe.evaluation.evaluate import reconstruction_metrics

    class Echo(torch.nn.Module):
        """Encodes a cloud as itself and decodes it shifted by `shift` mm along x."""

        def __init__(self, shift: float) -> None:
            super().__init__()
            self.shift = shift

        def encode(self, clouds):
            return clouds, clouds

        def decode(self, z):
            return z + torch.tensor([self.shift, 0.0, 0.0])

    points = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0]], dtype=np.float32)
    parts = [PartData("p", PointCloud(points, np.zeros(3), "volume"), [], [])]
    assert reconstruction_metrics(Echo(0.0), parts)["p"] == {"chamfer_mm2": 0.0, "nn_distance_mm": 0.0,
                                                             "nn_distance_unit_sphere": 0.0}
    shifted = reconstruction_metrics(Echo(1.0), parts)["p"]
    assert shifted["nn_distance_mm"] == pytest.approx(1.0)     # every nearest neighbour 1 mm away
    assert shifted["chamfer_mm2"] == pytest.approx(6.0)        # 3 points x 1 mm^2, both ways
    # centroid (10/3, 10/3, 0); the farthest point (10, 0, 0) lies sqrt(20^2 + 10^2) / 3 mm from it
    assert shifted["nn_distance_unit_sphere"] == pytest.approx(3 / math.sqrt(500.0))


@pytest.mark.parametrize("engine", [pytest.param("torch", marks=pytest.mark.slow), "compiled"])
def test_default_settings_let_a_slow_pin_fit_converge(tmp_path, engine):
    """Regression: under the former cap of 3000 evaluations the second start of seed 1 on the pin dowel6 (the
    oracle's kept start there) stopped unconverged on the torch engine; it meets the stopping rule after
    about 3400. With the default settings the tolerance, not the cap, ends it, on either engine and under
    either force error (the pooled MSE of that regression and the default nmse)."""
    cfg = compose_config(["domain=pins", "seed=1"])
    root = generate_dataset(tmp_path / "data", seed=0, parts=["dowel6"])
    dowel = prepare_part(load_dataset(root).parts["dowel6"], load_spec(root), PreprocessSettings.from_config(cfg.data))
    _, head, dynamics = build_components(cfg)
    context = EvalContext(PIPEModel(None, head, dynamics), torch.zeros(1, head.latent_dim), {}, [],
                          1.0 / cfg.data.rate_hz, cfg.seed, dict(cfg.evaluation))
    settings = replace(identification.IdentificationSettings.from_config(cfg.evaluation.identification),
                       engine=engine)
    trials = [Profile(p.time, p.depth, p.force) for p in dowel.profiles]
    for loss in ("mse", "nmse"):
        job = identification.part_jobs(context, "dowel6", trials, replace(settings, restarts=2, via_mse=False))[1]
        fit = identification.fit_start(job.model, job.head, job.batch, replace(settings, loss=loss))
        assert fit.converged and fit.evaluations < settings.max_evaluations, (loss, fit)
