"""What machine a run ran on: results reproduce to the digit on one machine, not across machines (the same
code rounds differently on another CPU or library build), so every run records its CPU, the instruction sets
its numeric kernels run on, and the library versions."""

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


def cpu_kernels() -> str:
    """The instruction sets the numeric kernels run on here: torch's dispatch level (AVX2, AVX512, ...;
    ATEN_CPU_CAPABILITY lowers it) and the CPU numba compiles its loops for (NUMBA_CPU_NAME, else the host's).
    One CPU model name can hide two of them: two "AMD EPYC" hosts, one with AVX-512, gave other
    figures from the same code (2026-12-06)."""
    import numba
    import torch
    from llvmlite import binding

    compiled_for = numba.config.CPU_NAME or binding.get_host_cpu_name()
    return f"torch {torch.backends.cpu.get_cpu_capability()}, numba {compiled_for}"


def _version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def machine_info() -> dict[str, str]:
    """CPU model, logical CPUs, the kernels' instruction sets, operating system, Python and the numeric
    libraries' versions, as strings."""
    return {"cpu": cpu_model(), "cpus": str(os.cpu_count()), "kernels": cpu_kernels(), "system": platform.platform(),
            "python": platform.python_version(), **{name: _version(name) for name in LIBRARIES}}
