"""A shared MLflow tracking server (README, "Scaling out"): `mlflow server` with a database backend and an
artifact root on 127.0.0.1, a training logged to it over HTTP, and its run, metrics and model read back
through the client and predicted with; the server stopped by its process id."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import pytest
from conftest import ROOT, TINY_DOMAIN


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_until_healthy(url: str, server: subprocess.Popen, seconds: float = 120) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        assert server.poll() is None, f"mlflow server exited: {server.stderr.read()[-3000:]}"
        try:
            with urllib.request.urlopen(f"{url}/health", timeout=2) as response:
                if response.status == 200:
                    return
        except OSError:
            time.sleep(0.5)
    raise AssertionError(f"mlflow server at {url} did not answer within {seconds} s")


@pytest.mark.slow
def test_a_training_logs_to_a_tracking_server_and_its_model_reads_back(tiny_data, tmp_path):
    import mlflow.pytorch
    from mlflow.tracking import MlflowClient

    port = free_port()
    url = f"http://127.0.0.1:{port}"
    server = subprocess.Popen(
        [sys.executable, "-m", "mlflow", "server", "--host", "127.0.0.1", "--port", str(port), "--workers", "1",
         "--backend-store-uri", f"sqlite:///{tmp_path / 'server.db'}",
         "--artifacts-destination", str(tmp_path / "artifacts")],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        wait_until_healthy(url, server)
        env = {**os.environ, "MLFLOW_TRACKING_URI": url}
        result = subprocess.run(
            [sys.executable, str(ROOT / "train.py"), "experiment=smoke", f"data.dir={tiny_data}",
             f"hydra.run.dir={tmp_path / 'run'}", "mlflow.experiment=server", *TINY_DOMAIN],
            capture_output=True, text=True, timeout=600, cwd=ROOT, env=env)
        assert result.returncode == 0, result.stderr[-3000:]
        run_id = (tmp_path / "run" / "mlflow_run_id").read_text().strip()

        client = MlflowClient(tracking_uri=url)
        run = client.get_run(run_id)
        assert run.info.status == "FINISHED" and run.data.tags["domain"] == "tiny"
        written = json.loads((tmp_path / "run" / "metrics.json").read_text())["test"]["fit_F"]
        assert run.data.metrics["test/pipe/fit_F"] == pytest.approx(written)
        assert {a.path for a in client.list_artifacts(run_id)} >= {"config.yaml", "metrics.json", "report"}
        assert any((tmp_path / "artifacts").rglob("MLmodel"))          # stored under the server's artifact root
        versions = client.search_model_versions("name='pipe-tiny'")
        assert [v.run_id for v in versions] == [run_id]
        previous = os.environ["MLFLOW_TRACKING_URI"]     # set_tracking_uri sets the variable too: restore both
        mlflow.set_tracking_uri(url)
        try:
            model = mlflow.pytorch.load_model(f"runs:/{run_id}/model", map_location="cpu")
        finally:
            mlflow.set_tracking_uri(previous)
            os.environ["MLFLOW_TRACKING_URI"] = previous
        assert type(model).__name__ == "PIPEModel" and list(model.dynamics.parameter_names) == ["a0", "a1", "a2", "b0"]

        mesh = tiny_data / "parts" / "dsub26" / "mesh.stl"
        predicted = subprocess.run(
            [sys.executable, str(ROOT / "predict.py"), f"mesh={mesh}", "run=models:/pipe-tiny/latest",
             f"hydra.run.dir={tmp_path / 'predict'}"], capture_output=True, text=True, timeout=600, cwd=ROOT, env=env)
        assert predicted.returncode == 0, predicted.stderr[-3000:]
        assert (tmp_path / "predict" / "force.csv").is_file()
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()
    assert server.returncode is not None
    with pytest.raises(OSError):
        urllib.request.urlopen(f"{url}/health", timeout=2)
