"""Writing a dataset folder all at once: built beside its destination, then renamed into place, so that a
failed or interrupted run never leaves a half-written dataset that looks valid."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

from pipe.data.spec import SPEC_FILE
from pipe.errors import PipeError


def check_replaceable(out: Path, what: str) -> None:
    """Refuse an `out` that exists and is neither empty nor a dataset (`what` written there before)."""
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / SPEC_FILE).is_file())):
        raise PipeError(f"exists and is not {what}; choose an empty or new folder", out)


def write_dataset_folder(out: Path, write: Callable[[Path], None]) -> Path:
    """Call `write(staging)` on a fresh folder beside `out`, then put it in the place of `out` (replacing an
    earlier dataset there); on any error `out` is left as it was."""
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        write(staging)
        if out.exists():
            old = out.with_name(f".{out.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            out.rename(old)
            staging.rename(out)
            shutil.rmtree(old)
        else:
            staging.rename(out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return out
