"""Wall time and peak memory of each stage of one domain run (stage 1, stage 2, evaluation), as train.py
runs it (checkpoints, CSV and MLflow logging included; MLflow into a throwaway SQLite store).

Peak memory is the process's peak resident set size during the stage (Linux: VmHWM, reset before each
stage through /proc/self/clear_refs). Run it alone: a second torch process on 2 cores distorts it.

    python benchmarks/training.py domain=conn [encoder=dgcnn] [stages.vae.epochs=50 ...]

With the default force weights ([0, 1000], chosen in every run) each stage runs twice; `stages.vae.force_weight=0`
times one.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def peak_rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmHWM in /proc/self/status (Linux only)")


def reset_peak() -> None:
    Path("/proc/self/clear_refs").write_text("5")


def measured(fn, name: str, record: dict):
    """fn wrapped to record its wall time and the peak memory reached while it ran; a stage run once per
    candidate force weight (the default's two) adds up its times, keeps its highest peak and counts its calls."""
    def wrapper(*args, **kwargs):
        reset_peak()
        start = time.perf_counter()
        out = fn(*args, **kwargs)
        entry = record.setdefault(name, {"seconds": 0.0, "peak_rss_mb": 0, "calls": 0})
        entry["seconds"] = round(entry["seconds"] + time.perf_counter() - start, 2)
        entry["peak_rss_mb"] = max(entry["peak_rss_mb"], round(peak_rss_mb()))
        entry["calls"] += 1
        return out
    return wrapper


def main(overrides: list[str]) -> None:
    os.environ.setdefault("PROJECT_ROOT", str(ROOT))
    from hydra import compose, initialize_config_module

    import pipe.pipeline as pipeline

    record: dict = {}
    pipeline.fit_vae = measured(pipeline.fit_vae, "stage 1 (vae)", record)
    pipeline.fit_head = measured(pipeline.fit_head, "stage 2 (head)", record)
    pipeline.evaluate_methods = measured(pipeline.evaluate_methods, "evaluation", record)
    with tempfile.TemporaryDirectory() as tmp, initialize_config_module("pipe.conf", version_base="1.3"):
        cfg = compose("config", overrides=[f"paths.output_dir={tmp}/run", "trainer.progress_bar=false",
                                           f"mlflow.tracking_uri=sqlite:///{tmp}/mlflow.db", *overrides])
        start = time.perf_counter()
        pipeline.run_domain(cfg)
        record["whole run"] = {"seconds": round(time.perf_counter() - start, 2)}
    print(json.dumps({"overrides": overrides, "threads": __import__("torch").get_num_threads(), **record}, indent=2))


if __name__ == "__main__":
    main(sys.argv[1:])
