"""Output files written whole or not at all: each is written beside its destination under a temporary
name and renamed onto it, so that an interrupted or failed run never leaves a half-written report, metrics
file or figure that looks valid (and an earlier complete one stays until the new one is complete)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path beside `path` (same suffix, so that writers that go by it still do) to write to;
    renamed onto `path` when the block ends, removed if it raises."""
    path = Path(path)
    temporary = path.with_name(f".{path.stem}.{os.getpid()}.partial{path.suffix}")
    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def write_text_atomically(path: str | Path, text: str) -> None:
    with atomic_path(path) as temporary:
        temporary.write_text(text)
