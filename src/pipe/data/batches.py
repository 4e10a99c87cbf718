"""Tensors and batches built from a prepared domain: clouds per part, trials padded to a common length."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, TensorDataset

from pipe.data.prepared import PartData
from pipe.data.preprocess import Profile


@dataclass
class TrialBatch:  # not frozen: Lightning moves its tensors to the device in place
    part: torch.Tensor     # (B,) index into the domain's part list
    depth: torch.Tensor    # (B, T) mm, padded with the final value
    force: torch.Tensor    # (B, T) N, padded with the final value
    mask: torch.Tensor     # (B, T) True on real samples
    dt: float              # s, the profiles' common sample period


def stack_clouds(parts: list[PartData]) -> torch.Tensor:
    """The parts' point clouds as one (parts, n, 3) tensor in mm."""
    return torch.from_numpy(np.stack([p.cloud.points for p in parts])).float()


def stack_slices(parts: list[PartData]) -> torch.Tensor | None:
    """The parts' mesh slices (pipe.data.slices) as one (parts, SLICE_SIZE) float64 tensor, None where a part
    has none (a cloud not sampled from a mesh file)."""
    if any(p.cloud.slices is None for p in parts):
        return None
    return torch.from_numpy(np.stack([p.cloud.slices for p in parts])).double()


def stack_geometry(parts: list[PartData]) -> tuple[torch.Tensor, torch.Tensor | None]:
    """What PIPE encodes of the parts: their clouds (`stack_clouds`) and mesh slices (`stack_slices`), the
    arguments of `PIPEModel.latent_distribution`."""
    return stack_clouds(parts), stack_slices(parts)


def sample_period(profile: Profile) -> float:
    return float(profile.time[1] - profile.time[0])


class TrialDataset(Dataset):
    """Every trial of the given parts; `part_index` maps part names to rows of the latent table."""

    def __init__(self, parts: list[PartData], part_index: dict[str, int]) -> None:
        self.items = [(part_index[p.name], prof) for p in parts for prof in p.profiles]

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> tuple[int, Profile]:
        return self.items[i]


def collate_trials(items: list[tuple[int, Profile]]) -> TrialBatch:
    """Trials of one sample rate, padded with their final values to the longest."""
    periods = {round(sample_period(p), 12) for _, p in items}
    if len(periods) != 1:
        raise ValueError(f"trials of different sample periods {sorted(periods)} cannot share a batch")
    length = max(len(p.depth) for _, p in items)
    pad = lambda x: np.pad(x, (0, length - len(x)), mode="edge")  # noqa: E731
    return TrialBatch(
        part=torch.tensor([i for i, _ in items]),
        depth=torch.from_numpy(np.stack([pad(p.depth) for _, p in items])).float(),
        force=torch.from_numpy(np.stack([pad(p.force) for _, p in items])).float(),
        mask=torch.from_numpy(np.stack([np.arange(length) < len(p.depth) for _, p in items])),
        dt=sample_period(items[0][1]),
    )


def part_batch(part: PartData, row: int) -> TrialBatch:
    """All trials of one part, padded, tagged with the part's latent row."""
    return collate_trials([(row, p) for p in part.profiles])


def unpad(values: np.ndarray, part: PartData) -> list[np.ndarray]:
    """Rows of a padded (trials, T) array cut back to each of the part's trials' own length."""
    return [values[i, : len(p.force)] for i, p in enumerate(part.profiles)]


def cloud_loader(parts: list[PartData], batch_size: int, shuffle: bool, seed: int) -> DataLoader:
    """Batches of (the parts' clouds, their rows in `parts`), in an order fixed by `seed`."""
    return DataLoader(TensorDataset(stack_clouds(parts), torch.arange(len(parts))), batch_size=batch_size,
                      shuffle=shuffle, generator=torch.Generator().manual_seed(seed))


def trial_loader(parts: list[PartData], part_index: dict[str, int], batch_size: int, shuffle: bool,
                 seed: int) -> DataLoader:
    return DataLoader(TrialDataset(parts, part_index), batch_size=batch_size, shuffle=shuffle,
                      collate_fn=collate_trials, generator=torch.Generator().manual_seed(seed))
