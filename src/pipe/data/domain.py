"""A domain: the train / val / test split of parts (paper, Table I), checked against a dataset."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipe.errors import PipeError

SPLITS = ("train", "val", "test")


@dataclass(frozen=True)
class Domain:
    name: str
    train: tuple[str, ...]
    val: tuple[str, ...]
    test: tuple[str, ...]

    @property
    def parts(self) -> tuple[str, ...]:
        return self.train + self.val + self.test


def numbered_part(prefix: str, number: int) -> str:
    """The name of part `number` of a numbered set, e.g. a generated family's `pins_0007`."""
    return f"{prefix}_{number:04d}"


def numbered_split(prefix: str | None, split: str, test_count: int, val_count: int, train_count: int) -> list[str]:
    """One split of a numbered set of parts, divided by number: test the first test_count, val the next
    val_count, train the next train_count. A larger train_count only adds parts, so training sets of growing
    size are nested and share the test and validation parts (a learning curve, conf/domain/curve.yaml).
    Without a prefix (a family domain over data that names no family) every split is empty:
    `domain_from_config` then says what is missing."""
    if prefix is None:
        return []
    first = {"test": 0, "val": test_count, "train": test_count + val_count}
    counts = {"test": test_count, "val": val_count, "train": train_count}
    if split not in first:
        raise PipeError(f"numbered_split: unknown split {split!r}; choose one of {', '.join(SPLITS)}")
    if min(counts.values()) < 0:
        raise PipeError(f"numbered_split: part counts cannot be negative, got {counts}")
    return [numbered_part(prefix, k) for k in range(first[split], first[split] + counts[split])]


def domain_from_config(cfg: Mapping[str, Any]) -> Domain:
    """Build a domain from its config group: training parts are required, no part is named twice in a split,
    and test parts must not be in train or val. Without test parts a run scores nothing and publishes the
    model trained on all the others (`pipe.pipeline.publish_trained`)."""
    name = str(cfg.get("name", "?"))
    if "family" in cfg and cfg["family"] is None:
        raise PipeError(f"domain {name!r} splits the parts of a generated family, but the data config names no "
                        "family; add data=family (e.g. data=family data.generate.family=pins)")
    splits = {}
    for split in SPLITS:
        parts = cfg.get(split)
        if parts is None or isinstance(parts, str) or not all(isinstance(p, str) for p in parts):
            raise PipeError(f"domain {name!r}: '{split}' must be a list of part names, got {parts!r}")
        splits[split] = tuple(parts)
    if not splits["train"]:
        raise PipeError(f"domain {name!r} has no training parts")
    for split, parts in splits.items():
        if twice := sorted({part for part in parts if parts.count(part) > 1}):
            raise PipeError(f"domain {name!r}: parts {twice} are named more than once in '{split}'")
    for a, b in (("train", "val"), ("train", "test"), ("val", "test")):
        shared = sorted(set(splits[a]) & set(splits[b]))
        if shared:
            raise PipeError(f"domain {name!r}: parts {shared} are in both '{a}' and '{b}'")
    return Domain(name, **splits)


def require_parts(domain: Domain, dataset_root: str | Path) -> None:
    """Fail clearly when the domain names parts the dataset at `dataset_root` does not have (its `parts/`
    folders)."""
    folder = Path(dataset_root) / "parts"
    available = {p.name for p in folder.iterdir() if p.is_dir()} if folder.is_dir() else set()
    missing = sorted(set(domain.parts) - available)
    if missing:
        raise PipeError(f"domain {domain.name!r} needs part(s) {missing} that the dataset does not have",
                        dataset_root)
