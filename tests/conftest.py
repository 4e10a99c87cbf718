"""Shared fixtures: a small generated dataset and the real meshes beside the repository."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

if os.environ.get("PYTEST_XDIST_WORKER"):
    # One worker per core (pyproject's addopts): torch and numba in each worker, and in every command its
    # tests start, take one thread, set before they start their pools; two workers with a thread per core
    # each slow each other far beyond 2x. tests/test_kernel_threads.py runs the compiled kernels on two.
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[name] = "1"

import pytest  # noqa: E402

from pipe.model import ltv  # noqa: E402
from pipe.synthetic import generate_dataset  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
REAL_MESHES = Path(os.environ.get("PIPE_REAL_MESHES", ROOT.parent / "shared" / "real-meshes"))


HEAVY_MODULES = ("torch", "lightning", "mlflow", "pipe.tracking", "pipe.pipeline", "pipe.predict")
_NOTING_IMPORTS = """\
import runpy, sys
sys.argv = sys.argv[1:]
try:
    runpy.run_path(sys.argv[0], run_name="__main__")
finally:
    print(sorted(m for m in {modules} if m in sys.modules))
"""


def run_noting_imports(script: str, *args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    """Run train.py or predict.py (`script`, from the repository root) in a fresh interpreter; the last line of
    its stdout lists which of `HEAVY_MODULES` it loaded (seconds of imports a refusal should not wait for)."""
    code = _NOTING_IMPORTS.format(modules=HEAVY_MODULES)
    return subprocess.run([sys.executable, "-c", code, str(ROOT / script), *args], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


@pytest.fixture(scope="session", autouse=True)
def mlflow_store(tmp_path_factory) -> str:
    """Every test (and the commands they start) tracks into a temporary SQLite store, never the project's."""
    uri = f"sqlite:///{tmp_path_factory.mktemp('mlflow') / 'mlflow.db'}"
    os.environ["MLFLOW_TRACKING_URI"] = uri
    return uri


@pytest.fixture
def compiled_simulator():
    """The compiled simulator for every batch size: identification runs thousands of small simulations, and
    parts fitted together or alone then take the same arithmetic."""
    previous = ltv.get_backend()
    ltv.set_backend("compiled")
    yield
    ltv.set_backend(previous)


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory) -> Path:
    """Two parts of the synthetic dataset (a plug and a pin), generated once per test session."""
    return generate_dataset(tmp_path_factory.mktemp("data") / "small", seed=0, parts=["dsub9", "taper8"])


@pytest.fixture
def dataset_copy(small_dataset, tmp_path) -> Path:
    """A private copy of the small dataset that a test may break."""
    return Path(shutil.copytree(small_dataset, tmp_path / "ds"))


@pytest.fixture(scope="session")
def real_meshes() -> list[Path]:
    if not REAL_MESHES.is_dir():
        if os.environ.get("CI"):
            pytest.fail(f"the real meshes are missing at {REAL_MESHES} (set PIPE_REAL_MESHES)")
        pytest.skip(f"real meshes not found at {REAL_MESHES}; set PIPE_REAL_MESHES to run these tests")
    return sorted(p for p in REAL_MESHES.iterdir() if p.suffix.lower() in (".stl", ".obj"))


MEANPOOL_ENCODER = '''"""A throwaway encoder plugin: one linear layer per point, mean pooled."""
import torch

from pipe.model.vae import PointCloudVAE


class MeanPoolVAE(PointCloudVAE):
    def __init__(self, width: int = 16, **vae):
        super().__init__(feature_dim=width, **vae)
        self.point = torch.nn.Linear(3, width)

    def features(self, points):
        return torch.relu(self.point(points)).mean(dim=1)
'''

TINY_DOMAIN = ["domain.name=tiny", "domain.train=[dsub9,dsub15]", "domain.val=[vga]", "domain.test=[dsub26]"]


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory) -> Path:
    """Four D-subs: enough for a train / val / test split that trains in seconds."""
    return generate_dataset(tmp_path_factory.mktemp("tiny") / "data", parts=["dsub9", "dsub15", "vga", "dsub26"])


def compose_config(overrides: list[str]):
    from hydra import compose, initialize_config_module

    os.environ.setdefault("PROJECT_ROOT", str(ROOT))
    with initialize_config_module(config_module="pipe.conf", version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


def smoke_config(data: Path, out: Path, *extra: str):
    return compose_config(["experiment=smoke", f"data.dir={data}", f"paths.output_dir={out}", *TINY_DOMAIN, *extra])


@pytest.fixture(scope="session")
def trained_run(tiny_data, tmp_path_factory):
    """One smoke training of the tiny domain, tracked in the session's MLflow store."""
    from pipe.pipeline import run_domain

    return run_domain(smoke_config(tiny_data, tmp_path_factory.mktemp("run")))
