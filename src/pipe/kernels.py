"""Which instruction sets the numeric libraries' kernels run on: every library at the AVX2 level, so that any
x86-64 host with AVX2 and FMA computes the same figures (`avx2`), or each library's own choice for this CPU
(`native`); `auto` takes `avx2` where the CPU has it.

torch, numba, numpy, the OpenBLAS that numpy and scipy bundle, MKL and oneDNN each choose their kernels by the
CPU when they load, and the last bits of their rounding choose among the identification's many close minima
and move a trained model: the same code gave conn's seed-0 oracle 88.27 on an AMD host with AVX2 and 88.18 on
one with AVX-512, and other gpr, `nearest` and PIPE figures. Each library has a documented switch, read once
when it loads; with all of them at the AVX2 level an AVX-512 host repeats the AVX2 host's main command to the
digit, at the same speed (docs/experiments.md, "The same kernels on two hosts"). The switches must be set
before the libraries load: train.py and predict.py read `kernels=` from their command line before Hydra starts
(`set_from_arguments`; Hydra's launchers and MLflow load numpy and torch before a job's config is read), and
the processes they start (a multirun's jobs, the identification's workers, DDP's) inherit them. The job then
checks its config's choice against what its libraries run on (`use_kernels`) and refuses a mismatch rather
than record figures under a level they were not computed at. A caller of the API sets the level itself,
`use_kernels` before torch, numba and numpy load; any other command (an experiment script, a benchmark, a batch
job whose environment is not exported) runs at a level set by the shell before it, `eval "$(pipe kernels)"`
(`shell_lines`).
"""

from __future__ import annotations

import logging
import os
import platform
import shlex
from pathlib import Path

import yaml

from pipe.errors import PipeError
from pipe.machine import loaded_kernels

CHOICES = ("auto", "avx2", "native")

AVX2_ENVIRONMENT = {
    "ATEN_CPU_CAPABILITY": "avx2",       # torch's dispatch level
    "NUMBA_CPU_NAME": "haswell",         # the CPU numba compiles its loops for (the first with AVX2 and FMA)
    "OPENBLAS_CORETYPE": "Haswell",      # the kernels of numpy's and scipy's OpenBLAS
    # numpy's own dispatch targets above AVX2, by the names of numpy 2.4 and of numpy 1.x to 2.3 (a name the
    # installed numpy does not know is ignored)
    "NPY_DISABLE_CPU_FEATURES": " ".join((
        "X86_V4", "AVX512F", "AVX512CD", "AVX512_KNL", "AVX512_KNM", "AVX512_SKX", "AVX512_CLX", "AVX512_CNL",
        "AVX512_ICL", "AVX512_SPR", "AVX512FP16")),
    "MKL_ENABLE_INSTRUCTIONS": "AVX2",   # the highest instruction set of torch's MKL (not MKL_CBWR: any of its
                                         # branches, AUTO too, moved training here against the AVX2 host's figures)
    "ONEDNN_MAX_CPU_ISA": "AVX2",        # the same for torch's oneDNN (mkldnn)
}
_AVX2_LEVELS = {"torch": "AVX2", "numba": "haswell", "openblas": "Haswell"}   # as pipe.machine reads them
_NEEDED_FLAGS = ("avx2", "fma")
log = logging.getLogger(__name__)
_pinned: str | None = None    # "avx2" once this module set the switches in this process


def cpu_flags() -> set[str] | None:
    """The CPU's feature flags as Linux's /proc/cpuinfo lists them; None where there is no such file."""
    cpuinfo = Path("/proc/cpuinfo")
    if not cpuinfo.is_file():
        return None
    for line in cpuinfo.read_text(errors="replace").splitlines():
        if line.startswith("flags") and ":" in line:
            return set(line.split(":", 1)[1].split())
    return set()


