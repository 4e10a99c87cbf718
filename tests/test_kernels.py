"""The numeric libraries' kernels (pipe.kernels): `avx2` sets every library's switch to the AVX2 level before it
loads, so that hosts with other instruction sets compute alike; a library already loaded at another level, or
an environment that sets a switch otherwise, is refused rather than recorded under a level it did not run."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys

import pytest

from pipe import kernels
from pipe.errors import PipeError

needs_avx2 = pytest.mark.skipif(not kernels.has_avx2(), reason="this CPU lacks AVX2 and FMA: kernels=avx2 refused")
AVX2_RECORD = "torch AVX2, numba haswell, openblas Haswell, numpy X86_V3"   # pipe.machine.cpu_kernels at that level


@pytest.fixture
def clean_environment(monkeypatch):
    """No switch of the AVX2 level in the environment and none set by this process; both restored after, the
    environment whole (monkeypatch.delenv does not restore a variable that was absent and then set, and a
    switch left set would run this worker's later subprocesses at the AVX2 level)."""
    saved = dict(os.environ)
    for name in kernels.AVX2_ENVIRONMENT:
        os.environ.pop(name, None)
    monkeypatch.setattr(kernels, "_pinned", None)
    yield
    os.environ.clear()
    os.environ.update(saved)


def python_without_switches(code: str, **extra: str) -> subprocess.CompletedProcess:
    """`code` in a fresh interpreter whose environment sets none of the switches (but `extra`)."""
    env = {k: v for k, v in os.environ.items() if k not in kernels.AVX2_ENVIRONMENT} | extra
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)


@pytest.mark.parametrize(("machine", "flags", "level"), [
    ("x86_64", {"sse2", "avx", "avx2", "fma"}, "avx2"),
    ("x86_64", {"sse2", "avx", "avx2", "fma", "avx512f"}, "avx2"),
    ("x86_64", {"sse2", "avx", "avx2"}, "native"),      # AVX2 without FMA (a few early VIA and Intel parts)
    ("x86_64", {"sse2", "avx"}, "native"),
    ("aarch64", set(), "native"),
])
def test_auto_takes_the_avx2_level_where_the_cpu_has_avx2_and_fma(monkeypatch, machine, flags, level):
    monkeypatch.setattr(kernels.platform, "machine", lambda: machine)
    monkeypatch.setattr(kernels, "cpu_flags", lambda: flags)
    assert kernels.resolve("auto") == level
    assert kernels.resolve("native") == "native"
    if level == "native":
        with pytest.raises(PipeError, match=f"kernels=avx2 needs an x86-64 CPU with AVX2 and FMA; this one "
                                            f"\\({machine}\\) lacks them: use kernels=native"):
            kernels.resolve("avx2")
    else:
        assert kernels.resolve("avx2") == "avx2"


def test_an_unknown_choice_is_refused():
    with pytest.raises(PipeError, match="kernels='avx512' is not one of auto, avx2, native"):
        kernels.resolve("avx512")


@needs_avx2
def test_a_fresh_process_and_its_children_run_every_library_at_the_avx2_level():
    """The libraries' own reports after use_kernels, in the process and in one it starts (the identification's
    workers are such processes)."""
    code = ("from pipe.kernels import use_kernels; use_kernels('avx2')\n"
            "import multiprocessing, torch\n"
            "from pipe.machine import cpu_kernels\n"
            "print(cpu_kernels())\n"
            "if __name__ == '__main__':\n"
            "    with multiprocessing.get_context('spawn').Pool(1) as pool:\n"
            "        print(pool.apply(cpu_kernels))\n")
    result = python_without_switches(code)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-2:] == [AVX2_RECORD, AVX2_RECORD]


@needs_avx2
def test_libraries_loaded_at_another_level_are_refused():
    """torch run at its unvectorised level (torch reads its switch at its first operation), then the switch's
    variable removed: use_kernels sees what torch runs on, not what the environment says now."""
    code = ("import os, torch\n"
            "torch.ones(64).exp().sum()\n"
            "del os.environ['ATEN_CPU_CAPABILITY']\n"
            "from pipe.kernels import use_kernels\n"
            "from pipe.errors import PipeError\n"
            "try:\n"
            "    use_kernels('auto')\n"
            "except PipeError as err:\n"
            "    print(err)\n")
    result = python_without_switches(code, ATEN_CPU_CAPABILITY="default")
    assert result.returncode == 0, result.stderr
    assert "kernels=auto must be set before the numeric libraries load, but this process runs torch DEFAULT" \
        in result.stdout
    assert "give each level a command of its own, or use kernels=native" in result.stdout


