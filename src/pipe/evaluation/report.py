"""Results of a domain run as JSON, Markdown tables and plots (written to <run>/report/)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from pipe.evaluation.evaluate import MethodResult  # noqa: E402
from pipe.evaluation.spread import Spread, verdict  # noqa: E402
from pipe.files import atomic_path, write_text_atomically
from pipe.model.novelty import novelty  # noqa: E402
from pipe.model.uncertainty import BandSettings, theta_band  # noqa: E402

COLUMNS = [("fit_F", "FIT(F) [%]"), ("fit_dF", "FIT(dF/dt) [%]"), ("nrmse_fit_F", "NRMSE fit(F) [%]"),
           ("rms", "rms [N]"), ("rms_rel", "rms_rel"), ("static_rms", "static rms [N]"),
           ("id_loss", "identification MSE [N^2]"), ("id_evals", "identification evaluations")]


def results_document(domain: str, counts: dict[str, int], results: dict[str, MethodResult],
                     reconstruction: dict[str, dict[str, float]], seconds: dict[str, float],
                     novelties: dict[str, dict[str, float | str]] | None) -> dict:
    return {"domain": domain, "parts": counts, "seconds": seconds, "reconstruction": reconstruction,
            "methods": {name: {"domain": r.domain, "per_part": r.per_part} for name, r in results.items()},
            "novelty": novelties}


def novelty_of_test_parts(run) -> dict[str, dict[str, float | str]] | None:
    """Each test part's nearest training part and its distance over the training parts' coverage radius, in
    what the head reads (`pipe.model.novelty`: above 1 PIPE extrapolates); None where not measured."""
    if not run.card.reference_codes:
        return None
    codes = torch.stack([run.latents[run.index[part.name]] for part in run.test])
    found = novelty(codes, torch.tensor(run.card.reference_codes), run.card.train_parts)
    return None if found is None else {part.name: {"nearest_training_part": item.nearest, "ratio": item.ratio}
                                       for part, item in zip(run.test, found)}


def _cell(metrics: dict[str, float], key: str) -> str:
    return f"{metrics[key]:.2f}" if key in metrics else "-"


def results_markdown(doc: dict) -> str:
    """Table II of the paper (domain, part counts, rms, rms_rel) with FIT and one row per method,
    then the same metrics per test part."""
    counts, methods = doc["parts"], doc["methods"]
    head = "| domain | method | # train | # val | # test | " + " | ".join(t for _, t in COLUMNS) + " |"
    rule = "|" + " --- |" * (5 + len(COLUMNS))
    lines = [f"### Domain {doc['domain']}", "", head, rule]
    for name, m in methods.items():
        lines.append(f"| {doc['domain']} | {name} | {counts['train']} | {counts['val']} | {counts['test']} | "
                     + " | ".join(_cell(m["domain"], k) for k, _ in COLUMNS) + " |")
    lines += ["", "| test part | method | " + " | ".join(t for _, t in COLUMNS) + " |",
              "|" + " --- |" * (2 + len(COLUMNS))]
    for part in next(iter(methods.values()))["per_part"]:
        for name, m in methods.items():
            lines.append(f"| {part} | {name} | " + " | ".join(_cell(m["per_part"][part], k) for k, _ in COLUMNS)
                         + " |")
    lines += _band_lines({k: f"{v:.2f}" for k, v in methods.get("pipe", {}).get("domain", {}).items()})
    if doc.get("novelty"):
        lines += ["", "| test part | nearest training part (head's input) | distance over the training parts' "
                  "coverage radius (above 1: extrapolated) |", "| --- | --- | --- |"]
        lines += [f"| {part} | {n['nearest_training_part']} | {n['ratio']:.2f} |" for part, n in doc["novelty"].items()]
    lines += ["", "| test part | reconstruction: mean nearest-neighbour distance [mm] | the same on clouds "
              "normalised to the unit sphere | Chamfer [mm^2] |", "| --- | --- | --- | --- |"]
    lines += [f"| {part} | {r['nn_distance_mm']:.3f} | {r['nn_distance_unit_sphere']:.4f} | {r['chamfer_mm2']:.1f} |"
              for part, r in doc["reconstruction"].items()]
    return "\n".join(lines) + "\n"


def _band_lines(pipe: dict[str, str]) -> list[str]:
    """PIPE's band coverage on the test parts (`pipe.model.uncertainty`), where the results have it."""
    if "band_cover" not in pipe:
        return []
    return ["", "PIPE's force band at its nominal level (evaluation.band.level): share of the measured test "
                f"samples inside the band calibrated on the validation parts {pipe['band_cover']} (mean width "
                f"{pipe['band_width']} N); inside the latent band alone {pipe['band_cover_latent']}."]