def has_avx2() -> bool:
    """Whether this CPU runs the AVX2 level's kernels: x86-64 with AVX2 and FMA."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    flags = cpu_flags()
    return flags is None or all(flag in flags for flag in _NEEDED_FLAGS)   # no cpuinfo: the libraries will tell


def resolve(choice: str) -> str:
    """`avx2` or `native` for a choice of CHOICES (`auto`: avx2 where the CPU has it)."""
    if choice not in CHOICES:
        raise PipeError(f"kernels={choice!r} is not one of {', '.join(CHOICES)}")
    if choice == "auto":
        return "avx2" if has_avx2() else "native"
    if choice == "avx2" and not has_avx2():
        raise PipeError(f"kernels=avx2 needs an x86-64 CPU with AVX2 and FMA; this one ({platform.machine()}) "
                        "lacks them: use kernels=native (its figures are this machine's own)")
    return choice


def loaded_mismatches() -> list[str]:
    """What the already loaded libraries run on where it is not the AVX2 level, e.g. 'torch AVX512'."""
    found = []
    for library, level in loaded_kernels().items():
        above = ("512" in level or level == "X86_V4") if library == "numpy" else level != _AVX2_LEVELS[library]
        if above:
            found.append(f"{library} {level}")
    return found


def _clashes() -> list[str]:
    """The AVX2 level's switches that the environment sets otherwise, as NAME=value."""
    return [f"{name}={os.environ[name]}" for name, value in AVX2_ENVIRONMENT.items()
            if os.environ.get(name, value) != value]


def _choice_in_params(path: str) -> str | None:
    """The `kernels` of a parameter file (`params=`, relative to the project root as train.py reads it)."""
    try:
        values = yaml.safe_load((Path(os.environ.get("PROJECT_ROOT", ".")) / path).read_text())
    except (OSError, yaml.YAMLError):
        return None               # train.py refuses the file with its own message
    return values.get("kernels") if isinstance(values, dict) else None


def set_from_arguments(arguments: list[str]) -> None:
    """Set the AVX2 level's switches for this process when its command line's `kernels=` (Hydra's override
    syntax; else that of the parameter file `params=` names; else `auto`) resolves to it and the environment
    does not set them otherwise. Anything else is left to `use_kernels`, which refuses it with a message once
    the config is read."""
    global _pinned
    given = dict(argument.lstrip("+").partition("=")[::2] for argument in arguments)
    choice = given.get("kernels") or (given.get("params") and _choice_in_params(given["params"])) or "auto"
    try:
        level = resolve(choice)
    except PipeError:
        return
    if level == "avx2" and not _clashes():
        os.environ.update(AVX2_ENVIRONMENT)
        _pinned = level


def use_kernels(choice: str) -> str:
    """Set the numeric libraries' kernels for this process and the processes it starts; returns the level
    (`avx2` or `native`). Call it before torch, numba and numpy load: a library loaded before at another level
    is refused, as is an environment that sets one of the switches otherwise (under `auto` that environment's
    choice is taken, with a warning)."""
    global _pinned
    level = resolve(choice)
    if level == "native":
        if _pinned == "avx2":
            raise PipeError("kernels=native, but this process set its libraries to the AVX2 level when it started "
                            "(kernels= is read from the command line then, auto when not given): give kernels=native "
                            "on the command line, in a command of its own")
        return level
    if clashes := _clashes():
        if choice == "auto":     # the environment chose: its figures are recorded under the kernels they ran on
            log.warning("kernels=auto: the environment sets %s, so the libraries run on their own choice "
                        "(kernels=native); unset it for the AVX2 level", ", ".join(clashes))
            return "native"
        raise PipeError(f"kernels={choice} sets the AVX2 level, but the environment sets {', '.join(clashes)}: "
                        "unset them, or use kernels=native to run on the environment's choice")
    if mismatches := loaded_mismatches():
        raise PipeError(f"kernels={choice} must be set before the numeric libraries load, but this process runs "
                        f"{', '.join(mismatches)} already (loaded by the caller, or by an earlier job of the same "
                        "multirun at another level): give each level a command of its own, or use kernels=native")
    os.environ.update(AVX2_ENVIRONMENT)
    _pinned = level
    return level


def shell_lines(choice: str) -> str:
    """POSIX shell lines that set (`avx2`) or unset (`native`) the switches for the commands a shell runs after
    them: `eval "$(pipe kernels auto)"` before a script that loads the libraries itself. A comment line names the
    level."""
    level = resolve(choice)
    if level == "native":
        lines = [f"unset {' '.join(AVX2_ENVIRONMENT)}", "# pipe kernels: native, each library's own choice"]
    else:
        lines = [f"export {name}={shlex.quote(value)}" for name, value in AVX2_ENVIRONMENT.items()]
        lines.append("# pipe kernels: avx2, torch, numba, numpy, OpenBLAS, MKL and oneDNN at the AVX2 level")
    return "\n".join(lines)
