"""Tensors and batches built from a prepared domain: clouds per part, trials padded to a common length."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from pipe.data.prepare import PartData


@dataclass
class TrialBatch:  # not frozen: Lightning moves its tensors to the device in place
    part: torch.Tensor     # (B,) index into the domain's part list
    depth: torch.Tensor    # (B, T) mm, padded with the final value
    force: torch.Tensor    # (B, T) N, padded with the final value
    mask: torch.Tensor     # (B, T) True on real samples


def stack_clouds(parts: list[PartData]) -> torch.Tensor:
    """The parts' point clouds as one (parts, n, 3) tensor in mm."""
    return torch.from_numpy(np.stack([p.cloud.points for p in parts])).float()


class TrialDataset(Dataset):
    """Every trial of the given parts; `part_index` maps part names to rows of the latent table."""

    def __init__(self, parts: list[PartData], part_index: dict[str, int]) -> None:
        self.items = [(part_index[p.name], prof.depth, prof.force) for p in parts for prof in p.profiles]

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> tuple[int, np.ndarray, np.ndarray]:
        return self.items[i]


def collate_trials(items: list[tuple[int, np.ndarray, np.ndarray]]) -> TrialBatch:
    length = max(len(d) for _, d, _ in items)
    pad = lambda x: np.pad(x, (0, length - len(x)), mode="edge")  # noqa: E731
    return TrialBatch(
        part=torch.tensor([p for p, _, _ in items]),
        depth=torch.from_numpy(np.stack([pad(d) for _, d, _ in items])).float(),
        force=torch.from_numpy(np.stack([pad(f) for _, _, f in items])).float(),
        mask=torch.from_numpy(np.stack([np.arange(length) < len(d) for _, d, _ in items])),
    )


def cloud_loader(parts: list[PartData], batch_size: int, shuffle: bool, seed: int) -> DataLoader:
    return DataLoader(stack_clouds(parts), batch_size=batch_size, shuffle=shuffle,
                      generator=torch.Generator().manual_seed(seed))


def trial_loader(parts: list[PartData], part_index: dict[str, int], batch_size: int, shuffle: bool,
                 seed: int) -> DataLoader:
    return DataLoader(TrialDataset(parts, part_index), batch_size=batch_size, shuffle=shuffle,
                      collate_fn=collate_trials, generator=torch.Generator().manual_seed(seed))
