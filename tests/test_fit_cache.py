"""Identification from the part's own scales, and the folder of stored fits (pipe.evaluation.fit_cache)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from test_baselines import DT, part

import pipe.model
from pipe.data.preprocess import Profile
from pipe.evaluation import compiled_objective, fit_cache, identification
from pipe.evaluation.context import EvalContext
from pipe.evaluation.fit_cache import fit_key
from pipe.evaluation.identification import identify
from pipe.model.pipe_model import PIPEModel
from pipe.plugins.encoder.pointnet import PointNetVAE
from pipe.plugins.head import gaussian
from pipe.plugins.head.gaussian import GaussianHead
from pipe.plugins.model.mds2 import MDS2

SETTINGS = {"restarts": 2, "max_evaluations": 60}


pytestmark = pytest.mark.usefixtures("compiled_simulator")   # conftest.py


def context(force_scale: float = 10.0, seed: int = 0, **settings) -> EvalContext:
    torch.manual_seed(0)
    model = PIPEModel(PointNetVAE(num_points=16), GaussianHead(32, 4), MDS2(), force_scale=force_scale,
                      depth_scale=6.0)
    return EvalContext(model, torch.zeros(2, 32), {"t": 0, "u": 1}, [], DT, seed=seed,
                       settings={"identification": SETTINGS | settings})


fitted_part = part("t", 2.0)


def forces(ctx: EvalContext, fitted) -> np.ndarray:
    """The identified model's force on the fitted part's trials."""
    batch = ctx.batch(fitted_part)
    with torch.no_grad():
        return fitted.model(torch.zeros(len(batch.part), 32), batch.depth, DT).numpy()


def test_a_fit_does_not_depend_on_the_training_parts_scales():
    """The parameters are scaled by the part's own recordings: models trained on data of other force scales
    identify the part alike (the learning curve's oracle is the same at every training-set size)."""
    small, large = context(force_scale=1.0), context(force_scale=100.0)
    a, b = identify(small, [fitted_part])[0], identify(large, [fitted_part])[0]
    assert a.evaluations == b.evaluations and a.loss == b.loss
    np.testing.assert_array_equal(forces(small, a), forces(large, b))
    peak = np.mean([np.abs(p.force).max() for p in fitted_part.profiles])    # the part's own, about 12 N
    torch.testing.assert_close(a.model.theta_scale, MDS2().parameter_scales(peak, 6.0).float())


def test_a_stored_fit_is_reused_by_a_later_run_without_fitting_again(tmp_path, monkeypatch):
    first = context(cache=str(tmp_path))
    fitted = identify(first, [fitted_part])[0]
    assert len(list(tmp_path.glob("t-*.pt"))) == 1

    def refuse(*args):
        raise AssertionError("fitted again")

    monkeypatch.setattr(identification, "fit_jobs", refuse)
    later = context(force_scale=50.0, cache=str(tmp_path))     # another run, trained on other data
    reused = identify(later, [fitted_part])[0]
    assert (reused.loss, reused.evaluations, reused.converged) == (fitted.loss, fitted.evaluations, fitted.converged)
    np.testing.assert_array_equal(forces(later, reused), forces(first, fitted))
    assert not any(p.requires_grad for p in reused.model.head.parameters())


def test_a_relative_cache_folder_is_taken_from_the_project_root(tmp_path, monkeypatch):
    monkeypatch.setenv("PROJECT_ROOT", str(tmp_path))
    monkeypatch.chdir("/")
    identify(context(cache="runs/fits"), [fitted_part])
    assert len(list((tmp_path / "runs" / "fits").glob("t-*.pt"))) == 1


@pytest.mark.parametrize("change", ["trial", "seed", "settings", "target", "head", "dynamics", "kernels", "libc",
                                    "scipy"])
def test_whatever_decides_a_fit_changes_its_key(change, monkeypatch):
    """Each thing that moves a fit moves its key: the machine's kernels and libraries too (another OpenBLAS
    kernel type alone moved conn's oracle by 0.71 points: docs/experiments.md, "OpenBLAS's kernels, MKL's, and
    96 starts")."""
    trials = [Profile(p.time, p.depth, p.force) for p in fitted_part.profiles]
    settings, seed, target, head, dynamics = dict(SETTINGS), 0, "force", GaussianHead(32, 4), MDS2()
    before = fit_key("t", trials, target, settings, seed, DT, head, dynamics)
    if change == "trial":
        trials[1] = Profile(trials[1].time, trials[1].depth, trials[1].force + 1e-9)
    elif change == "seed":
        seed = 1
    elif change == "settings":
        settings["ridge"] = 0.2
    elif change == "target":
        target = "force_clean"
    elif change in ("kernels", "libc", "scipy"):
        machine = fit_cache.arithmetic()
        assert change in machine
        other = {"kernels": machine["kernels"].replace("openblas ", "openblas not-"), "libc": "glibc 0.0",
                 "scipy": "0.0.0"}
        monkeypatch.setattr(fit_cache, "_arithmetic", lambda: {**machine, change: other[change]})
    elif change == "head":
        head = GaussianHead(32, 4, num_local_models=8)
    else:
        dynamics = MDS2(time_constant=0.03)
    assert fit_key("t", trials, target, settings, seed, DT, head, dynamics) != before


@pytest.mark.parametrize("module", ["ltv", "ltv_numba", "ltv_2x2", "losses", "pipe_model"])
def test_the_key_covers_the_source_of_every_simulator_kernel(module):
    """A fit depends on the compiled kernels' arithmetic too: the two-state kernels (ltv_2x2) were once left
    out of the key, so a changed kernel would have reused fits made by the old one."""
    source = (Path(pipe.model.__file__).parent / f"{module}.py").read_bytes()
    assert source in fit_cache._code(GaussianHead(32, 4), MDS2())


def test_the_key_covers_the_compiled_objective_and_the_head_plugins_kernels():
    """The compiled engine's fits depend on the core's objective and on kernels that live beside the head's
    module (plugins/head/gaussian_kernels.py), which no class of the model is defined in."""
    code = fit_cache._code(GaussianHead(32, 4), MDS2())
    for path in (Path(compiled_objective.__file__), Path(gaussian.__file__).with_name("gaussian_kernels.py")):
        assert path.read_bytes() in code


def test_the_neutral_profile_alone_is_shared_across_seeds_and_a_start_that_draws_is_not(tmp_path):
    """A fit from the neutral profile itself (neutral_jitter=0, one start) draws nothing and is stored once for
    every seed; the jittered neutral start (the default) and the random starts draw from the seed, so each seed
    stores and reads its own."""
    def fit(seed: int, **settings):
        return identify(context(seed=seed, cache=str(tmp_path), **settings), [fitted_part])[0]

    def values(fitted) -> torch.Tensor:
        return torch.cat([p.flatten() for p in fitted.model.head.parameters()])

    fit(0, restarts=1, neutral_jitter=0.0)
    fit(1, restarts=1, neutral_jitter=0.0)
    assert len(list(tmp_path.glob("*.pt"))) == 1
    jittered = [fit(seed, restarts=1) for seed in (0, 1)]
    assert len(list(tmp_path.glob("*.pt"))) == 3
    assert not torch.equal(values(jittered[0]), values(jittered[1]))
    assert torch.equal(values(fit(1, restarts=1)), values(jittered[1]))     # read back: the seed's own
    fit(0)
    fit(1)
    assert len(list(tmp_path.glob("*.pt"))) == 5


def test_a_damaged_stored_fit_is_fitted_again_and_replaced(tmp_path, caplog):
    fitted = identify(context(cache=str(tmp_path)), [fitted_part])[0]
    (stored,) = tmp_path.glob("t-*.pt")
    stored.write_bytes(b"not a fit")
    again = identify(context(cache=str(tmp_path)), [fitted_part])[0]
    assert "unreadable" in caplog.text and again.loss == fitted.loss
    assert torch.load(stored, weights_only=True)["loss"] == fitted.loss
    assert not list(tmp_path.glob("*.tmp"))


def test_a_fit_is_keyed_alike_in_every_process_on_the_same_kernels_and_apart_on_others():
    """The key holds the kernels the libraries chose when they loaded: another process on the same ones keys a
    fit alike (so later runs reuse it), one told to run other OpenBLAS kernels keys it apart."""
    import os
    import subprocess
    import sys

    script = ("import numpy as np; from pipe.data.preprocess import Profile; "
              "from pipe.evaluation.fit_cache import fit_key; from pipe.plugins.head.gaussian import GaussianHead; "
              "from pipe.plugins.model.mds2 import MDS2; t = np.linspace(0.0, 1.0, 5); "
              "print(fit_key('t', [Profile(t, t, t)], 'force', {}, 0, 0.01, GaussianHead(32, 4), MDS2()))")
    t = np.linspace(0.0, 1.0, 5)
    here = fit_key("t", [Profile(t, t, t)], "force", {}, 0, 0.01, GaussianHead(32, 4), MDS2())
    keys = [subprocess.run([sys.executable, "-c", script], env=os.environ | extra, capture_output=True, text=True,
                           timeout=120) for extra in ({}, {"OPENBLAS_CORETYPE": "Prescott"})]   # no host's own
    assert keys[0].stdout.strip() == here, keys[0].stderr[-2000:]
    assert keys[1].stdout.strip() not in ("", here), keys[1].stderr[-2000:]
