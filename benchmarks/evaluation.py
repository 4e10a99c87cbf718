"""Wall time and results of each evaluated method, on the trained model of an earlier run (`phase=evaluate`:
its checkpoints are only read, the evaluation's files go to a temporary folder).

First every method's system identifications are fitted at once, as the evaluation does (the oracles'
starts on the test parts, gpr's on the training parts, in `evaluation.identification.workers` processes);
then each method is fitted and scored on its own, in the order of `evaluation.baselines`, with those fits.
Run it alone: a second torch process on 2 cores distorts it.

    python benchmarks/evaluation.py runs/conn/seed_0 [evaluation.identification.ridge=0 ...]
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHOWN = ("fit_F", "static_rms", "id_loss", "id_evals", "id_steps")


def main(run: str, overrides: list[str]) -> None:
    os.environ.setdefault("PROJECT_ROOT", str(ROOT))
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    import pipe.pipeline as pipeline
    from pipe.evaluation.evaluate import available_methods, identify_for

    evaluate, record = pipeline.evaluate_methods, {}

    def one_at_a_time(ctx, test, names):
        start = time.perf_counter()         # every method's identifications at once, as the evaluation starts
        identify_for(ctx, available_methods(ctx, test, names).values(), test)
        record["identification (all methods' starts)"] = {"seconds": round(time.perf_counter() - start, 2)}
        results = {}
        for name in names:
            start = time.perf_counter()
            results |= evaluate(ctx, test, [name])
            if name in results:
                shown = {k: round(v, 3) for k, v in results[name].domain.items() if k in SHOWN}
                record[name] = {"seconds": round(time.perf_counter() - start, 2), **shown}
        return results

    pipeline.evaluate_methods = one_at_a_time
    saved = OmegaConf.load(Path(run) / "config.yaml")
    with tempfile.TemporaryDirectory() as tmp, initialize_config_module("pipe.conf", version_base="1.3"):
        weights = OmegaConf.to_container(saved.stages.vae).get("force_weight", 0.0)   # one, or the candidates
        cfg = compose("config", overrides=[f"domain={saved.domain.name}", f"seed={saved.seed}", "phase=evaluate",
                                           f"stages.vae.force_weight={weights}",
                                           f"paths.output_dir={tmp}/run", f"resume={Path(run).resolve()}",
                                           "trainer.progress_bar=false", "mlflow.enabled=false", *overrides])
        start = time.perf_counter()
        pipeline.run_domain(cfg)
        record["whole evaluation"] = {"seconds": round(sum(r["seconds"] for r in record.values()), 2)}
        record["whole run"] = {"seconds": round(time.perf_counter() - start, 2)}
    print(json.dumps({"run": run, "overrides": overrides, **record}, indent=2))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