@needs_avx2
def test_an_environment_that_sets_a_switch_otherwise_is_refused_or_under_auto_followed(clean_environment, caplog):
    os.environ["OPENBLAS_CORETYPE"] = "SkylakeX"           # restored by clean_environment
    with pytest.raises(PipeError, match="kernels=avx2 sets the AVX2 level, but the environment sets "
                                        "OPENBLAS_CORETYPE=SkylakeX: unset them, or use kernels=native"):
        kernels.use_kernels("avx2")
    kernels.set_from_arguments([])                       # auto: nothing set over the environment's choice
    assert os.environ["OPENBLAS_CORETYPE"] == "SkylakeX" and "ATEN_CPU_CAPABILITY" not in os.environ
    assert kernels.use_kernels("auto") == "native"
    assert "kernels=auto: the environment sets OPENBLAS_CORETYPE=SkylakeX, so the libraries run on their own " \
        "choice (kernels=native)" in caplog.text
    assert "ATEN_CPU_CAPABILITY" not in os.environ


@needs_avx2
@pytest.mark.parametrize(("arguments", "set_here"), [
    ([], True),                                          # auto
    (["domain=pins", "kernels=avx2"], True),
    (["++kernels=avx2"], True),
    (["kernels=native"], False),
    (["kernels=native,avx2"], False),                    # a sweep: each job's use_kernels decides
    (["kernels=avx3"], False),                           # refused by the settings check, with its message
])
def test_the_command_line_sets_the_switches_before_hydra_starts(clean_environment, arguments, set_here):
    kernels.set_from_arguments(arguments)
    assert all(os.environ.get(name) == (value if set_here else None)
               for name, value in kernels.AVX2_ENVIRONMENT.items())


def test_native_after_the_avx2_level_was_set_is_refused(clean_environment, monkeypatch):
    monkeypatch.setattr(kernels, "_pinned", "avx2")
    with pytest.raises(PipeError, match="kernels=native, but this process set its libraries to the AVX2 level"):
        kernels.use_kernels("native")
    monkeypatch.setattr(kernels, "_pinned", None)
    assert kernels.use_kernels("native") == "native" and "NUMBA_CPU_NAME" not in os.environ


@needs_avx2
@pytest.mark.parametrize(("params", "set_here"), [("kernels: native\n", False), ("kernels: auto\nseed: 3\n", True),
                                                  ("seed: 3\n", True), (None, True)])   # None: no such file
def test_a_parameter_file_chooses_the_level_as_dvc_runs_train_py(clean_environment, tmp_path, params,
                                                                  set_here):
    """DVC's stages give `params=params.yaml domain=<name>` and nothing else: the file's kernels= counts."""
    os.environ["PROJECT_ROOT"] = str(tmp_path)             # restored by clean_environment
    if params is not None:
        (tmp_path / "params.yaml").write_text(params)
    kernels.set_from_arguments(["params=params.yaml", "domain=pins", "phase=train"])
    assert (os.environ.get("NUMBA_CPU_NAME") == "haswell") is set_here


def shell_then_python(choice: str, code: str, **extra: str) -> subprocess.CompletedProcess:
    """`eval "$(pipe kernels <choice>)"` in bash, then `code` in a fresh interpreter started by that shell; the
    environment sets none of the switches but `extra`."""
    pipe_kernels = f"{shlex.quote(sys.executable)} -m pipe.cli kernels {choice}"
    script = f'eval "$({pipe_kernels})" && exec {shlex.quote(sys.executable)} -c {shlex.quote(code)}'
    env = {k: v for k, v in os.environ.items() if k not in kernels.AVX2_ENVIRONMENT} | extra
    return subprocess.run(["bash", "-c", script], capture_output=True, text=True, env=env, timeout=300)


def test_pipe_kernels_prints_shell_lines_that_set_or_unset_every_switch():
    switches = "import os, json; print(json.dumps({k: os.environ.get(k) for k in %r}))" % list(kernels.AVX2_ENVIRONMENT)
    if kernels.has_avx2():
        result = shell_then_python("avx2", switches, OPENBLAS_CORETYPE="SkylakeX")
        assert result.returncode == 0, result.stderr
        assert json.loads(result.stdout) == kernels.AVX2_ENVIRONMENT    # quoted as the shell reads them back
    result = shell_then_python("native", switches, **kernels.AVX2_ENVIRONMENT)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout) == dict.fromkeys(kernels.AVX2_ENVIRONMENT)   # each library's own choice
    assert kernels.shell_lines("native").endswith("# pipe kernels: native, each library's own choice")


@needs_avx2
def test_a_command_run_after_pipe_kernels_runs_every_library_at_the_avx2_level():
    """What an experiment script or a batch job gets: the same kernels as train.py's kernels=auto."""
    result = shell_then_python("auto", "import torch\nfrom pipe.machine import cpu_kernels\nprint(cpu_kernels())")
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-1] == AVX2_RECORD


def test_pipe_kernels_refuses_avx2_on_a_cpu_without_it_and_auto_unsets_there(monkeypatch, capsys):
    from pipe.cli import main

    monkeypatch.setattr(kernels.platform, "machine", lambda: "aarch64")
    assert main(["kernels", "avx2"]) == 2
    assert "kernels=avx2 needs an x86-64 CPU with AVX2 and FMA; this one (aarch64) lacks them" in " ".join(
        capsys.readouterr().err.split())
    assert main(["kernels"]) == 0
    assert capsys.readouterr().out.startswith(f"unset {' '.join(kernels.AVX2_ENVIRONMENT)}\n")