def _digits(value: Spread, decimals: int) -> str:
    return f"{value.mean:.{decimals}f} ± {value.std:.{decimals}f}"


def spread_markdown(domain: str, counts: dict[str, int], seeds: list[int], summary: dict[str, dict[str, Spread]],
                    reconstruction: dict[str, Spread]) -> str:
    """Every method's metrics as mean ± std over the seeds, and PIPE against it on FIT(F) (a difference
    within the spreads is a tie, `pipe.evaluation.spread`); then the VAE's reconstruction of the test parts."""
    head = "| domain | method | # train | # val | # test | " + " | ".join(t for _, t in COLUMNS) + " | PIPE vs it |"
    lines = [f"### Domain {domain}, mean ± std over seeds {', '.join(map(str, seeds))}", "", head,
             "|" + " --- |" * (6 + len(COLUMNS))]
    pipe = summary["pipe"]["fit_F"]
    for name, metrics in summary.items():
        judged = "-" if name == "pipe" else verdict(pipe, metrics["fit_F"], "fit_F")
        lines.append(f"| {domain} | {name} | {counts['train']} | {counts['val']} | {counts['test']} | "
                     + " | ".join(str(metrics[k]) if k in metrics else "-" for k, _ in COLUMNS) + f" | {judged} |")
    lines += _band_lines({k: str(v) for k, v in summary["pipe"].items()})
    lines += ["", "PIPE vs it: on FIT(F), `better` or `worse` only when the means differ by more than the two "
              "standard deviations added; `tie` otherwise.", "",
              "Reconstruction of the test clouds (mean over the test parts): mean nearest-neighbour distance "
              f"{_digits(reconstruction['nn_distance_mm'], 3)} mm, "
              f"{_digits(reconstruction['nn_distance_unit_sphere'], 4)} on clouds normalised to the unit sphere "
              f"(the paper reports 0.012 mm), Chamfer {_digits(reconstruction['chamfer_mm2'], 1)} mm^2."]
    return "\n".join(lines) + "\n"


def _common(arrays: list[np.ndarray]) -> np.ndarray:
    n = min(len(a) for a in arrays)
    return np.stack([a[:n] for a in arrays])


def force_curves(parts, results: dict[str, MethodResult], dt: float) -> dict[str, dict[str, np.ndarray]]:
    """Per test part the curves of forces.png, up to its shortest trial: time_s, the measured force's mean over
    the trials with its min and max, PIPE's mean prediction with its calibrated band (its limits' mean over
    the trials) and every baseline's mean prediction."""
    curves = {}
    for part in parts:
        measured = _common([p.force for p in part.profiles])
        t = np.arange(measured.shape[1]) * dt
        series = {"time_s": t, "measured": measured.mean(0), "measured_min": measured.min(0),
                  "measured_max": measured.max(0)}
        for name, result in results.items():
            series[name] = _common(result.forces[part.name])[:, : len(t)].mean(0)
            band = result.bands.get(part.name)
            if band is not None:
                series[f"{name}_lower"], series[f"{name}_upper"] = (
                    _common(limits)[:, : len(t)].mean(0) for limits in band.calibrated())
        curves[part.name] = series
    return curves


def write_force_curves(curves: dict[str, dict[str, np.ndarray]], path: Path) -> None:
    """The force curves as a long CSV (part, series, time_s, force_N): `dvc plots` data."""
    rows = [f"{part},{name},{t:.4f},{value:.6g}" for part, series in curves.items()
            for name, values in series.items() if name != "time_s" for t, value in zip(series["time_s"], values)]
    write_text_atomically(path, "\n".join(["part,series,time_s,force_N", *rows]) + "\n")


