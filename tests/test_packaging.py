"""Plugins that install: a third-party package registers an encoder and a baseline through the `pipe.plugins`
entry points and trains with no PYTHONPATH and no hydra.searchpath; and pipe itself, installed without
a checkout (non-editable), trains with its built-in plugins and configs."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from conftest import MEANPOOL_ENCODER, ROOT, TINY_DOMAIN

PLUGIN_FILES = {
    "pyproject.toml": '''
        [build-system]
        requires = ["setuptools>=68"]
        build-backend = "setuptools.build_meta"

        [project]
        name = "my-pipe-plugin"
        version = "0.0.1"

        [project.entry-points."pipe.plugins"]
        my_plugin = "my_pipe_plugin"

        [tool.setuptools]
        packages = ["my_pipe_plugin", "my_pipe_plugin.conf"]

        [tool.setuptools.package-data]
        "my_pipe_plugin.conf" = ["*/*.yaml"]
    ''',
    "my_pipe_plugin/__init__.py": '''
        """A throwaway pipe plugin: the meanpool encoder and the zero baseline."""
        from my_pipe_plugin import baselines  # noqa: F401  (registers the baseline)
    ''',
    "my_pipe_plugin/encoder.py": MEANPOOL_ENCODER,
    "my_pipe_plugin/baselines.py": '''
        import numpy as np
        from pipe.evaluation.methods import METHODS, Method

        @METHODS.register
        class Zero(Method):
            """Predicts no force at all."""

            name = "zero"

            def predict(self, ctx, part):
                return [np.zeros_like(p.force) for p in part.profiles]
    ''',
    "my_pipe_plugin/conf/__init__.py": "",
    "my_pipe_plugin/conf/encoder/meanpool.yaml": '''
        _target_: my_pipe_plugin.encoder.MeanPoolVAE
        latent_dim: 32
        width: 8
    ''',
}


def pip(*args: str) -> None:
    """pip of the test environment, offline: the build uses the environment's own setuptools."""
    result = subprocess.run([sys.executable, "-m", "pip", "--disable-pip-version-check", "-q", *args],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]


def run(args: list[str], cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    environment = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PROJECT_ROOT")}
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=600, cwd=cwd,
                          env=environment | (env or {}))


@pytest.mark.slow
def test_an_installed_plugin_package_trains_with_its_encoder_and_baseline(tiny_data, tmp_path):
    package = tmp_path / "my-pipe-plugin"
    for name, text in PLUGIN_FILES.items():
        (package / name).parent.mkdir(parents=True, exist_ok=True)
        (package / name).write_text(textwrap.dedent(text).lstrip())
    pip("install", "--no-deps", "--no-build-isolation", str(package))
    try:
        listed = run([str(ROOT / "train.py"), "--help"], cwd=tmp_path)
        assert "encoder: dgcnn, meanpool, pointnet" in listed.stdout, listed.stderr[-3000:]
        result = run([str(ROOT / "train.py"), "experiment=smoke", "encoder=meanpool", "evaluation.baselines=[zero]",
                      f"data.dir={tiny_data}", f"hydra.run.dir={tmp_path / 'run'}", "mlflow.registered_model=null",
                      *TINY_DOMAIN], cwd=tmp_path)
        assert result.returncode == 0, result.stderr[-3000:]
        assert "MeanPoolVAE" in result.stdout and "zero" in result.stdout and "dsub26" in result.stdout
    finally:
        pip("uninstall", "-y", "my-pipe-plugin")
    gone = run([str(ROOT / "train.py"), "experiment=smoke", "encoder=meanpool"], cwd=tmp_path)
    assert gone.returncode != 0 and "meanpool" in gone.stderr


@pytest.mark.slow
def test_pipe_installed_without_a_checkout_trains_with_its_builtin_plugins(tiny_data, tmp_path):
    source, site = tmp_path / "source", tmp_path / "site"
    source.mkdir()   # a copy: the checkout's build/ folder of earlier builds could leak stale files
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    for name in ("src", "plugins", "conf"):
        shutil.copytree(ROOT / name, source / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    pip("install", "--no-deps", "--no-build-isolation", "--target", str(site), str(source))
    for shipped in ("pipe/plugins/encoder/pointnet.py", "pipe/plugins/model/mds2.py", "pipe/conf/config.yaml",
                    "pipe/conf/encoder/dgcnn.yaml", "pipe/conf/hydra/launcher/slurm.yaml",
                    "hydra_plugins/pipe_searchpath/__init__.py"):
        assert (site / shipped).is_file(), shipped
    work = tmp_path / "work"      # no checkout anywhere near: the installed package alone
    work.mkdir()
    env = {"PYTHONPATH": str(site)}
    where = run(["-c", "import pipe, pipe.plugins; print(pipe.__file__, pipe.plugins.__file__)"], cwd=work, env=env)
    assert where.stdout.split() == [str(site / "pipe/__init__.py"), str(site / "pipe/plugins/__init__.py")]
    result = run(["-c", "from pipe.app import train; train()", "experiment=smoke", f"data.dir={tiny_data}",
                  "mlflow.registered_model=null", *TINY_DOMAIN], cwd=work, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "dsub26" in result.stdout and (work / "outputs" / "tiny").is_dir()
