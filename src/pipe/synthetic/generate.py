"""Write the synthetic dataset: meshes, trials with sensor noise, and per-trial ground truth."""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipe.data.folders import check_replaceable, write_dataset_folder
from pipe.data.spec import Columns, DatasetSpec
from pipe.errors import PipeError
from pipe.synthetic.catalogue import CATALOGUE, Pin, Plug
from pipe.synthetic.contact import TrialConditions, static_curves, target_depth
from pipe.synthetic.dynamics import INTERNAL_RATE_HZ, ContactTables, command_profile, simulate, static_tcp_depth
from pipe.synthetic.families import DEFAULT_COUNT, family_part_names, family_parts
from pipe.synthetic.meshes import part_mesh

SAMPLE_RATE_HZ = 500
TRIALS_PER_PART = 10
REST_S, HOLD_S = 0.2, 1.0
NOMINAL_SPEED = {"plug": 4.0, "pin": 8.0}   # mm/s
FORCE_NOISE = 0.04                           # N, sensor noise (1 sigma)
POSITION_NOISE = 0.002                       # mm, encoder noise (1 sigma)
GRID_STEP = 0.005                            # mm, depth grid of the contact tables
TRUTH_STEP = 0.02                            # mm, depth step of the stored static curves
COLUMNS = Columns(time="t", position="p_z", force="F_z", force_clean="F_z_clean")
CHUNK_PARTS = 32                             # parts integrated together (memory: trials x steps at 10 kHz)


@dataclass(frozen=True)
class SimulatedTrial:
    part: str
    conditions: TrialConditions
    time: np.ndarray
    depth: np.ndarray        # measured TCP depth, mm
    force: np.ndarray        # measured force, N (noise and bias)
    force_clean: np.ndarray  # sensor reading without noise and bias, N
    static_depth: np.ndarray  # true static curve: TCP depth, mm
    static_force: np.ndarray  # true static curve: force, N


def part_rng(seed: int, name: str) -> np.random.Generator:
    """Each part has its own stream, so a part's trials do not depend on which other parts are generated."""
    return np.random.default_rng([seed, zlib.crc32(name.encode())])


def draw_conditions(part: Plug | Pin, rng: np.random.Generator) -> TrialConditions:
    is_plug = isinstance(part, Plug)
    return TrialConditions(
        speed=NOMINAL_SPEED["plug" if is_plug else "pin"] * rng.uniform(0.7, 1.3),
        misalignment=min(abs(rng.normal(0.0, 0.15)), 0.4),
        gap=rng.uniform(1.0, 2.0),
        overtravel=rng.uniform(0.1, 0.3) if is_plug else (rng.uniform(0.3, 0.7) if part.taper else 0.0),
        friction_scale=rng.uniform(0.9, 1.1),
        contact_offsets=rng.normal(0.0, 0.04, part.contacts),
        sensor_bias=rng.uniform(-1.0, 1.0),
    )


def simulate_parts(parts: dict[str, Plug | Pin] | list[str], seed: int,
                   trials: int = TRIALS_PER_PART) -> list[SimulatedTrial]:
    """Simulate `trials` insertions of each part (name -> part, or names of catalogue parts), CHUNK_PARTS
    parts integrated together (trials do not interact: the chunks change nothing but the memory taken)."""
    if not isinstance(parts, dict):
        parts = {name: CATALOGUE[name] for name in parts}
    names = list(parts)
    return [trial for first in range(0, len(names), CHUNK_PARTS)
            for trial in _simulate_together({n: parts[n] for n in names[first:first + CHUNK_PARTS]}, seed, trials)]


def _simulate_together(parts: dict[str, Plug | Pin], seed: int, trials: int) -> list[SimulatedTrial]:
    rngs = {name: part_rng(seed, name) for name in parts}
    jobs = [(name, draw_conditions(parts[name], rngs[name])) for name in parts for _ in range(trials)]
    return simulate_conditions(parts, jobs, rngs)


