"""Evaluation metrics of the paper's "Evaluation" section (and MATLAB compare's fit, named apart).

FIT(x) = (1 - NMSE(x)) * 100, NMSE = ||x - x_hat||^2 / ||x - mean(x)||^2   (paper; squared norms)
NRMSE fit = (1 - ||x - x_hat|| / ||x - mean(x)||) * 100                     (MATLAB `compare`)
rms = sqrt(mean((F - F_hat)^2)) [N];  rms_rel = sqrt(mean(((F - F_hat) / max|F|)^2))
"""

from __future__ import annotations

import numpy as np


def _deviation(x: np.ndarray) -> float:
    return float(np.sum((x - x.mean()) ** 2))


def fit_percent(x: np.ndarray, x_hat: np.ndarray) -> float:
    """The paper's FIT: 100 (1 - NMSE) with squared norms."""
    return 100.0 * (1.0 - float(np.sum((x - x_hat) ** 2)) / _deviation(x))


def nrmse_fit_percent(x: np.ndarray, x_hat: np.ndarray) -> float:
    """MATLAB compare's fit: 100 (1 - NRMSE) with plain norms."""
    return 100.0 * (1.0 - np.sqrt(np.sum((x - x_hat) ** 2)) / np.sqrt(_deviation(x)))


def rms(x: np.ndarray, x_hat: np.ndarray) -> float:
    return float(np.sqrt(np.mean((x - x_hat) ** 2)))


def rms_rel(x: np.ndarray, x_hat: np.ndarray) -> float:
    """rms of the error relative to the measured force's largest magnitude (paper)."""
    return float(np.sqrt(np.mean(((x - x_hat) / np.abs(x).max()) ** 2)))


def force_metrics(force: np.ndarray, predicted: np.ndarray, dt: float) -> dict[str, float]:
    """The paper's metrics of one trial: FIT of F and of dF/dt (central differences), rms, rms_rel."""
    rate, rate_hat = np.gradient(force, dt), np.gradient(predicted, dt)
    return {
        "fit_F": fit_percent(force, predicted),
        "fit_dF": fit_percent(rate, rate_hat),
        "nrmse_fit_F": nrmse_fit_percent(force, predicted),
        "rms": rms(force, predicted),
        "rms_rel": rms_rel(force, predicted),
    }


def mean_metrics(rows: list[dict[str, float]]) -> dict[str, float]:
    return {key: float(np.mean([r[key] for r in rows])) for key in rows[0]}
