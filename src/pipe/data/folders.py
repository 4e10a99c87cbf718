"""Dataset folders as a whole: written all at once (built beside their destination, then renamed into place, so
that a failed or interrupted run never leaves a half-written folder that looks valid), and their content version."""

from __future__ import annotations

import hashlib
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

from pipe.data.spec import SPEC_FILE
from pipe.errors import PipeError


def dataset_version(root: Path) -> str:
    """Content hash of a dataset folder: every file's path and bytes, in sorted order."""
    digest = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def check_replaceable(out: Path, what: str, marker: str = SPEC_FILE) -> None:
    """Refuse an `out` that exists and is neither empty nor `what` written there before (a folder holding the
    file `marker`)."""
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / marker).is_file())):
        raise PipeError(f"exists and is not {what}; choose an empty or new folder", out)


def write_dataset_folder(out: Path, write: Callable[[Path], None]) -> Path:
    """Call `write(staging)` on a fresh folder beside `out`, then put it in the place of `out` (replacing an
    earlier folder there); on any error `out` is left as it was."""
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
