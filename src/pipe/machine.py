"""What machine a run ran on: results reproduce to the digit where the numeric kernels' instruction sets and the
library builds are alike, not across others (the same code rounds differently on them; `pipe.kernels` sets
every x86-64 host with AVX2 to the same kernels), so every run records its CPU, the instruction sets its
numeric kernels run on, and the library versions."""

from __future__ import annotations

import os
import platform
import sys
from importlib import metadata
from pathlib import Path

LIBRARIES = ("torch", "numba", "numpy", "scipy")   # scipy: the identification's L-BFGS-B


def cpu_model() -> str:
    """The CPU's model name (Linux's /proc/cpuinfo), else what `platform` knows of the processor."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text(errors="replace").splitlines():
            if line.startswith("model name") and ":" in line:
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine() or "unknown"


def loaded_kernels() -> dict[str, str]:
    """The instruction sets of the numeric libraries this process has loaded, by library (`torch`, `numba`,
    `openblas`, `numpy`); a library not loaded is left out, and none is loaded here."""
    found = {}
    if "torch" in sys.modules:
        found["torch"] = sys.modules["torch"].backends.cpu.get_cpu_capability()
    if "numba" in sys.modules:
        from llvmlite import binding

        found["numba"] = sys.modules["numba"].config.CPU_NAME or binding.get_host_cpu_name()
    if "numpy" in sys.modules:
        from threadpoolctl import threadpool_info

        openblas = sorted({lib["architecture"] for lib in threadpool_info()
                           if lib["internal_api"] == "openblas" and lib.get("architecture")})
        if openblas:
            found["openblas"] = "/".join(openblas)
        simd = sys.modules["numpy"].show_config(mode="dicts").get("SIMD Extensions", {})   # in rising order
        found["numpy"] = (simd.get("found") or simd.get("baseline") or ["unknown"])[-1]
    return found


def cpu_kernels() -> str:
    """The instruction sets the numeric kernels run on here: torch's dispatch level (AVX2, AVX512, ...;
    ATEN_CPU_CAPABILITY lowers it), the CPU numba compiles its loops for (NUMBA_CPU_NAME, else the host's), the
    kernels numpy's and scipy's OpenBLAS chose (Haswell, SkylakeX, ...; OPENBLAS_CORETYPE sets them) and numpy's
    own highest SIMD dispatch target (X86_V3, X86_V4, ...; NPY_DISABLE_CPU_FEATURES turns targets off). One CPU
    model name can hide two of them: two "AMD EPYC" hosts, one with AVX-512, gave other figures from the same
    code (2026-12-06), and torch's, numba's and OpenBLAS's each move an identification on one host, numpy's did
    not (docs/experiments.md, "The oracle under other kernels on one host", "OpenBLAS's kernels, MKL's, and 96
    starts" and "numpy's own SIMD dispatch")."""
    import numba  # noqa: F401
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401  (loads scipy's own OpenBLAS beside numpy's, for threadpoolctl to find)
    import torch  # noqa: F401

    return ", ".join(f"{library} {level}" for library, level in loaded_kernels().items())


def libc() -> str:
    """The C library (name and version) whose libm the compiled loops call for exp and log: two versions may
    round a last bit otherwise."""
    name, version = platform.libc_ver()
    return f"{name} {version}" if name else "unknown"


def _version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def arithmetic() -> dict[str, str]:
    """What can make the same code round differently on two machines, beside its inputs: the kernels'
    instruction sets (`cpu_kernels`), the C library's version (`libc`) and the numeric libraries' versions. A
    stored fit is reused only where they are the same (`pipe.evaluation.fit_cache`)."""
    return {"kernels": cpu_kernels(), "libc": libc(), **{name: _version(name) for name in LIBRARIES}}


def machine_info() -> dict[str, str]:
    """CPU model, logical CPUs, operating system, Python, the kernels' instruction sets and the numeric
    libraries' versions (`arithmetic`), as strings."""
    return {"cpu": cpu_model(), "cpus": str(os.cpu_count()), "system": platform.platform(),
            "python": platform.python_version(), **arithmetic()}