def plot_forces(curves: dict[str, dict[str, np.ndarray]], fits: dict[str, float], path: Path) -> None:
    """Measured vs predicted force per test part (`force_curves`), titled with PIPE's FIT(F) where `fits`
    has it."""
    fig, axes = plt.subplots(1, len(curves), figsize=(5 * len(curves), 3.6), squeeze=False)
    for ax, (part, series) in zip(axes[0], curves.items()):
        t = series["time_s"]
        ax.fill_between(t, series["measured_min"], series["measured_max"], color="tab:blue", alpha=0.25, lw=0)
        ax.plot(t, series["measured"], color="tab:blue", label="measured")
        for name, values in series.items():
            if name in ("time_s", "measured", "measured_min", "measured_max") or name.endswith(("_lower", "_upper")):
                continue
            if name == "pipe":
                if "pipe_lower" in series:
                    ax.fill_between(t, series["pipe_lower"], series["pipe_upper"], color="k", alpha=0.15, lw=0,
                                    label="PIPE band (mean over trials)")
                ax.plot(t, values, color="k", label="PIPE")
            else:
                ax.plot(t, values, lw=0.8, ls="--", label=name)
        ax.set_title(f"{part}: FIT(F) {fits[part]:.1f} %" if part in fits else part)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("F_z [N]")
    axes[0, -1].legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as temporary:
        fig.savefig(temporary, dpi=110)
    plt.close(fig)


@torch.no_grad()
def plot_theta(model, parts, latents: torch.Tensor, index: dict[str, int], path: Path,
               logvars: torch.Tensor | None = None, band: BandSettings | None = None) -> None:
    """Theta(p_z) of each test part over its depth range, with the local models where the head has them and
    the latent band where the latent distributions are given."""
    names = model.dynamics.parameter_names
    fig, axes = plt.subplots(len(parts), len(names), figsize=(3.4 * len(names), 2.8 * len(parts)), squeeze=False)
    for row, part in zip(axes, parts):
        depth_max = float(np.mean([np.abs(p.depth).max() for p in part.profiles]))
        depth = torch.linspace(0, depth_max, 300)[None]
        z = latents[index[part.name]]
        profile = model.profile(z[None], torch.tensor([depth_max]))
        theta = profile(depth)[0].numpy()
        local = getattr(profile.raw, "weights", None)
        limits = None
        if logvars is not None:
            limits = theta_band(model, z, logvars[index[part.name]], depth_max, depth[0], band or BandSettings())
        for j, ax in enumerate(row):
            if local is not None:  # each local model's contribution a_i Psi_i / sum Psi
                parts_j = (local(depth)[0, :, j] * profile.raw.amplitude[0, j] * profile.scale[j]).numpy()
                ax.plot(depth[0], parts_j, lw=0.6, alpha=0.6)
            if limits is not None:
                ax.fill_between(depth[0], limits[0][:, j], limits[1][:, j], color="k", alpha=0.15, lw=0)
            ax.plot(depth[0], theta[:, j], color="k", lw=1.5)
            ax.set_title(f"{part.name}: {names[j]}", fontsize=9)
            ax.set_xlabel("p_z [mm]")
    fig.tight_layout()
    with atomic_path(path) as temporary:
        fig.savefig(temporary, dpi=100)
    plt.close(fig)


@torch.no_grad()
def plot_clouds(encoder, parts, path: Path) -> None:
    """Input point cloud and its reconstruction from the mean latent code, per test part."""
    fig = plt.figure(figsize=(4.2 * len(parts), 7))
    encoder.eval()
    for k, part in enumerate(parts):
        cloud = torch.from_numpy(part.cloud.points)[None]
        recon = encoder.decode(encoder.encode(cloud)[0])[0].numpy()
        for row, (points, title) in enumerate(((part.cloud.points, "input"), (recon, "reconstruction"))):
            ax = fig.add_subplot(2, len(parts), row * len(parts) + k + 1, projection="3d")
            ax.scatter(points[:, 0], points[:, 1], points[:, 2], s=0.6)
            ax.set_title(f"{part.name}: {title}", fontsize=9)
            ax.set_box_aspect(np.ptp(part.cloud.points, axis=0) + 1e-6)
    fig.tight_layout()
    with atomic_path(path) as temporary:
        fig.savefig(temporary, dpi=100)
    plt.close(fig)


