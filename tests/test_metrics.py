"""The paper's metrics against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest

from pipe.evaluation.metrics import fit_percent, force_metrics, mean_metrics, nrmse_fit_percent, rms, rms_rel

X = np.array([1.0, 2.0, 3.0, 4.0])
X_HAT = np.array([1.0, 2.0, 3.0, 5.0])   # error 1 in the last sample; ||x - mean||^2 = 5


def test_fit_is_one_minus_nmse_with_squared_norms():
    assert fit_percent(X, X_HAT) == pytest.approx(100 * (1 - 1 / 5))          # 80
    assert fit_percent(X, X) == 100.0
    assert fit_percent(X, np.full(4, X.mean())) == pytest.approx(0.0)        # the mean predicts nothing


def test_matlab_compare_fit_uses_plain_norms():
    assert nrmse_fit_percent(X, X_HAT) == pytest.approx(100 * (1 - 1 / np.sqrt(5)))   # 55.28
    assert nrmse_fit_percent(X, X_HAT) < fit_percent(X, X_HAT)


def test_rms_and_rms_rel():
    assert rms(X, X_HAT) == pytest.approx(0.5)                               # sqrt(1 / 4)
    assert rms_rel(X, X_HAT) == pytest.approx(np.sqrt((1 / 4) ** 2 / 4))     # error / max|F| = 1/4, once
    assert rms_rel(-X, -X_HAT) == pytest.approx(rms_rel(X, X_HAT))


def test_fit_of_the_derivative_uses_central_differences():
    dt = 0.5
    force = np.array([0.0, 1.0, 4.0, 9.0, 16.0])          # gradient: 2, 4, 8, 12, 14
    predicted = np.array([0.0, 1.0, 4.0, 9.0, 14.0])      # gradient: 2, 4, 8, 10, 10
    metrics = force_metrics(force, predicted, dt)
    rate = np.array([2.0, 4.0, 8.0, 12.0, 14.0])
    expected = 100 * (1 - (0 + 0 + 0 + 4 + 16) / np.sum((rate - rate.mean()) ** 2))
    assert metrics["fit_dF"] == pytest.approx(expected)
    assert metrics["fit_F"] == pytest.approx(fit_percent(force, predicted))


def test_mean_metrics_average_each_key():
    assert mean_metrics([{"a": 1.0, "b": 4.0}, {"a": 3.0, "b": 0.0}]) == {"a": 2.0, "b": 2.0}


def test_stage_two_normalised_loss_is_one_minus_fit_per_trial():
    """stages.head.loss=nmse: each trial's squared error over its force's squared deviation from its mean,
    padding excluded, averaged over the trials; so 1 - FIT / 100 trial by trial."""
    import torch

    from pipe.model.losses import masked_normalised_mse

    force = torch.tensor([[1.0, 3.0, 3.0], [10.0, 20.0, 30.0]])        # trial 0 padded after two samples
    mask = torch.tensor([[True, True, False], [True, True, True]])
    predicted = torch.tensor([[2.0, 3.0, 9.0], [10.0, 20.0, 20.0]])
    # trial 0: error 1, squared deviation 2 (mean 2); trial 1: error 100, squared deviation 200 (mean 20)
    assert float(masked_normalised_mse(predicted, force, mask)) == pytest.approx((1 / 2 + 100 / 200) / 2)
    fits = [fit_percent(force[k][mask[k]].numpy(), predicted[k][mask[k]].numpy()) for k in range(2)]
    assert float(masked_normalised_mse(predicted, force, mask)) == pytest.approx(1 - np.mean(fits) / 100)


def test_trial_weights_give_each_force_loss_as_a_weighted_sum_of_squared_errors():
    """The identification's per-trial weights (`trial_weights`): on the trials above, 1/5 each under mse (five
    real samples) and 1 / (2 x 2), 1 / (2 x 200) under nmse; their weighted squared errors are the losses."""
    import torch

    from pipe.evaluation.force_error import trial_weights
    from pipe.model.losses import FORCE_LOSSES

    force = torch.tensor([[1.0, 3.0, 3.0], [10.0, 20.0, 30.0]])
    mask = torch.tensor([[True, True, False], [True, True, True]])
    predicted = torch.tensor([[2.0, 3.0, 9.0], [10.0, 20.0, 20.0]])
    expected = {"mse": [1 / 5, 1 / 5], "nmse": [1 / 4, 1 / 400]}
    for loss, weights in expected.items():
        computed = trial_weights(force, mask, loss)
        np.testing.assert_allclose(computed.numpy(), weights, rtol=1e-6)
        squared = torch.where(mask, predicted - force, 0.0).pow(2).sum(1)
        assert float((computed * squared).sum()) == pytest.approx(float(FORCE_LOSSES[loss](predicted, force, mask)))
    with pytest.raises(ValueError, match="unknown force loss 'mae'"):
        trial_weights(force, mask, "mae")
