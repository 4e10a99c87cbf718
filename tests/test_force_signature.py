"""Stage 1's force term (stages.vae.force_weight): the force signature against hand-computed bins, its
standardisation, the stage's loss against the term computed apart, and train.py with the term."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import TINY_DOMAIN, smoke_config
from test_training import run_train

from pipe.data.batches import cloud_loader
from pipe.data.prepared import PartData
from pipe.data.preprocess import PointCloud, Profile
from pipe.pipeline import run_domain
from pipe.training.force_signature import force_signature, standardised
from pipe.training.stages import VAEStage


def part(*trials) -> PartData:
    return PartData("p", None, [Profile(np.arange(len(d)) * 0.01, np.array(d, float), np.array(f, float))
                                for d, f in trials], [])


def test_force_signature_averages_the_trials_force_in_bins_of_depth_and_fills_empty_bins():
    # deepest |depth| 10 mm in both trials; fractions 0 .2 .4 | .6 .8 1 and 0 | .5 1 (the deepest in the last
    # bin, the depth's sign ignored): bin 0 holds 0 1 2 1, bin 1 holds 3 4 5 1 7
    two = part(([0, 2, 4, 6, 8, 10], [0, 1, 2, 3, 4, 5]), ([0, -5, -10], [1, 1, 7]))
    np.testing.assert_allclose(force_signature(two, 2), [1.0, 4.0])
    # samples at 0 and 10 mm only: bins 1 and 2 of 4 take the line between the centres of bins 0 and 3
    np.testing.assert_allclose(force_signature(part(([0, 10], [2, 8])), 4), [2.0, 4.0, 6.0, 8.0])


def test_signatures_are_standardised_by_the_training_parts_alone():
    train = np.array([[1.0, 5.0], [3.0, 5.0]])          # column 1 is the same on both training parts
    train_z, val_z = standardised(train, np.array([[4.0, 7.0]]))
    np.testing.assert_allclose(train_z.numpy(), [[-1.0, 0.0], [1.0, 0.0]])
    np.testing.assert_allclose(val_z.numpy(), [[2.0, 2.0]])      # (4 - 2) / 1 and (7 - 5) / 1
    assert standardised(train, np.zeros((0, 2)))[1].shape == (0, 2)


def test_the_cloud_batches_carry_each_clouds_row():
    parts = [PartData(f"p{i}", PointCloud(np.full((4, 3), i, np.float32), np.zeros(3), "volume"), [], [])
             for i in range(5)]
    for clouds, rows in cloud_loader(parts, 2, True, 0):
        assert torch.equal(clouds[:, 0, 0], rows.float())


@pytest.mark.filterwarnings("ignore:You are trying to `self.log")   # the stage outside a Trainer
def test_the_force_term_adds_its_weighted_readout_error_to_the_training_loss_only():
    from pipe.plugins.encoder.pointnet import PointNetVAE

    torch.manual_seed(0)
    encoder = PointNetVAE(num_points=32, latent_dim=4)
    signatures = (torch.randn(3, 5), torch.randn(2, 5))
    shaped = VAEStage(encoder, lr=1e-3, kl_weight=1.0, force_weight=7.0, signatures=signatures)
    plain = VAEStage(encoder, lr=1e-3, kl_weight=1.0)
    clouds, rows = torch.randn(2, 32, 3), torch.tensor([2, 0])
    losses = {}
    for name, stage in (("shaped", shaped), ("plain", plain)):
        torch.manual_seed(1)                 # the same latent draw for both
        losses[name] = stage._step([clouds, rows], "train")
    mu = encoder.train().encode(clouds)[0]
    readout = shaped.readout(mu)
    term = ((readout - signatures[0][rows]) ** 2).mean()
    assert losses["shaped"].item() == pytest.approx(losses["plain"].item() + 7.0 * term.item(), rel=1e-5)
    # the readout trains with the encoder; without the term there is none
    optimised = {id(p) for group in shaped.configure_optimizers().param_groups for p in group["params"]}
    assert {id(p) for p in shaped.readout.parameters()} <= optimised and plain.readout is None


def test_train_py_with_the_force_term_trains_another_code_and_keeps_the_checkpoint_choice(tiny_data, tmp_path):
    plain = run_domain(smoke_config(tiny_data, tmp_path / "plain", "mlflow.enabled=false",
                                    "evaluation.baselines=[nearest]"))
    shaped = run_domain(smoke_config(tiny_data, tmp_path / "shaped", "mlflow.enabled=false",
                                     "evaluation.baselines=[nearest]", "stages.vae.force_weight=100",
                                     "stages.vae.force_bins=4"))
    assert np.isfinite(shaped.pipe.domain["fit_F"]) and shaped.pipe.domain["fit_F"] != plain.pipe.domain["fit_F"]
    header, *rows = (tmp_path / "shaped/logs/vae/metrics.csv").read_text().splitlines()
    names = header.split(",")
    assert {"vae/train_force", "vae/val_force"} <= set(names)
    # the checkpoint is still chosen by Chamfer + KL alone (kl_weight 1): the term is only logged beside it
    for row in rows:
        values = dict(zip(names, row.split(",")))
        if values["vae/val_loss"]:
            assert float(values["vae/val_loss"]) == pytest.approx(float(values["vae/val_chamfer"])
                                                                  + float(values["vae/val_kl"]), rel=1e-5)
    state = torch.load(tmp_path / "shaped/checkpoints/vae/best.ckpt", weights_only=True)["state_dict"]
    assert state["readout.weight"].shape == (4, 32)       # (force_bins, latent_dim)


@pytest.mark.parametrize("setting, message", [
    ("stages.vae.force_weight=-1", "stages.vae.force_weight must be a number, 0 or more (0: no force term), or a "
                                   "list of such numbers to choose from on the validation parts, not -1"),
    ("stages.vae.force_weight=much", "stages.vae.force_weight must be a number, 0 or more (0: no force term), or "
                                     "a list of such numbers to choose from on the validation parts, not 'much'"),
    ("stages.vae.force_bins=0", "stages.vae.force_bins must be a whole number, 1 or more, not 0")])
def test_a_wrong_force_term_is_refused_before_stage_one(tiny_data, tmp_path, setting, message):
    result = run_train("experiment=smoke", setting, f"data.dir={tiny_data}", f"hydra.run.dir={tmp_path}",
                       *TINY_DOMAIN)
    said = " ".join(result.stderr.split())          # as printed, folded to the terminal's width
    assert result.returncode != 0 and message in said
    assert "Traceback" not in said and not (tmp_path / "checkpoints").exists()


def test_a_resume_with_another_force_setting_is_refused_and_leaves_the_run_as_it_was(tiny_data, tmp_path):
    run_domain(smoke_config(tiny_data, tmp_path, "mlflow.enabled=false", "phase=train", "stages.vae.force_weight=100",
                            "stages.vae.force_bins=4"))
    kept = [tmp_path / "config.yaml", tmp_path / "checkpoints/vae/last.ckpt", tmp_path / "checkpoints/head/last.ckpt",
            tmp_path / "logs/vae/metrics.csv", tmp_path / "logs/head/metrics.csv"]
    before = [path.read_bytes() for path in kept]
    result = run_train("experiment=smoke", "mlflow.enabled=false", "phase=train", f"resume={tmp_path}",
                       f"data.dir={tiny_data}", f"hydra.run.dir={tmp_path}", "stages.vae.epochs=3", *TINY_DOMAIN)
    said = " ".join(result.stderr.split())          # as printed, folded to the terminal's width
    assert result.returncode != 0 and "Traceback" not in said
    assert "was trained with other settings than this run's: the weights of stage 'vae' differ in readout.bias, " \
           "readout.weight, train_signatures, val_signatures" in said
    assert "checkpoints/vae/last.ckpt" in said and "the run folder's config.yaml" in said
    assert [path.read_bytes() for path in kept] == before