def read_epoch_metrics(csv_path: Path) -> dict[str, list[tuple[int, float]]]:
    """Per metric name, (epoch, value) pairs from a Lightning CSVLogger file."""
    series: dict[str, list[tuple[int, float]]] = {}
    if not csv_path.is_file():
        return series
    with csv_path.open() as handle:
        for row in csv.DictReader(handle):
            for key, value in row.items():
                if key not in ("epoch", "step") and value not in ("", None):
                    series.setdefault(key, []).append((int(row["epoch"]), float(value)))
    return series


LOSS_PANELS = (("vae", "stage 1: VAE", ("vae/train_chamfer", "vae/val_chamfer", "vae/train_kl")),
               ("head", "stage 2: head (MSE, N^2)", ("head/train_loss", "head/val_loss")))


def epoch_losses(run_dir: Path) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Per stage, the loss curves of `LOSS_PANELS` from the CSV logs: epochs and the mean of each epoch's
    logged values (a training loss is logged per step)."""
    curves = {}
    for stage, _, keys in LOSS_PANELS:
        series = read_epoch_metrics(run_dir / "logs" / stage / "metrics.csv")
        curves[stage] = {}
        for key in keys:
            if key in series:
                epochs, values = np.array(series[key]).T
                unique = np.unique(epochs)
                curves[stage][key] = (unique.astype(int), np.array([values[epochs == e].mean() for e in unique]))
    return curves


def write_losses(curves: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]], path: Path) -> None:
    """The loss curves as a long CSV (stage, series, epoch, loss): `dvc plots` data."""
    rows = [f"{stage},{key},{epoch},{value:.6g}" for stage, series in curves.items()
            for key, (epochs, values) in series.items() for epoch, value in zip(epochs, values)]
    write_text_atomically(path, "\n".join(["stage,series,epoch,loss", *rows]) + "\n")


def plot_losses(curves: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]], path: Path) -> None:
    """Loss curves of both stages (`epoch_losses`; paper, Fig. "losses")."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, (stage, title, _) in zip(axes, LOSS_PANELS):
        for key, (epochs, values) in curves[stage].items():
            ax.plot(epochs, values, label=key)
        ax.set_yscale("log")
        ax.set_xlabel("epoch")
        ax.set_title(title)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as temporary:
        fig.savefig(temporary, dpi=110)
    plt.close(fig)


def write_report(run, out: Path) -> list[Path]:
    """results.json, results.md, the four figures of a finished run and the data of two of them (forces.csv,
    losses.csv)."""
    out.mkdir(parents=True, exist_ok=True)
    doc = results_document(run.domain_name, run.counts, run.results, run.reconstruction, run.seconds,
                           novelty_of_test_parts(run))
    files = {"results.json": json.dumps(doc, indent=2) + "\n", "results.md": results_markdown(doc)}
    for name, text in files.items():
        write_text_atomically(out / name, text)
    curves = force_curves(run.test, run.results, run.dt)
    write_force_curves(curves, out / "forces.csv")
    fits = {part: m["fit_F"] for part, m in run.results["pipe"].per_part.items()} if "pipe" in run.results else {}
    plot_forces(curves, fits, out / "forces.png")
    plot_theta(run.model, run.test, run.latents, run.index, out / "theta.png", run.logvars, run.card.band.settings)
    plot_clouds(run.model.encoder, run.test, out / "point_clouds.png")
    losses = epoch_losses(run.logs_dir)
    write_losses(losses, out / "losses.csv")
    plot_losses(losses, out / "losses.png")
    return sorted(out.iterdir())