def simulate_conditions(parts: dict[str, Plug | Pin], jobs: list[tuple[str, TrialConditions]],
                        rngs: dict[str, np.random.Generator]) -> list[SimulatedTrial]:
    """One trial per (part name, conditions) job, integrated together; each part's sensor noise drawn from its
    generator in `rngs`, trial after trial."""
    commands = [command_profile(c.gap, target_depth(parts[n]) + c.overtravel, c.speed, REST_S, HOLD_S)
                for n, c in jobs]
    n_steps = max(len(cmd) for cmd in commands)
    command = np.stack([np.pad(cmd, (0, n_steps - len(cmd)), mode="edge") for cmd in commands])
    grid = np.arange(0.0, command.max() + 1.0, GRID_STEP)
    curves = [static_curves(parts[n], c, grid) for n, c in jobs]
    tables = ContactTables(GRID_STEP, np.stack([e for e, _ in curves]), np.stack([f for _, f in curves]))
    decimation = INTERNAL_RATE_HZ // SAMPLE_RATE_HZ
    depth, force = simulate(command, tables, decimation)

    out = []
    truth_x = np.arange(0.0, grid[-1], TRUTH_STEP)
    for i, ((name, cond), cmd) in enumerate(zip(jobs, commands)):
        n = (len(cmd) - 1) // decimation + 1
        rng = rngs[name]
        clean = force[i, :n]
        measured_depth = depth[i, :n] + rng.normal(0.0, POSITION_NOISE, n)
        measured_force = clean + cond.sensor_bias + rng.normal(0.0, FORCE_NOISE, n)
        elastic, friction = static_curves(parts[name], cond, truth_x)
        static_force = elastic + friction
        static_depth = static_tcp_depth(truth_x, static_force)
        keep = static_depth <= depth[i, :n].max()
        out.append(SimulatedTrial(name, cond, np.arange(n) / SAMPLE_RATE_HZ, measured_depth, measured_force,
                                  clean, static_depth[keep], static_force[keep]))
    return out


def part_metadata(part: Plug | Pin) -> dict:
    if isinstance(part, Plug):
        return {"family": part.family, "contacts": part.contacts, "shell_width_mm": part.width,
                "shell_height_mm": part.height, "mate_length_mm": part.mate_length}
    meta = {"family": part.family, "diameter_mm": part.diameter, "length_mm": part.length,
            "insert_depth_mm": part.insert_depth}
    if part.taper:
        meta["taper"] = "1:50"
    if part.chamfer is not None:
        meta["chamfer_mm"] = round(part.chamfer, 3)
    return meta


def _write_csv(path: Path, header: list[str], columns: list[np.ndarray], fmt: list[str]) -> None:
    np.savetxt(path, np.column_stack(columns), fmt=fmt, delimiter=",", header=",".join(header), comments="")


def write_dataset(out: Path, parts: dict[str, Plug | Pin], command: str, trials: list[SimulatedTrial]) -> None:
    spec = DatasetSpec(root=out, name="pipe-synthetic", columns=COLUMNS, sample_rate_hz=SAMPLE_RATE_HZ,
                       parts={n: part_metadata(p) for n, p in parts.items()})
    text = f"# Synthetic insertions generated by `{command}`; see docs/synthetic.md.\n"
    (out / "dataset.yaml").write_text(text + spec.to_yaml())
    counters: dict[str, int] = {}
    for name, part in parts.items():
        part_dir = out / "parts" / name
        (part_dir / "trials").mkdir(parents=True)
        (part_dir / "truth").mkdir()
        part_mesh(part).export(part_dir / "mesh.stl")
    for trial in trials:
        index = counters[trial.part] = counters.get(trial.part, -1) + 1
        part_dir = out / "parts" / trial.part
        stem = f"trial_{index:02d}.csv"
        _write_csv(part_dir / "trials" / stem, ["t", "p_z", "F_z", "F_z_clean"],
                   [trial.time, trial.depth, trial.force, trial.force_clean], ["%.4f", "%.5f", "%.5f", "%.5f"])
        _write_csv(part_dir / "truth" / stem, ["p_z", "F_static"], [trial.static_depth, trial.static_force],
                   ["%.5f", "%.5f"])


def generated_part_names(family: str | None = None, count: int = DEFAULT_COUNT) -> list[str]:
    """The parts `generate_dataset` writes (the whole catalogue, or `count` parts of a `family`), known
    without simulating them."""
    return list(CATALOGUE) if family is None else family_part_names(family, count)


def generate_dataset(out: str | Path, seed: int = 0, parts: list[str] | None = None, family: str | None = None,
                     count: int = DEFAULT_COUNT) -> Path:
    """Generate the synthetic dataset into `out`, replacing an earlier generated dataset there atomically:
    the catalogue's parts (all, or the named `parts`), or `count` parts of a `family` (`families`).

    A folder that exists, is not empty and holds no dataset.yaml is refused rather than overwritten.
    """
    out = Path(out)
    if family is not None:
        if parts is not None:
            raise PipeError("give either a part family or catalogue part names, not both")
        chosen = family_parts(family, count, seed)
        command = f"pipe data generate --family {family} --count {count} --seed {seed}"
    else:
        names = list(CATALOGUE) if parts is None else list(dict.fromkeys(parts))
        unknown = [n for n in names if n not in CATALOGUE]
        if unknown:
            raise PipeError(f"unknown part(s) {unknown}; the synthetic parts are: {', '.join(CATALOGUE)}")
        chosen = {n: CATALOGUE[n] for n in names}
        command = f"pipe data generate --seed {seed}"
    check_replaceable(out, "a generated dataset")
    trials = simulate_parts(chosen, seed)
    write_dataset_folder(out, lambda staging: write_dataset(staging, chosen, command, trials))
    return out
