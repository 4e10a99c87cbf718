"""What machine a run ran on: results reproduce to the digit on one machine, not across machines (the same
code rounds differently on another CPU or library build), so every run records its CPU and library versions."""

from __future__ import annotations

import os
import platform
from importlib import metadata
from pathlib import Path

LIBRARIES = ("torch", "numba", "numpy")


def cpu_model() -> str:
    """The CPU's model name (Linux's /proc/cpuinfo), else what `platform` knows of the processor."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text(errors="replace").splitlines():
            if line.startswith("model name") and ":" in line:
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine() or "unknown"


def _version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def machine_info() -> dict[str, str]:
    """CPU model, logical CPUs, operating system, Python and the numeric libraries' versions, as strings."""
    return {"cpu": cpu_model(), "cpus": str(os.cpu_count()), "system": platform.platform(),
            "python": platform.python_version(), **{name: _version(name) for name in LIBRARIES}}
