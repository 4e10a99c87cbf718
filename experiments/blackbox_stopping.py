"""Why the blackbox baseline can fall below `mean` (issue 9: "a baseline below `mean` is investigated"): for
finished run folders, the blackbox is fitted as the evaluation fits it, and at each of its validation checks
(every 100 steps) its validation FIT(F), which chooses the step it keeps, is recorded with its test FIT(F),
which only reports. It reads the code through `--inputs` (one of `code_inputs`; default: what PIPE's head
reads), not through the evaluation's choice among them. One JSON line per run: the checks' steps, both curves,
the kept step and the best test step. Results: docs/experiments.md. Usage (one thread, as the results were
measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/blackbox_stopping.py OUT.jsonl runs/pins/seed_0 ...
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from common import load_encoder, load_run

from pipe.evaluation import methods
from pipe.evaluation.context import EvalContext
from pipe.evaluation.evaluate import score
from pipe.pipeline import build_model, latent_codes


def curves(run: Path, inputs: str | None) -> dict:
    cfg, data, (encoder, head, dynamics) = load_run(run)
    load_encoder(encoder, run)
    train, val, test = data.splits["train"], data.splits["val"], data.splits["test"]
    model = build_model(cfg, data, (encoder, head, dynamics))
    latents, logvars, index = latent_codes(model, data)
    ctx = EvalContext(model, latents, index, train, 1.0 / cfg.data.rate_hz, cfg.seed, dict(cfg.evaluation), val=val,
                      logvars=logvars)
    validation, tested = [], []
    checked = methods.validation_nmse

    def recording(method, context):               # at every check: the test FIT beside the validation score
        nmse = checked(method, context)
        validation.append(100 * (1 - nmse))
        tested.append(float(np.mean([score(method, context, part, method.predict(context, part))["fit_F"]
                                     for part in test])))
        return nmse

    methods.validation_nmse = recording
    try:
        blackbox = methods.METHODS["blackbox"]()
        blackbox.inputs = inputs or next(iter(methods.code_inputs(ctx)))
        if blackbox.inputs not in methods.code_inputs(ctx):
            raise SystemExit(f"{run}: --inputs {inputs}: its code offers {', '.join(methods.code_inputs(ctx))}")
        blackbox.fit_inputs(ctx)
    finally:
        methods.validation_nmse = checked
    steps = [min(k * blackbox.CHECK_EVERY, cfg.evaluation.blackbox_steps) for k in range(1, len(validation) + 1)]
    return {"run": str(run), "inputs": blackbox.inputs, "steps": steps, "val_fit": validation, "test_fit": tested,
            "kept_step": blackbox.best_step, "best_test_step": steps[int(np.argmax(tested))]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", help="JSON lines file to append to")
    ap.add_argument("runs", nargs="+", help="finished seed folders of train.py")
    ap.add_argument("--inputs", choices=["code+sections", "code", "sections"],
                    help="the part of the code it reads (default: what PIPE's head reads)")
    args = ap.parse_args()
    for run in args.runs:
        row = curves(Path(run), args.inputs)
        print(json.dumps({k: (np.round(v, 2).tolist() if isinstance(v, list) else v) for k, v in row.items()}),
              flush=True)
        with open(args.out, "a") as handle:
            handle.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
