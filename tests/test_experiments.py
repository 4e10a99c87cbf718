"""The experiment scripts of issue 9 (experiments/): they rebuild a finished run exactly, so that a variant's
row differs from the run's own result by the variant alone, and their summary computes what it says."""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import runpy
import statistics
import subprocess
import sys

import pytest
from conftest import ROOT, smoke_config

EXPERIMENTS = ROOT / "experiments"


def run_script(*args: str) -> str:
    """What a script that trains or scores prints, run as `python <script>` in its own process (its threads,
    seeds and simulator backend stay its own)."""
    env = {**os.environ, "PROJECT_ROOT": str(ROOT)}
    done = subprocess.run([sys.executable, *args], cwd=EXPERIMENTS, env=env, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def run_here(script: str, *args: str) -> subprocess.CompletedProcess:
    """`python <script> <args>` run in this process, for what finishes before any work (a table of rows, a
    refusal): as its own process would run it (argv, the experiments folder as cwd and first on the import path,
    the message of a SystemExit on stderr with status 1) without importing the whole stack again (7 s each).
    The methods a script registers (gpr_cv.py's) are taken out of the registry again."""
    from pipe.evaluation.methods import METHODS

    stdout, stderr = io.StringIO(), io.StringIO()
    saved_argv, saved_path, saved_root = sys.argv, list(sys.path), os.environ.get("PROJECT_ROOT")
    saved_methods = dict(METHODS._classes)
    sys.argv, sys.path[:0] = [script, *args], [str(EXPERIMENTS)]
    status = 0
    try:
        with contextlib.chdir(EXPERIMENTS), contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            try:
                runpy.run_path(str(EXPERIMENTS / script), run_name="__main__")
            except SystemExit as stop:
                if isinstance(stop.code, int):
                    status = stop.code
                elif stop.code is not None:        # SystemExit("message"), as Python prints it
                    print(stop.code, file=sys.stderr)
                    status = 1
    finally:
        sys.argv, sys.path[:] = saved_argv, saved_path
        METHODS._classes.clear()
        METHODS._classes.update(saved_methods)
        if saved_root is None:
            os.environ.pop("PROJECT_ROOT", None)
        else:
            os.environ["PROJECT_ROOT"] = saved_root
    return subprocess.CompletedProcess([script, *args], status, stdout.getvalue(), stderr.getvalue())


@pytest.fixture(scope="module")
def unsliced_run(tiny_data, tmp_path_factory):
    """A smoke run trained without the mesh's slices (code.slices=false), for the scripts' `slices` variants,
    which add them to a run's code."""
    from pipe.pipeline import run_domain

    return run_domain(smoke_config(tiny_data, tmp_path_factory.mktemp("unsliced"), "mlflow.enabled=false",
                                   "code.slices=false"))


def printed_here(script: str, *args: str) -> str:
    """What `script` prints where it does no work but read rows (run_here), checking that it succeeded."""
    done = run_here(script, *args)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def printed_table(script: str, rows: list[dict], tmp_path, *args: str) -> str:
    """What `script` prints for `rows` written to a JSON lines file (its --table, or summarise.py's output)."""
    rows_file = tmp_path / "rows.jsonl"
    rows_file.write_text("".join(json.dumps(row) + "\n" for row in rows))
    return printed_here(script, str(rows_file), *args)


@pytest.mark.slow
def test_stage2_variants_default_reproduces_the_runs_own_result(trained_run, tmp_path):
    rows_file = tmp_path / "rows.jsonl"
    run_script("stage2_variants.py", str(rows_file), str(trained_run.run_dir), "--fits", str(tmp_path / "fits"),
               "--variants", "default,epochs=1,select=fit,loss=mse,loss=mse+epochs=1,hidden=16,local=3,pretrain=20,"
               "mu=0.01,default")
    default, one_epoch, by_fit, mse, combined, *others, tuned, again = (
        json.loads(line) for line in rows_file.read_text().splitlines())
    assert (default["variant"], one_epoch["variant"]) == ("default", "epochs=1")
    # the head trained again from the run's own initial weights: the run's PIPE and nearest to the digit
    assert default["test"]["pipe"] == pytest.approx(trained_run.results["pipe"].domain["fit_F"], abs=1e-9)
    assert default["test"]["nearest"] == pytest.approx(trained_run.results["nearest"].domain["fit_F"], abs=1e-9)
    assert set(default) >= {"train", "val", "test"} and set(default["train"]) == {"pipe"}
    # one epoch instead of the smoke profile's two is another head
    assert one_epoch["test"]["pipe"] != pytest.approx(default["test"]["pipe"], abs=1e-6)
    # select=fit keeps the epoch of the highest validation FIT and restores that very head
    assert by_fit["kept_epoch"] in (0, 1)
    assert by_fit["val"]["pipe"] == pytest.approx(by_fit["kept_val_fit"], abs=1e-9)
    assert by_fit["val"]["pipe"] >= default["val"]["pipe"] - 1e-9
    # the paper's pooled loss trains another head than the run's own (the default, nmse)
    assert mse["variant"] == "loss=mse" and mse["test"]["pipe"] != pytest.approx(default["test"]["pipe"], abs=1e-6)
    # variants combine: the pooled loss for one epoch is neither of its parts alone
    assert combined["variant"] == "loss=mse+epochs=1"
    assert combined["test"]["pipe"] != pytest.approx(mse["test"]["pipe"], abs=1e-6)
    assert combined["test"]["pipe"] != pytest.approx(one_epoch["test"]["pipe"], abs=1e-6)
    # a head of another size, and one pre-trained on the identified profiles (stored in --fits), is another head
    assert [row["variant"] for row in others] == ["hidden=16", "local=3", "pretrain=20"]
    assert all(row["test"]["pipe"] != pytest.approx(default["test"]["pipe"], abs=1e-6) for row in others)
    assert len(list((tmp_path / "fits").rglob("*.pt"))) == 2       # the two training parts, dsub9 and dsub15
    # mu=L fine-tunes the encoder's last part: other codes, another result; the next variant gets the run's own
    # encoder back
    assert tuned["variant"] == "mu=0.01" and tuned["test"]["pipe"] != pytest.approx(default["test"]["pipe"], abs=1e-6)
    assert again["test"] == pytest.approx(default["test"], abs=1e-9)


@pytest.mark.parametrize("script, spec, message", [
    ("stage2_variants.py", "bogus", "unknown variant"), ("stage2_variants.py", "loss=mae", "unknown variant"),
    ("stage2_variants.py", "noise=0.3+select=loss", "unknown variant"), ("stage2_variants.py", "loss", "unknown"),
    ("stage2_variants.py", "mu=0.001+select=fit", "combine with neither"),
    ("stage2_variants.py", "clip=0", "run it with part_cv.py"), ("stage2_variants.py", "sections=0", "part_cv.py"),
    ("stage2_variants.py", "slices", "part_cv.py"), ("stage2_variants.py", "align", "part_cv.py"),
    ("stage2_variants.py", "leadin", "part_cv.py"), ("part_cv.py", "leadin+hidden=16", "combine with neither"),
    ("stage2_variants.py", "corners", "part_cv.py"), ("part_cv.py", "corners+mu=0.01", "combine with neither"),
    ("part_cv.py", "align+pretrain=5", "unaligned"), ("part_cv.py", "slices+hidden=16", "combine with neither"),
    ("part_cv.py", "slices+sections=0", "combine with neither"),
    ("part_cv.py", "sections=-1", "at least 0"),
    ("part_cv.py", "select=fit", "unsupported variant"), ("part_cv.py", "loss=mse+std", "unsupported variant")])
def test_experiment_scripts_refuse_a_variant_they_cannot_run_before_any_run(script, spec, message, tmp_path):
    done = run_here(script, str(tmp_path / "rows.jsonl"), "no/such/run", "--variants", f"default,{spec}")
    assert done.returncode != 0 and message in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "rows.jsonl").exists()


@pytest.mark.parametrize("script", ["part_cv.py", "stage2_variants.py"])
def test_experiment_scripts_name_a_run_folder_that_is_not_one(script, tmp_path):
    done = run_here(script, str(tmp_path / "rows.jsonl"), "no/such/run", "--variants", "default")
    assert done.returncode != 0 and "Traceback" not in done.stderr
    assert "no/such/run: not a trained folder of train.py (no config.yaml in it)" in done.stderr
    assert not (tmp_path / "rows.jsonl").exists()


def test_clipped_codes_stay_within_the_rows_range_widened_by_the_margin():
    import torch
    sys.path.insert(0, str(ROOT / "experiments"))
    from stage2_variants import clipped

    codes = torch.tensor([[0.0, 10.0], [2.0, 20.0], [5.0, 0.0], [-3.0, 15.0]])
    # rows 0 and 1 span [0, 2] and [10, 20]; a margin of 0.5 widens them to [-1, 3] and [5, 25]
    assert torch.equal(clipped(codes, [0, 1], 0.0), torch.tensor([[0.0, 10.0], [2.0, 20.0], [2.0, 10.0],
                                                                  [0.0, 15.0]]))
    assert torch.equal(clipped(codes, [0, 1], 0.5), torch.tensor([[0.0, 10.0], [2.0, 20.0], [3.0, 5.0],
                                                                  [-1.0, 15.0]]))


def test_pretraining_brings_the_heads_profiles_to_the_targets():
    """The pre-training of `pretrain=S` fits the head's log profiles to targets another head of the same
    structure produces, which it can reach exactly."""
    import torch
    sys.path.insert(0, str(ROOT / "experiments"))
    from profile_pretraining import ProfileTargets, pretrain_head

    from pipe.model.pipe_model import PIPEModel
    from pipe.plugins.head.gaussian import GaussianHead
    from pipe.plugins.model.mds2 import MDS2

    torch.manual_seed(0)
    target_model, model = (PIPEModel(None, GaussianHead(8, 4, hidden=16), MDS2(), 5.0, 20.0) for _ in range(2))
    z, depth_max = torch.randn(6, 8), torch.linspace(8.0, 20.0, 6)
    depth = torch.linspace(0.0, 1.0, 21)[None] * depth_max[:, None]
    with torch.no_grad():
        targets = ProfileTargets(z, depth_max, depth, target_model.profile(z, depth_max)(depth).log())
        before = (model.profile(z, depth_max)(depth).log() - targets.log_theta).pow(2).mean().item()
    after = pretrain_head(model, targets, 300)
    with torch.no_grad():
        assert (model.profile(z, depth_max)(depth).log() - targets.log_theta).pow(2).mean().item() == \
            pytest.approx(after, rel=0.5)
    assert after < 0.05 * before


def test_summarise_tables_each_domain_and_variant_over_the_seeds(tmp_path):
    rows = [{"run": f"runs/curve/pins/train_20/seed_{k}", "variant": "default",
             "val": {"pipe": 70.0 + k}, "test": {"pipe": 60.0 + 2 * k, "nearest": 55.0 + k}} for k in range(3)]
    rows.append({"run": "runs/conn/seed_0", "variant": "noise=0.3", "train": {"pipe": 90.0}, "val": {"pipe": 75.0},
                 "test": {"pipe": 68.0, "nearest": 70.0}})
    printed = printed_table("summarise.py", rows, tmp_path)
    pins = statistics.stdev([60.0, 62.0, 64.0])            # 2.00; val's spread 1.00, PIPE - nearest 1, 2, 3
    assert f"| default | 3 | 71.00 ± 1.00 | 62.00 ± {pins:.2f} | 56.00 ± 1.00 | 6.00 ± 1.00 |" in printed
    assert "pins/train_20" in printed and "\nconn\n" in printed
    # a domain whose rows all hold the training parts' FIT gets that column too
    assert "| noise=0.3 | 1 | 90.00 ± 0.00 | 75.00 ± 0.00 | 68.00 ± 0.00 | 70.00 ± 0.00 | -2.00 ± 0.00 |" in printed
    assert "| variant | seeds | val: PIPE |" in printed and "| variant | seeds | train: PIPE | val: PIPE |" in printed


def write_curve_run(folder, family: str, count: int, seed: int, objective: float, pipe: float, nearest: float) -> None:
    """A learning-curve seed folder as far as force_selection.py reads it: stage 2's best validation loss and
    the held-out FIT(F) of PIPE and `nearest`."""
    run = folder / family / f"train_{count}" / f"seed_{seed}"
    run.mkdir(parents=True)
    (run / "training.json").write_text(json.dumps({"seconds": {}, "objective": objective}))
    (run / "metrics.json").write_text(json.dumps({"test": {"fit_F": pipe},
                                                  "baselines": {"nearest": {"fit_F": nearest}}}))


@pytest.mark.parametrize("candidates, message", [
    (["0=runs/a"], "at least two candidates"), (["0=runs/a", "runs/b"], "at least two candidates"),
    (["0=no/such/folder", "1000=nor/this"], "no domain has a finished run")])
def test_force_selection_refuses_candidates_it_cannot_compare(candidates, message, tmp_path):
    done = run_here("force_selection.py", str(tmp_path / "out.json"), *candidates)
    assert done.returncode == 2 and message in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "out.json").exists()


def test_force_selection_chooses_by_the_validation_loss_per_seed_and_per_size(tmp_path):
    plain, small, force = tmp_path / "plain", tmp_path / "small", tmp_path / "force"
    for seed, (objective, pipe) in enumerate([(0.30, 60.0), (0.20, 62.0), (0.40, 64.0)]):
        write_curve_run(plain, "rect", 50, seed, objective, pipe, 50.0 + seed)
    for seed, (objective, pipe) in enumerate([(0.25, 78.0), (0.30, 76.0), (0.30, 80.0)]):
        write_curve_run(force, "rect", 50, seed, objective, pipe, 58.0 + 2 * seed)
    for seed in range(3):       # a size whose default runs are in another folder of the candidate
        write_curve_run(small, "pins", 5, seed, 0.5, 40.0 + seed, 30.0)
        write_curve_run(force, "pins", 5, seed, 0.6 if seed else 0.4, 20.0, 30.0)
    write_curve_run(plain, "pins", 10, 0, 0.1, 70.0, 60.0)     # a size without every seed: left out
    oracle = tmp_path / "oracle" / "rect" / "train_100"
    oracle.mkdir(parents=True)
    (oracle / "results.json").write_text(json.dumps({"methods": {"oracle": {"fit_F": {"mean": 88.0, "std": 1.0,
                                                                                      "n": 3}}}}))
    out, png = tmp_path / "selection.json", tmp_path / "curve.png"
    printed = run_script("force_selection.py", str(out), f"0={small},{plain}", f"1000={force}", "--plot", str(png),
                         "--oracle", str(tmp_path / "oracle"))
    assert png.read_bytes().startswith(b"\x89PNG")
    rows = {row["domain"]: row for row in json.loads(out.read_text())}
    assert list(rows) == ["pins/train_5", "rect/train_50"]
    rect = rows["rect/train_50"]
    # per seed: 0.25 < 0.30, 0.20 < 0.30, 0.30 < 0.40; per size: mean 0.2833 < 0.30
    assert rect["per seed"]["chosen"] == ["1000", "0", "1000"] and rect["per seed"]["pipe"] == [78.0, 62.0, 80.0]
    assert rect["per seed"]["nearest"] == [58.0, 51.0, 62.0]
    assert rect["per size"]["chosen"] == ["1000"] * 3 and rect["per size"]["pipe"] == [78.0, 76.0, 80.0]
    # against the default's 62.00 ± 2.00: 73.33 ± 9.87 is a tie, 78.00 ± 2.00 better
    assert rect["per seed"]["verdict"] == "tie" and rect["per size"]["verdict"] == "better"
    assert rows["pins/train_5"]["per seed"]["chosen"] == ["1000", "0", "0"]
    assert rows["pins/train_5"]["per size"]["chosen"] == ["0"] * 3
    spread = statistics.stdev([78.0, 62.0, 80.0])
    assert (f"| rect/train_50 | 0.3000 | 0.2833 | 62.00 ± 2.00 | 78.00 ± 2.00 | 1000, 0, 1000 | "
            f"73.33 ± {spread:.2f} (tie) |") in printed
    sys.path.insert(0, str(ROOT / "experiments"))
    from force_selection import read_oracles, selection_curve

    from pipe.evaluation.spread import Spread

    curve = selection_curve(list(rows.values()), read_oracles(tmp_path / "oracle"))
    assert curve["rect"]["pipe"][50].mean == 78.0 and curve["rect"]["pipe, force_weight=0"][50].mean == 62.0
    assert curve["rect"]["nearest"][50].mean == 60.0 and curve["rect"]["oracle"] == {50: Spread(88.0, 1.0, 3)}
    assert curve["pins"]["pipe"][5].mean == 41.0 and "oracle" not in curve["pins"]


@pytest.mark.slow
def test_part_cv_holds_out_each_non_test_part_in_turn(unsliced_run, tmp_path):
    rows_file = tmp_path / "rows.jsonl"
    # ema=2 differs only if the averaged head is the one kept (before KeptAverage, the default's to the digit)
    variants = ("default", "loss=mse", "mu=0.01", "ema=2", "sections=0", "sections=3", "slices", "align", "leadin",
                "corners", "sections=1")
    run_script("part_cv.py", str(rows_file), str(unsliced_run.run_dir), "--variants", ",".join(variants))
    rows = [json.loads(line) for line in rows_file.read_text().splitlines()]
    # every training and validation part of the tiny domain held out once per variant; the test part never
    assert sorted((row["held_out"], row["variant"]) for row in rows) == sorted(
        (part, variant) for part in ("dsub9", "dsub15", "vga") for variant in variants)
    by_case = {(row["held_out"], row["variant"]): row["fit"] for row in rows}
    parts = ("dsub9", "dsub15", "vga")
    assert all(by_case[(part, "default")] != pytest.approx(by_case[(part, other)], abs=1e-6)
               for part in parts for other in variants[1:-1])
    # the cross-section weighed by 1 is the default's input, the same head: the same FIT to the digit
    assert all(by_case[(part, "sections=1")] == pytest.approx(by_case[(part, "default")], abs=1e-9) for part in parts)


def test_part_cv_align_trains_and_scores_every_part_of_the_fold_aligned():
    import numpy as np
    sys.path.insert(0, str(ROOT / "experiments"))
    from part_cv import fold_parts

    from pipe.data.alignment import align_final_depth
    from pipe.data.prepared import PartData
    from pipe.data.preprocess import Profile

    def part(name: str, ends: list[float]) -> PartData:          # trials whose deepest points differ
        profiles = [Profile(np.arange(3) * 0.01, np.array([0.0, end / 2, end]), np.zeros(3), None) for end in ends]
        return PartData(name, cloud=None, profiles=profiles, static_curves=[None] * len(ends))

    pool = [part("a", [10.0, 11.0, 12.5]), part("b", [4.0, 6.0]), part("c", [7.0, 9.0, 8.0])]
    aligned = {p.name: align_final_depth(p) for p in pool}
    train, held_out = pool[:2], pool[2]
    assert fold_parts(train, held_out, {}, aligned) == [*train, held_out]          # the default: as recorded
    parts = fold_parts(train, held_out, {"align": 0.0}, aligned)
    assert [p.name for p in parts] == ["a", "b", "c"] and parts[-1] is aligned["c"]
    assert [[float(t.depth.max()) for t in p.profiles] for p in parts] == [[11.0] * 3, [5.0] * 2, [8.0] * 3]


def test_part_cv_lead_in_code_is_the_log_standardised_over_the_folds_training_parts():
    import math

    import torch
    sys.path.insert(0, str(ROOT / "experiments"))
    from part_cv import lead_in_code

    # training pins of 0.5, 1 and 2 mm: logs -a, 0, a (a = log 2), their mean 0 and spread a; a held-out 4 mm is 2a
    pins = torch.tensor([[0.5], [1.0], [2.0], [4.0]], dtype=torch.float64).log()
    assert lead_in_code(pins, [0, 1, 2]).squeeze(1).tolist() == pytest.approx([-1.0, 0.0, 1.0, 2.0], abs=1e-6)
    # plugs all measure the grid's first depth: a spread of 0, raised to the floor of 0.05; a pin beside them
    plugs = torch.tensor([[0.01], [0.01], [0.01], [0.01], [0.5]], dtype=torch.float64).log()
    assert lead_in_code(plugs, [0, 1, 2]).squeeze(1).tolist() == pytest.approx(
        [0.0, 0.0, 0.0, 0.0, math.log(50) / 0.05], rel=1e-6)


def test_scaled_sections_multiply_the_cross_section_alone():
    import torch
    sys.path.insert(0, str(ROOT / "experiments"))
    from part_cv import scaled_sections, section_weights

    from pipe.model.sections import SectionCode

    clouds = torch.rand(3, 64, 3, generator=torch.Generator().manual_seed(0)) * torch.tensor([2.0, 3.0, 10.0])
    sections = SectionCode.fitted(clouds)
    assert torch.allclose(scaled_sections(sections, 2.5)(clouds), 2.5 * sections(clouds))
    assert torch.equal(sections.std, SectionCode.fitted(clouds).std)          # the original is left alone
    assert torch.equal(section_weights(2, 5, 0.5), torch.tensor([1.0, 1.0, 0.5, 0.5, 0.5]))


def test_part_cv_table_averages_the_held_out_parts_per_seed(tmp_path):
    fits = {("runs/pins/seed_0", "a"): (50.0, 60.0), ("runs/pins/seed_0", "b"): (70.0, 40.0),
            ("runs/pins/seed_1", "a"): (30.0, 90.0), ("runs/pins/seed_1", "b"): (80.0, 10.0)}
    rows = [{"run": run, "variant": variant, "held_out": part, "fit": fit}
            for (run, part), pair in fits.items() for variant, fit in zip(("default", "loss=nmse"), pair)]
    for row in rows[1::2]:                   # nmse's rows carry nearest's FIT, 10 points below PIPE's
        row["nearest"] = row["fit"] - 10.0
    printed = printed_table("part_cv.py", rows, tmp_path, "--table")
    # default: seed means 60 and 55, median of 50, 70, 30, 80 = 60; nmse: seed means 50 and 50, median 50,
    # above default in 2 of the 4 held-out cases (60 > 50, 90 > 30)
    assert f"| pins | default | 2 | 57.50 ± {statistics.stdev([60.0, 55.0]):.2f} | 60.00 |  |  |" in printed
    assert "| pins | loss=nmse | 2 | 50.00 ± 0.00 | 50.00 | 2 of 4 | 40.00 ± 0.00 |" in printed


def test_part_cv_table_gives_the_blackbox_a_column_where_the_rows_have_it(tmp_path):
    rows = [{"run": f"runs/dsub/seed_{seed}", "variant": "default", "held_out": part, "fit": fit,
             "nearest": fit - 10.0, "blackbox": box}
            for seed, part, fit, box in [(0, "a", 70.0, 10.0), (0, "b", 50.0, 30.0), (1, "a", 80.0, -50.0),
                                         (1, "b", 60.0, 10.0)]]
    printed = printed_table("part_cv.py", rows, tmp_path, "--table")
    # PIPE: seed means 60 and 70; nearest 10 below; blackbox: seed means 20 and -20
    assert "| domain | variant | seeds | FIT(F) [%] | median | above default | nearest | blackbox |" in printed
    assert (f"| dsub | default | 2 | 65.00 ± {statistics.stdev([60.0, 70.0]):.2f} | 65.00 |  | "
            f"55.00 ± {statistics.stdev([50.0, 60.0]):.2f} | 0.00 ± {statistics.stdev([20.0, -20.0]):.2f} |") in printed
    for row in rows:                         # --blackbox-clip: the clipped blackbox 5 above the plain one
        row["blackbox_clip"] = row["blackbox"] + 5.0
    printed = printed_table("part_cv.py", rows, tmp_path, "--table")
    assert "| nearest | blackbox | blackbox_clip |" in printed
    assert f"| 0.00 ± {statistics.stdev([20.0, -20.0]):.2f} | 5.00 ± {statistics.stdev([20.0, -20.0]):.2f} |" in printed


def test_part_cv_clipping_switches_the_clip_on_in_a_copy_of_the_config():
    from omegaconf import OmegaConf
    sys.path.insert(0, str(ROOT / "experiments"))
    from part_cv import clipping

    cfg = OmegaConf.create({"evaluation": {"blackbox_steps": 2000}})
    OmegaConf.set_struct(cfg, True)          # as a run's saved config is read back
    assert clipping(cfg).evaluation == {"blackbox_steps": 2000, "blackbox_clip": True}
    assert "blackbox_clip" not in cfg.evaluation


@pytest.mark.slow
def test_part_cv_blackbox_scores_each_fold_beside_pipe_and_nearest(unsliced_run, tmp_path):
    rows_file = tmp_path / "rows.jsonl"
    run_script("part_cv.py", str(rows_file), str(unsliced_run.run_dir), "--variants", "default", "--blackbox",
               "--blackbox-clip")
    rows = [json.loads(line) for line in rows_file.read_text().splitlines()]
    assert sorted(row["held_out"] for row in rows) == ["dsub15", "dsub9", "vga"]
    assert all(math.isfinite(row["blackbox"]) and row["blackbox"] != row["nearest"] for row in rows)
    # the same network's start and draws, clipped: two training parts per fold span too little for every
    # held-out part to lie inside their range, so clipping moves at least one fold
    assert all(math.isfinite(row["blackbox_clip"]) for row in rows)
    assert any(row["blackbox_clip"] != pytest.approx(row["blackbox"], abs=1e-6) for row in rows)


@pytest.mark.slow
def test_oracle_starts_reproduce_the_runs_oracle_with_its_own_number_of_starts(trained_run, tmp_path):
    rows_file = tmp_path / "rows.jsonl"
    from omegaconf import OmegaConf

    restarts = OmegaConf.load(trained_run.run_dir / "config.yaml").evaluation.identification.restarts
    run_script("oracle_starts.py", str(rows_file), str(trained_run.run_dir), "--starts", str(restarts + 1))
    rows = [json.loads(line) for line in rows_file.read_text().splitlines()]
    assert [row["starts"] for row in rows] == list(range(1, restarts + 2))
    # the first starts are the evaluation's own: with as many, the run's reported oracle to the digit
    own = rows[restarts - 1]
    assert own["fit_F"] == pytest.approx(trained_run.results["oracle"].domain["fit_F"], abs=1e-9)
    # the best of more starts is never a higher objective
    for part in own["parts"]:
        objectives = [row["parts"][part]["objective"] for row in rows]
        assert all(later <= earlier for earlier, later in zip(objectives, objectives[1:]))


def screening_paths() -> list[dict]:
    """Three starts of one path each, hand-made, screened at 10 and 20 evaluations: start 0 ends early in a
    shallow basin, start 1 starts slowly into the deepest, start 2 leads at both budgets into a middle one."""
    return [{"start": 0, "via_mse": False, "objective": -1.0, "evaluations": 15, "fit_F": 80.0, "scores": [-0.9, -1.0]},
            {"start": 1, "via_mse": False, "objective": -3.0, "evaluations": 100, "fit_F": 90.0,
             "scores": [-0.5, -0.8]},
            {"start": 2, "via_mse": False, "objective": -2.0, "evaluations": 50, "fit_F": 85.0, "scores": [-1.5, -1.8]}]


def test_oracle_screening_searches_keep_and_count_as_worked_out_by_hand():
    sys.path.insert(0, str(ROOT / "experiments"))
    from oracle_screening import paths_of, plain, screened

    paths = paths_of({"paths": screening_paths()})
    # the first start alone, and all three (15 + 100 + 50 evaluations)
    assert plain(paths, 1) == (paths[0], 15) and plain(paths, 3) == (paths[1], 165)
    # 10 evaluations each, then the leader there (start 2) fitted again to its end
    assert screened(paths, [10, 20], 3, 10, 1) == (paths[2], 30 + 50)
    # at 20, start 0 has ended (15) and keeps its fit; start 2 still leads and is fitted again
    assert screened(paths, [10, 20], 3, 20, 1) == (paths[2], 15 + 20 + 20 + 50)
    # two continued at 10: start 2 and start 0 (-0.9 before start 1's -0.5), both fitted again
    assert screened(paths, [10, 20], 3, 10, 2) == (paths[2], 30 + 50 + 15)
    # all continued: the plain search's fit, at the screen's extra cost
    assert screened(paths, [10, 20], 3, 10, 3) == (paths[1], 30 + 165)
    # the screen over the first two starts only
    assert screened(paths, [10, 20], 2, 10, 1) == (paths[0], 20 + 15)


def test_oracle_screening_tables_read_each_search_and_where_the_best_basin_ranks(tmp_path):
    row = {"parts_of": "dsub", "seed": 0, "part": "dsub26", "starts": 3, "budgets": [10, 20],
           "paths": screening_paths()}
    printed = printed_table("oracle_screening.py", [row], tmp_path, "--table", "--continued", "1", "3")
    # fewer starts than the default's 12: costs over all three starts' 165 evaluations
    label = "| dsub: 1 parts (seed 0) |"
    assert f"{label} 1 starts | 80.00 | 0 of 1 | 0.09 |" in printed
    assert f"{label} 3 starts | 90.00 | 1 of 1 | 1.00 |" in printed
    assert f"{label} 3 screened at 10, best 1 continued | 85.00 | 0 of 1 | {80 / 165:.2f} |" in printed
    assert f"{label} 3 screened at 20, best 3 continued | 90.00 | 1 of 1 | {205 / 165:.2f} |" in printed
    # the deepest basin (start 1's) ranks last of the three paths at both budgets
    ranks = printed_table("oracle_screening.py", [row], tmp_path, "--ranks").splitlines()
    assert ranks[2] == "| dsub (seed 0) | dsub26 | 1 of 3 | 1 | 3 | 3 |"


def test_oracle_screening_sets_rows_of_other_overrides_apart_and_costs_them_over_the_defaults(tmp_path):
    """The same part fitted again under an override (a stricter stopping rule, say: start 0 now ends in the
    deepest basin after 40 evaluations): its searches are a set of their own, their costs over the default's
    three starts (165 evaluations); a part the default rows lack is costed over its own."""
    default = {"parts_of": "dsub", "seed": 0, "part": "dsub26", "starts": 3, "budgets": [10, 20],
               "paths": screening_paths()}
    stricter = {**default, "overrides": ["evaluation.identification.tolerance=1e-6"],
                "paths": [{**screening_paths()[0], "objective": -3.5, "evaluations": 40, "fit_F": 92.0}]
                + screening_paths()[1:]}
    alone = {**stricter, "part": "other"}
    printed = printed_table("oracle_screening.py", [default, stricter], tmp_path, "--table", "--continued", "1")
    assert "| dsub: 1 parts (seed 0) | 3 starts | 90.00 | 1 of 1 | 1.00 |" in printed
    label = "| dsub: 1 parts (seed 0, evaluation.identification.tolerance=1e-6) |"
    assert f"{label} 1 starts | 92.00 | 1 of 1 | {40 / 165:.2f} |" in printed
    assert f"{label} 3 starts | 92.00 | 1 of 1 | {190 / 165:.2f} |" in printed
    printed = printed_table("oracle_screening.py", [default, alone], tmp_path, "--table", "--continued", "1")
    assert "| dsub: 1 parts (seed 0, evaluation.identification.tolerance=1e-6) | 3 starts | 92.00 | 1 of 1 | 1.00 |" \
        in printed


def test_oracle_screening_refuses_a_run_without_parts_to_identify(tmp_path):
    done = run_here("oracle_screening.py", str(tmp_path / "rows.jsonl"), "--starts", "4")
    assert done.returncode == 1 and "give --domain (a paper domain) or --family" in done.stderr
    assert not (tmp_path / "rows.jsonl").exists()


@pytest.mark.slow
def test_oracle_screening_traces_the_oracles_own_fits(tmp_path):
    """dsub's one test part from two starts: the first start's kept path is the evaluation's oracle of one
    start to the digit; a direct path's screening scores never rise with the budget (a path fitted on the
    pooled MSE first is scored on nmse at its best MSE so far, which may), and a path that ended before a
    budget scores its final objective there."""
    rows_file = tmp_path / "rows.jsonl"
    data = f"data.dir={tmp_path / 'data'}"
    run_script("oracle_screening.py", str(rows_file), "--domain", "dsub", "--starts", "2", "--override", data)
    row, = [json.loads(line) for line in rows_file.read_text().splitlines()]
    assert row["part"] == "dsub26" and [p["start"] for p in row["paths"]] == [0, 0, 1, 1]
    assert [p["via_mse"] for p in row["paths"]] == [False, True, False, True]
    for path in row["paths"]:
        if not path["via_mse"]:
            assert all(later <= earlier for earlier, later in zip(path["scores"], path["scores"][1:]))
        for budget, score in zip(row["budgets"], path["scores"]):
            if path["evaluations"] <= budget:
                assert score == path["objective"]
    sys.path.insert(0, str(ROOT / "experiments"))
    from common import oracle_context
    from oracle_screening import paths_of, plain
    from twin_oracle import paper_config

    from pipe.evaluation.evaluate import evaluate_methods

    _, test, ctx = oracle_context(paper_config("dsub", 0, ["threads=1", data, "evaluation.identification.restarts=1"]))
    oracle = evaluate_methods(ctx, test, ["oracle"])["oracle"].per_part["dsub26"]
    kept, _ = plain(paths_of(row), 1)
    assert kept.fit_F == pytest.approx(oracle["fit_F"], abs=1e-9)
    assert kept.evaluations == oracle["id_evals"]


def test_gpr_targets_perturbations_move_the_neutral_start_alone_each_by_a_draw_of_its_own():
    import torch
    from conftest import compose_config

    from pipe.evaluation import identification
    from pipe.evaluation.methods import METHODS
    from pipe.pipeline import build_components

    registered = list(METHODS)
    sys.path.insert(0, str(ROOT / "experiments"))
    from gpr_targets import NEUTRAL_START, perturbed_starts

    assert list(METHODS) == registered     # its gpr variants register when it runs: test_registry counts them

    head = build_components(compose_config([]))[1]

    def values(start_head, number: int):
        return torch.cat([p.detach().flatten() for p in start_head(head, "dsub9", 0, number).parameters()])

    starts = []
    for perturbation in (0, 1, 2):
        with perturbed_starts(1e-6, perturbation):
            starts.append(values(identification.start_head, 0))
            # a random start stays as it was
            assert torch.equal(values(identification.start_head, 1), values(NEUTRAL_START, 1))
    assert identification.start_head is NEUTRAL_START          # restored on leaving
    assert torch.equal(starts[0], torch.zeros_like(starts[0]))
    for moved in starts[1:]:
        assert 0 < moved.abs().max() < 1e-5
    assert not torch.equal(starts[1], starts[2])    # each perturbation its own draw (a bug once drew one for all)


@pytest.mark.slow    # identifies the tiny run's training parts from four starts: about 3 min here
def test_gpr_targets_neutral_start_is_the_runs_gpr_and_a_perturbed_start_moves_the_targets(trained_run, tmp_path):
    """Perturbation 0 is the evaluation's own gpr to the digit (PIPE and `nearest` beside it too); a start moved by
    0 is the same fit, and so is the consensus of identical targets; a start moved by 0.3 moves the targets."""
    fits = str(tmp_path / "fits")
    rows_file, moved_file = tmp_path / "rows.jsonl", tmp_path / "moved.jsonl"
    run_script("gpr_targets.py", str(rows_file), str(trained_run.run_dir), "--perturbations", "1", "--eps", "0",
               "--fits", fits)
    reference, neutral, unmoved, consensus = [json.loads(line) for line in rows_file.read_text().splitlines()]
    for method, row in (("pipe", reference), ("nearest", reference), ("gpr", neutral)):
        assert row[method] == pytest.approx(trained_run.results[method].domain["fit_F"], abs=1e-9), method
    assert unmoved["targets"] == neutral["targets"] and unmoved["gpr"] == neutral["gpr"]
    assert unmoved["gpr_1se"] == neutral["gpr_1se"] and math.isfinite(neutral["gpr_1se"])
    assert consensus["gpr"] == pytest.approx(neutral["gpr"], abs=1e-6)
    run_script("gpr_targets.py", str(moved_file), str(trained_run.run_dir), "--perturbations", "2", "--eps", "0.3",
               "--best-of", "1", "--fits", fits)
    _, again, *moved, _, best_first, best_second = [json.loads(line) for line in moved_file.read_text().splitlines()]
    assert again["targets"] == neutral["targets"]          # the neutral start's fits, read from the cache
    assert all(row["targets"] != neutral["targets"] for row in moved) and moved[0]["targets"] != moved[1]["targets"]
    # a group of one draw is that draw's gpr
    assert (best_first["draws"], best_second["draws"]) == ([1], [2])
    assert best_first["gpr"] == pytest.approx(moved[0]["gpr"], abs=1e-6)
    assert best_second["gpr"] == pytest.approx(moved[1]["gpr"], abs=1e-6)
    table = printed_here("gpr_targets.py", str(moved_file), "--table")
    assert f"| {neutral['gpr']:.2f} ± 0.00 |" in table


def test_oracle_starts_table_counts_the_cases_already_at_the_best_objective(tmp_path):
    objectives = {("runs/dsub/seed_0", 1): -1.0, ("runs/dsub/seed_0", 2): -2.0,
                  ("runs/dsub/seed_1", 1): -3.0, ("runs/dsub/seed_1", 2): -3.0}
    fits = {("runs/dsub/seed_0", 1): 80.0, ("runs/dsub/seed_0", 2): 84.0,
            ("runs/dsub/seed_1", 1): 86.0, ("runs/dsub/seed_1", 2): 86.0}
    rows = [{"run": run, "target": "force", "starts": k, "fit_F": fits[(run, k)],
             "parts": {"dsub26": {"objective": objective, "fit_F": fits[(run, k)]}}}
            for (run, k), objective in objectives.items()]
    printed = printed_table("oracle_starts.py", rows, tmp_path, "--table")
    # one start: seeds at 80 and 86, only seed 1 already at its best objective; two: 84 and 86, both
    spread_one, spread_two = statistics.stdev([80.0, 86.0]), statistics.stdev([84.0, 86.0])
    assert (f"| dsub | force | 83.00 ± {spread_one:.2f} (50 %) | 85.00 ± {spread_two:.2f} (100 %) |"
            in printed)


def test_parameter_codes_are_the_generators_parameters_standardised_over_the_training_parts():
    import torch
    sys.path.insert(0, str(ROOT / "experiments"))
    from parameter_codes import parameter_codes, shape_parameters

    from pipe.synthetic.catalogue import CATALOGUE

    dowel6 = CATALOGUE["dowel6"]        # 6 mm, 24 mm long, inserted 12 mm, the standard's 0.15 d lead-in
    assert shape_parameters(dowel6) == pytest.approx({
        "log diameter": math.log(6.0), "log length": math.log(24.0), "log insertion depth": math.log(12.0),
        "log lead-in": math.log(0.9), "taper": 0.0})
    # dsub9 and dsub15 (training) differ in width, contacts and body width; vga in contacts and pitch from dsub9
    parts = [CATALOGUE[name] for name in ("dsub9", "dsub15", "vga")]
    geometry, physics = (parameter_codes(parts, 2, kind, 32) for kind in ("geometry", "physics"))
    # over two training parts every varied parameter standardises to -1/sqrt(2) and +1/sqrt(2); what is the
    # same on both (height, rows, pitch, detents, detent strength ...) is dropped, the rest of the code is 0;
    # vga has dsub9's width
    half = 1 / math.sqrt(2)
    assert geometry.shape == (3, 32) and torch.allclose(geometry[:2, :3].abs(), torch.full((2, 3), half))
    assert torch.equal(geometry[:, 3:], torch.zeros(3, 29))
    assert torch.equal(physics, geometry)        # the catalogue's D-subs have one detent strength
    widths = [math.log(p.width) for p in parts]
    assert geometry[2, 0].item() == pytest.approx((widths[2] - (widths[0] + widths[1]) / 2)
                                                  / (abs(widths[1] - widths[0]) / math.sqrt(2)), rel=1e-6)
    assert geometry[2, 0].item() == pytest.approx(geometry[0, 0].item())


def test_parameter_codes_physics_adds_the_detent_strength_no_mesh_shows():
    import torch
    sys.path.insert(0, str(ROOT / "experiments"))
    from parameter_codes import parameter_codes

    from pipe.synthetic.families import family_parts

    parts = list(family_parts("rect", 6).values())
    geometry, physics = (parameter_codes(parts, 5, kind, 32) for kind in ("geometry", "physics"))
    varied = int((geometry.abs().sum(0) > 0).sum())
    assert torch.equal(physics[:, :varied], geometry[:, :varied])
    strengths = torch.tensor([p.detent_strength for p in parts], dtype=torch.float64)
    expected = (strengths - strengths[:5].mean()) / strengths[:5].std()
    assert torch.allclose(physics[:, varied].double(), expected, atol=1e-6)


def test_principal_codes_are_the_training_parts_whitened_principal_components():
    """Against scikit-learn's PCA with whitening (each component over its standard deviation, n - 1), up to
    each component's sign; with fewer training parts than the width, the components they do not span are 0."""
    import numpy as np
    import torch
    from sklearn.decomposition import PCA
    sys.path.insert(0, str(ROOT / "experiments"))
    from parameter_codes import principal_codes

    features = torch.randn(30, 12, generator=torch.Generator().manual_seed(0)) * torch.linspace(5.0, 0.1, 12)
    codes = principal_codes(features, 20, 8).double().numpy()
    reference = PCA(n_components=8, whiten=True).fit(features[:20].numpy()).transform(features.numpy())
    signs = np.sign((codes[:, :8] * reference).sum(0))
    np.testing.assert_allclose(codes[:, :8] * signs, reference, atol=1e-4)
    np.testing.assert_allclose(codes[:20].std(0, ddof=1), 1.0, atol=1e-5)

    few = principal_codes(features, 4, 8)      # 4 training parts span 3 directions about their mean
    assert torch.count_nonzero(few[:, 3:]) == 0 and torch.all(few[:4, :3].std(0) > 0.5)


@pytest.mark.slow
def test_parameter_codes_on_the_encoders_codes_reproduce_the_runs_own_result(unsliced_run, tmp_path):
    trained_run = unsliced_run
    rows_file = tmp_path / "rows.jsonl"
    run_script("parameter_codes.py", str(rows_file), str(trained_run.run_dir), "--codes",
               "codes,geometry,features,codes+slices")
    codes, geometry, features, sliced = (json.loads(line) for line in rows_file.read_text().splitlines())
    assert [row["variant"] for row in (codes, geometry, features, sliced)] == [
        "codes", "geometry", "features", "codes+slices"]
    assert math.isfinite(features["test"]["pipe"]) and features["test"]["pipe"] != codes["test"]["pipe"]
    assert math.isfinite(sliced["test"]["pipe"]) and sliced["test"]["pipe"] != codes["test"]["pipe"]
    assert codes["test"]["pipe"] == pytest.approx(trained_run.results["pipe"].domain["fit_F"], abs=1e-9)
    # each test part's FIT too, whose mean over the parts is the domain's
    assert statistics.fmean(codes["test_parts"]["pipe"].values()) == pytest.approx(codes["test"]["pipe"], abs=1e-9)
    assert codes["test"]["nearest"] == pytest.approx(trained_run.results["nearest"].domain["fit_F"], abs=1e-9)
    assert geometry["test"]["pipe"] != pytest.approx(codes["test"]["pipe"], abs=1e-6)


@pytest.mark.slow
def test_parameter_codes_trains_a_head_with_the_corners_after_the_encoders_code(trained_run, tmp_path):
    rows_file = tmp_path / "rows.jsonl"
    run_script("parameter_codes.py", str(rows_file), str(trained_run.run_dir), "--codes", "codes,codes+corners")
    codes, cornered = (json.loads(line) for line in rows_file.read_text().splitlines())
    assert cornered["variant"] == "codes+corners" and math.isfinite(cornered["test"]["nearest"])
    # the tiny domain's D-subs have round pins and rounded shells: no corners, so only the fresh head differs
    assert math.isfinite(cornered["test"]["pipe"]) and cornered["test"]["pipe"] != codes["test"]["pipe"]


@pytest.mark.slow
@pytest.mark.parametrize("script, option, code, message", [
    ("parameter_codes.py", "--codes", "codes+sections", "already ends with the cross-section"),
    ("parameter_codes.py", "--codes", "codes+slices", "already ends with the mesh's slices"),
    ("part_cv.py", "--variants", "slices", "already ends with the mesh's slices"),
    ("part_cv.py", "--variants", "sections=0", "run it on a run trained with code.slices=false")])
def test_scripts_refuse_sections_or_slices_variants_the_runs_code_does_not_fit(trained_run, tmp_path, script,
                                                                                option, code, message):
    done = subprocess.run([sys.executable, script, str(tmp_path / "rows.jsonl"), str(trained_run.run_dir),
                           option, code], cwd=ROOT / "experiments", env={**os.environ, "PROJECT_ROOT": str(ROOT)},
                          capture_output=True, text=True, timeout=600)
    assert done.returncode != 0 and message in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "rows.jsonl").exists()


@pytest.mark.slow
def test_blackbox_stopping_records_the_checks_of_one_input_and_keeps_the_best_validation_step(trained_run,
                                                                                           tmp_path):
    rows_file = tmp_path / "rows.jsonl"
    run_script("blackbox_stopping.py", str(rows_file), str(trained_run.run_dir), "--inputs", "code")
    row = json.loads(rows_file.read_text())
    assert row["inputs"] == "code"
    assert len(row["steps"]) == len(row["val_fit"]) == len(row["test_fit"]) >= 1
    assert row["kept_step"] == row["steps"][row["val_fit"].index(max(row["val_fit"]))]


@pytest.mark.slow
def test_candidate_ensemble_reproduces_the_kept_candidate_and_the_mean_force_fits_at_least_their_mean(tiny_data,
                                                                                                      tmp_path):
    """The kept candidate's row is the run's own PIPE to the digit; the mean of two forces fits every trial at
    least as well as the two fit on average (the squared error is convex), so per split too."""
    from pipe.pipeline import run_domain

    run = run_domain(smoke_config(tiny_data, tmp_path / "run", "mlflow.enabled=false",
                                  "stages.vae.force_weight=[0,100]"))
    rows_file = tmp_path / "rows.jsonl"
    run_script("candidate_ensemble.py", str(rows_file), str(run.run_dir))
    row = json.loads(rows_file.read_text())
    assert row["test"]["chosen"] == pytest.approx(run.pipe.domain["fit_F"], abs=1e-9)
    for split in ("val", "test"):
        alone = [row[split]["force_weight_0"], row[split]["force_weight_100"]]
        assert row[split]["chosen"] == row[split][f"force_weight_{row['chosen_weight']:g}"]
        assert row[split]["ensemble"] >= statistics.mean(alone) - 1e-9 * max(1.0, abs(statistics.mean(alone)))
    for name in ("force_weight_0", "force_weight_100"):     # the parts' figures give the split's
        assert statistics.mean(row["val_per_part"][name].values()) == pytest.approx(row["val"][name], abs=1e-9)
    assert "validation FIT(F), heavier weight minus lighter" in run_script("candidate_ensemble.py", str(rows_file),
                                                                           "--summary")


def test_candidate_ensemble_summary_gives_the_validation_margin_part_by_part(tmp_path):
    """Hand-computed: differences 2, 4 and 6 (weight 1000 minus 0, whatever the order the row lists them in)
    have mean 4 and standard error 2 / sqrt(3) = 1.15; a row written before the per-part figures is skipped."""
    row = {"run": "r/seed_0", "chosen_weight": 1000.0,
           "val": {}, "test": {"force_weight_1000": 77.5, "force_weight_0": 72.25},
           "val_per_part": {"force_weight_1000": {"a": 72.0, "b": 74.0, "c": 76.0},
                            "force_weight_0": {"a": 70.0, "b": 70.0, "c": 70.0}}}
    printed = printed_table("candidate_ensemble.py", [{"run": "old"}, row], tmp_path, "--summary")
    assert printed.splitlines() == ["r/seed_0: kept 1000; validation FIT(F), heavier weight minus lighter, +4.00 ± "
                                    "1.15 (standard error over 3 parts); test FIT(F), lighter / heavier, 72.25 / "
                                    "77.50"]


@pytest.fixture(scope="module")
def family_run(tmp_path_factory):
    """A smoke run of both force weights on a 7-part rect family (2 test, 2 validation, 3 training parts), and
    the family generated again with 9 parts: the curve's 7 unchanged and the 2 it does not use."""
    from conftest import compose_config

    from pipe.pipeline import run_domain
    from pipe.synthetic import generate_dataset

    folder = tmp_path_factory.mktemp("family_run")
    run = run_domain(compose_config([
        "experiment=smoke", "data=family", "data.generate.family=rect", "data.generate.count=7",
        f"data.dir={folder / 'family'}", "domain=curve", "domain.test_count=2", "domain.val_count=2",
        "domain.train_count=3", f"paths.output_dir={folder / 'run'}", "mlflow.enabled=false",
        "stages.vae.force_weight=[0,1000]"]))
    return run, generate_dataset(folder / "larger", family="rect", count=9, seed=0)


@pytest.mark.slow
def test_validation_size_scores_the_runs_own_validation_parts_as_its_choice_did_and_the_extra_ones(family_run,
                                                                                                 tmp_path):
    """The extra parts are the two the curve does not use, and on the run's own validation parts each
    candidate's mean stage-2 loss is the validation objective its choice compared (training.json)."""
    run, larger = family_run
    rows_file = tmp_path / "rows.jsonl"
    run_script("validation_size.py", str(rows_file), str(larger), str(run.run_dir))
    row = json.loads(rows_file.read_text())
    assert row["extra"] == ["rect_0007", "rect_0008"]
    for weight, objective in row["objectives"].items():
        scores = row[f"force_weight_{weight}"]
        assert list(scores["loss"]) == list(scores["fit_F"]) == ["rect_0002", "rect_0003", *row["extra"]]
        assert statistics.mean([scores["loss"]["rect_0002"], scores["loss"]["rect_0003"]]) == pytest.approx(
            objective, rel=1e-5)


@pytest.mark.slow
def test_more_test_parts_reproduces_the_runs_test_parts_and_adds_the_extra_ones(family_run, tmp_path):
    """On the run's own test parts every method's FIT(F) is the run's to a relative 1e-6 (the oracle's and gpr's
    fits read from its cache, PIPE and `nearest` rebuilt from the kept candidate's checkpoints, the blackbox
    trained again from the run's seed; simulated in float32); the extra parts come after them."""
    run, larger = family_run
    rows_file = tmp_path / "rows.jsonl"
    run_script("more_test_parts.py", str(rows_file), str(larger), str(run.run_dir))
    row = json.loads(rows_file.read_text())
    assert row["extra"] == ["rect_0007", "rect_0008"] and row["train_parts"] == 3
    assert set(row["fit_F"]) == {"pipe", "nearest", "oracle", "gpr", "blackbox"}
    for name in row["fit_F"]:
        assert list(row["fit_F"][name]) == ["rect_0000", "rect_0001", *row["extra"]]
        for part, metrics in run.results[name].per_part.items():
            assert row["fit_F"][name][part] == pytest.approx(metrics["fit_F"], rel=1e-6, abs=1e-6)


def test_more_test_parts_summary_gives_each_subset_over_the_seeds_and_the_share_of_the_gap(tmp_path):
    """Hand-computed, two seeds: PIPE 70 and 74 on the test part (72 ± 2.83), `nearest` 60, the oracle 80: it
    closes (72 - 60) / (80 - 60) = 60 % of the gap, the mark 70; on the extra part PIPE 50 against `nearest` 60
    and the oracle 90: -33.3 %."""
    def row(pipe_test):
        return {"run": "r", "train_parts": 100, "extra": ["rect_0130"],
                "fit_F": {"pipe": {"rect_0000": pipe_test, "rect_0130": 50.0},
                          "nearest": {"rect_0000": 60.0, "rect_0130": 60.0},
                          "oracle": {"rect_0000": 80.0, "rect_0130": 90.0}}}

    lines = printed_table("more_test_parts.py", [row(70.0), row(74.0)], tmp_path, "--summary").splitlines()
    assert lines[0] == ("rect 100 parts, test 1: pipe 72.00 ± 2.83, nearest 60.00 ± 0.00, oracle 80.00 ± 0.00; "
                        "PIPE closes 60.0 % of the gap (mark 70.00; 2 seeds)")
    assert lines[1].startswith("rect 100 parts, extra 1: pipe 50.00 ± 0.00") and "closes -33.3 %" in lines[1]
    assert lines[2].startswith("rect 100 parts, all 2: pipe 61.00 ± 1.41")


def test_more_test_parts_summary_by_median_and_lower_decile_and_the_parts_pipe_wins(tmp_path):
    """Hand-computed, one seed, three test parts: PIPE 10, 70 and 80, `nearest` 60, 60 and 90, the oracle 80, 80
    and 100. Medians 70, 60 and 80: PIPE closes (70 - 60) / (80 - 60) = 50 % of the gap, the mark 70. Lower
    deciles (linear between the sorted values, at 0.2 of the first step): 22, 60 and 80, -190 %. PIPE is above
    `nearest` on one part (70 > 60) and above the oracle on none. No extra parts: no line for them."""
    row = {"run": "r", "train_parts": 100, "extra": [],
           "fit_F": {"pipe": {"pins_0000": 10.0, "pins_0001": 70.0, "pins_0002": 80.0},
                     "nearest": {"pins_0000": 60.0, "pins_0001": 60.0, "pins_0002": 90.0},
                     "oracle": {"pins_0000": 80.0, "pins_0001": 80.0, "pins_0002": 100.0}}}
    median = printed_table("more_test_parts.py", [row], tmp_path, "--summary", "--statistic", "median",
                           "--paired").splitlines()
    assert median[0] == ("pins 100 parts, test 3: pipe 70.00 ± 0.00, nearest 60.00 ± 0.00, oracle 80.00 ± 0.00; "
                         "PIPE closes 50.0 % of the gap (mark 70.00; 1 seeds)")
    assert median[1] == "  PIPE above it on nearest 1, oracle 0 of 3 parts (seed by seed)"
    assert median[2].startswith("pins 100 parts, all 3: pipe 70.00 ± 0.00") and len(median) == 4
    decile = printed_table("more_test_parts.py", [row], tmp_path, "--summary", "--statistic", "decile")
    assert decile.splitlines()[0] == ("pins 100 parts, test 3: pipe 22.00 ± 0.00, nearest 60.00 ± 0.00, oracle "
                                      "80.00 ± 0.00; PIPE closes -190.0 % of the gap (mark 70.00; 1 seeds)")


def test_validation_size_summary_gives_the_margins_on_the_own_the_extra_and_all_parts(tmp_path):
    """Hand-computed: loss differences (weight 1000 minus 0) of 0.1 and 0.3 on the own parts (mean 0.2,
    standard error 0.1: keeps 0), -0.2 and -0.4 on the extra ones (mean -0.3: keeps 1000), all four mean -0.05,
    standard error sqrt((0.29 / 3) / 4) = 0.1555."""
    losses = {"a": 0.1, "b": 0.3, "c": -0.2, "d": -0.4}
    row = {"run": "r/seed_0", "chosen_weight": 0.0, "extra": ["c", "d"],
           "force_weight_0": {"loss": dict.fromkeys(losses, 1.0), "fit_F": dict.fromkeys(losses, 50.0)},
           "force_weight_1000": {"loss": {p: 1.0 + d for p, d in losses.items()},
                                 "fit_F": {p: 50.0 - 100 * d for p, d in losses.items()}}}
    printed = printed_table("validation_size.py", [row], tmp_path, "--summary")
    assert printed.splitlines() == [
        "r/seed_0 (kept 0): own 2: loss +0.2000 ± 0.1000, FIT -20.00 ± 10.00 -> keeps 0; extra 2: loss -0.3000 ± "
        "0.1000, FIT +30.00 ± 10.00 -> keeps 1000; all 4: loss -0.0500 ± 0.1555, FIT +5.00 ± 15.55 -> keeps 1000"]


@pytest.mark.slow
def test_blackbox_extrapolation_reproduces_the_runs_blackbox_and_clips_only_inputs_outside_the_training_range(
        family_run, tmp_path):
    """On the run's own test parts the blackbox's FIT(F) is the run's (trained again from its seed); with its
    inputs clipped to the training parts' range it is the same where no input lies outside it; the
    extrapolation ratio is the run's own report's (PIPE's warning)."""
    run, larger = family_run
    rows_file = tmp_path / "rows.jsonl"
    run_script("blackbox_extrapolation.py", str(rows_file), str(larger), str(run.run_dir))
    row = json.loads(rows_file.read_text())
    assert row["extra"] == ["rect_0007", "rect_0008"] and len(row["train"]) == row["train_parts"] == 3
    assert list(row["parts"]) == ["rect_0000", "rect_0001", *row["extra"]]
    for name, metrics in run.results["blackbox"].per_part.items():
        assert row["parts"][name]["fit_F"] == pytest.approx(metrics["fit_F"], rel=1e-6, abs=1e-6)
    from pipe.evaluation.report import novelty_of_test_parts

    for name, warning in novelty_of_test_parts(run).items():
        assert row["parts"][name]["novelty_ratio"] == pytest.approx(warning["ratio"], rel=1e-5)
    for part in row["parts"].values():
        assert part["beyond"] >= 0.0 and part["largest_force"] > 0.0
        if part["beyond"] == 0.0:
            assert part["fit_F_clipped"] == part["fit_F"]
    assert any(part["beyond"] > 0.0 for part in row["parts"].values())     # 3 training parts: some lie outside


def test_blackbox_extrapolation_summary_gives_each_subset_over_the_seeds_and_names_the_collapses(tmp_path):
    """Hand-computed, two seeds: on the test part 70 and 74 (72 ± 2.83), clipped 70 both; both parts flagged
    (ratio 3.25) in both seeds; the extra part's collapse (-500 in one seed) is listed with its column and
    distance, the other seed's 50 is not."""
    def row(seed, test, extra):
        part = {"fit_F_clipped": 70.0, "largest_force": 9.0, "measured_largest_force": 2.0, "beyond": 12.5,
                "beyond_column": "slices[10]", "novelty_ratio": 3.25}
        return {"run": f"r/seed_{seed}", "train_parts": 5, "extra": ["pins_0152"], "inputs": "slices",
                "parts": {"pins_0000": {**part, "fit_F": test}, "pins_0152": {**part, "fit_F": extra}}}

    lines = printed_table("blackbox_extrapolation.py", [row(0, 70.0, -500.0), row(1, 74.0, 50.0)], tmp_path,
                          "--summary").splitlines()
    assert lines[0] == "5 training parts, test 1: fit_F 72.00 ± 2.83, fit_F_clipped 70.00 ± 0.00 (2 seeds)"
    assert lines[1] == "5 training parts, extra 1: fit_F -225.00 ± 388.91, fit_F_clipped 70.00 ± 0.00 (2 seeds)"
    assert lines[2].startswith("5 training parts, all 2: fit_F -76.50 ± ")
    assert lines[3] == "  PIPE's extrapolation warning flags 2, 2 of the 2 parts by seed"
    assert lines[4:] == ["  seed_0 pins_0152: FIT -500, clipped 70.0, largest |F| 9.00 N (measured 2.00), "
                         "slices[10] 12.5 beyond the training range (reads slices); extrapolation ratio 3.25"]


@pytest.mark.slow
def test_candidate_cv_holds_out_each_non_test_part_per_candidate_as_part_cv_does(tiny_data, tmp_path):
    """Each candidate's PIPE on a held-out part is part_cv's `default` on that candidate's folder to the digit;
    the ensemble fits each held-out part at least as well as the two candidates on average (FIT is concave in
    the prediction); the run's kept candidate is the one flagged `chosen`."""
    from pipe.pipeline import run_domain

    run = run_domain(smoke_config(tiny_data, tmp_path / "run", "mlflow.enabled=false",
                                  "stages.vae.force_weight=[0,100]"))
    rows_file = tmp_path / "rows.jsonl"
    run_script("candidate_cv.py", str(rows_file), str(run.run_dir), "--fits", str(tmp_path / "fits"))
    rows = [json.loads(line) for line in rows_file.read_text().splitlines()]
    non_test = ("dsub9", "dsub15", "vga")
    assert sorted((r["candidate"], r["held_out"]) for r in rows) == sorted(
        (c, p) for c in ("force_weight_0", "force_weight_100", "ensemble") for p in non_test)
    kept = f"force_weight_{json.loads((run.run_dir / 'training.json').read_text())['force_weight']['chosen']:g}"
    assert {r["candidate"] for r in rows if r.get("chosen")} == {kept}
    pipe = {(r["candidate"], r["held_out"]): r["pipe"] for r in rows}
    reference = tmp_path / "reference.jsonl"
    run_script("part_cv.py", str(reference), str(run.run_dir / "force_weight_100"), "--variants", "default")
    for line in reference.read_text().splitlines():
        row = json.loads(line)
        assert pipe[("force_weight_100", row["held_out"])] == pytest.approx(row["fit"], abs=1e-9)
    for part in non_test:
        alone = statistics.mean([pipe[("force_weight_0", part)], pipe[("force_weight_100", part)]])
        assert pipe[("ensemble", part)] >= alone - 1e-9 * max(1.0, abs(alone))
    # gpr_cv.py, which trains nothing again, gives the kept candidate's gpr and gpr in hindsight to the digit
    gpr_file = tmp_path / "gpr.jsonl"
    run_script("gpr_cv.py", str(gpr_file), str(run.run_dir), "--fits", str(tmp_path / "fits"))
    gpr_rows = {r["held_out"]: r for r in map(json.loads, gpr_file.read_text().splitlines())}
    assert sorted(gpr_rows) == sorted(non_test)
    for row in rows:
        if row.get("chosen"):
            assert gpr_rows[row["held_out"]]["candidate"] == kept
            for column in ("gpr", "gpr_hindsight"):
                assert gpr_rows[row["held_out"]][column] == pytest.approx(row[column], abs=1e-9)


@pytest.mark.slow
def test_vae_augmentation_retrains_a_run_of_two_candidates_from_its_kept_one(tiny_data, tmp_path):
    """On a run that chose between two force weights, `none` trains stage 1 and 2 again as the kept candidate
    was trained (its weight, seed and initial weights): the run's own PIPE on the test part, to the digit; an
    augmentation trains another encoder."""
    from pipe.pipeline import run_domain

    run = run_domain(smoke_config(tiny_data, tmp_path / "run", "mlflow.enabled=false",
                                  "stages.vae.force_weight=[0,100]"))
    rows_file = tmp_path / "rows.jsonl"
    run_script("vae_augmentation.py", str(rows_file), str(run.run_dir), "--variants", "none,rotate")
    rows = {row["variant"]: row for row in map(json.loads, rows_file.read_text().splitlines())}
    assert sorted(rows) == ["augment:none", "augment:rotate"]
    assert {row["run"] for row in rows.values()} == {str(run.run_dir)}
    assert rows["augment:none"]["test"]["pipe"] == pytest.approx(run.pipe.domain["fit_F"], abs=1e-6)
    assert rows["augment:rotate"]["test"]["pipe"] != pytest.approx(run.pipe.domain["fit_F"], abs=1e-6)


@pytest.mark.slow
def test_stage1_per_fold_trains_the_force_weighted_encoder_without_the_held_out_part(tiny_data, tmp_path,
                                                                                      monkeypatch):
    """With stage1="force", the force-weighted candidate's stage 1 is trained again in each fold (the encoder
    itself) on the other non-test parts alone (no validation parts), into other codes; the weight-0 candidate's
    stage 1 read no recordings and is the run's own, so its folds are those without `stage1` to the digit, unless
    stage1="all" (the control)."""
    import copy

    import torch
    sys.path.insert(0, str(ROOT / "experiments"))
    import part_cv

    from pipe.pipeline import run_domain

    run = run_domain(smoke_config(tiny_data, tmp_path / "run", "mlflow.enabled=false",
                                  "stages.vae.force_weight=[0,100]"))
    fitted, fit_vae = [], part_cv.fit_module.fit_vae

    def recording_fit_vae(cfg, encoder, train, val, *args):
        fitted.append(([p.name for p in train], [p.name for p in val]))
        before = copy.deepcopy(encoder.state_dict())
        result = fit_vae(cfg, encoder, train, val, *args)
        # every fold trains the encoder itself, not only the force readout (an earlier fold's stage 2 froze it)
        changed = [not torch.equal(before[name], value) for name, value in encoder.state_dict().items()
                   if value.is_floating_point()]
        assert sum(changed) > len(changed) / 2
        return result

    monkeypatch.setattr(part_cv.fit_module, "fit_vae", recording_fit_vae)
    default = [("default", {})]
    weighted = {f.held_out.name: f.codes.clone() for f in part_cv.fold_models(
        run.run_dir / "force_weight_100", default, str(tmp_path / "fits"), stage1="force")}
    assert sorted((sorted(train), val) for train, val in fitted) == sorted(
        (sorted({"dsub9", "dsub15", "vga"} - {held}), []) for held in weighted)
    assert all(held not in train for held, (train, _) in zip(weighted, fitted))
    own = {f.held_out.name: f.codes.clone() for f in part_cv.fold_models(
        run.run_dir / "force_weight_100", default, str(tmp_path / "fits"))}
    assert all(not torch.allclose(weighted[part], own[part]) for part in own)
    fitted.clear()
    plain = [(f.held_out.name, f.codes.clone()) for f in part_cv.fold_models(
        run.run_dir / "force_weight_0", default, str(tmp_path / "fits"), stage1="force")]
    again = [(f.held_out.name, f.codes.clone()) for f in part_cv.fold_models(
        run.run_dir / "force_weight_0", default, str(tmp_path / "fits"))]
    assert not fitted and [name for name, _ in plain] == [name for name, _ in again]
    assert all(torch.equal(a, b) for (_, a), (_, b) in zip(plain, again))
    # stage1="all", the control: the weight-0 candidate's stage 1 trained again per fold as well
    control = {f.held_out.name: f.codes.clone() for f in part_cv.fold_models(
        run.run_dir / "force_weight_0", default, str(tmp_path / "fits"), stage1="all")}
    assert sorted(sorted(train) for train, _ in fitted) == sorted(
        sorted({"dsub9", "dsub15", "vga"} - {held}) for held in control)
    assert all(not torch.allclose(control[name], codes) for name, codes in again)


def test_domain_of_reads_a_candidates_folder_as_its_runs():
    sys.path.insert(0, str(ROOT / "experiments"))
    from summarise import domain_of

    assert domain_of("runs/conn/seed_0") == domain_of("runs/conn/seed_0/force_weight_1000") == "conn"
    assert domain_of("runs/curve/pins/train_20/seed_1/force_weight_0") == "pins/train_20"


def test_candidate_cv_table_averages_the_held_out_parts_per_seed_and_reads_the_kept_candidates_baselines(tmp_path):
    def row(run, candidate, part, pipe, chosen=False, nearest=0.0, gpr=0.0):
        return {"run": run, "candidate": candidate, "held_out": part, "pipe": pipe, "chosen": chosen,
                "nearest": nearest, "gpr": gpr, "gpr_hindsight": gpr + 1.0}
    rows = [row("runs/pins/seed_0", "force_weight_0", "a", 50.0, True, 40.0, 30.0),
            row("runs/pins/seed_0", "force_weight_0", "b", 70.0, True, 60.0, 10.0),
            row("runs/pins/seed_0", "force_weight_1000", "a", 90.0),
            row("runs/pins/seed_0", "force_weight_1000", "b", 10.0),
            {"run": "runs/pins/seed_0", "candidate": "ensemble", "held_out": "a", "pipe": 80.0},
            {"run": "runs/pins/seed_0", "candidate": "ensemble", "held_out": "b", "pipe": 60.0},
            row("runs/pins/seed_1", "force_weight_0", "a", 30.0), row("runs/pins/seed_1", "force_weight_0", "b", 50.0),
            row("runs/pins/seed_1", "force_weight_1000", "a", 20.0, True, 10.0, 70.0),
            row("runs/pins/seed_1", "force_weight_1000", "b", 40.0, True, 30.0, 50.0),
            {"run": "runs/pins/seed_1", "candidate": "ensemble", "held_out": "a", "pipe": 35.0},
            {"run": "runs/pins/seed_1", "candidate": "ensemble", "held_out": "b", "pipe": 45.0}]
    printed = printed_table("candidate_cv.py", rows, tmp_path, "--table")
    # per seed: weight 0 60, 40; weight 1000 50, 30; chosen 60 (weight 0), 30 (weight 1000); ensemble 70, 40;
    # nearest on the chosen codes 50, 20; gpr 20, 60; gpr in hindsight 21, 61
    sd = statistics.stdev
    # medians over the four held-out cases: 50, 30, 45, 52.5, 35, 40, 41
    assert (f"| pins | 50.00 ± {sd([60, 40]):.2f} (50.00) | 40.00 ± {sd([50, 30]):.2f} (30.00) | "
            f"45.00 ± {sd([60, 30]):.2f} (45.00) | 55.00 ± {sd([70, 40]):.2f} (52.50) | "
            f"35.00 ± {sd([50, 20]):.2f} (35.00) | 40.00 ± {sd([20, 60]):.2f} (40.00) | "
            f"41.00 ± {sd([21, 61]):.2f} (41.00) |") in printed
    # paired, per seed and candidate: the mean over the held-out parts of PIPE's FIT minus the baseline's
    assert "| pins | seed_0 | force_weight_0 | +10.00 | +40.00 | force_weight_0 | force_weight_0 |" in printed
    assert "| pins | seed_0 | force_weight_1000 | +50.00 | +50.00 | force_weight_0 | force_weight_0 |" in printed
    assert "| pins | seed_1 | force_weight_0 | +40.00 | +40.00 | force_weight_0 | force_weight_1000 |" in printed
    assert "| pins | seed_1 | force_weight_1000 | +10.00 | -30.00 | force_weight_0 | force_weight_1000 |" in printed


def test_gpr_cv_table_averages_the_held_out_parts_per_seed(tmp_path):
    def row(run, part, gpr, likelihood, hindsight):
        return {"run": run, "candidate": "force_weight_0", "held_out": part, "gpr": gpr,
                "gpr_likelihood": likelihood, "gpr_hindsight": hindsight}
    rows = [row("runs/pins/seed_0", "a", 50.0, -10.0, 60.0), row("runs/pins/seed_0", "b", 70.0, 10.0, 80.0),
            row("runs/pins/seed_1", "a", 20.0, -30.0, 30.0), row("runs/pins/seed_1", "b", 40.0, -20.0, 90.0),
            row("runs/conn/seed_0", "c", 5.0, 1.0, 7.0)]
    printed = printed_table("gpr_cv.py", rows, tmp_path, "--table")
    # pins per seed: leave-one-out 60, 30; likelihood 0, -25; hindsight 70, 60; medians over the four cases
    sd = statistics.stdev
    assert (f"| pins (2) | 45.00 ± {sd([60, 30]):.2f} (45.00) | -12.50 ± {sd([0, -25]):.2f} (-15.00) | "
            f"65.00 ± {sd([70, 60]):.2f} (70.00) |") in printed
    assert "| conn (1) | 5.00 ± 0.00 (5.00) | 1.00 ± 0.00 (1.00) | 7.00 ± 0.00 (7.00) |" in printed


def test_candidate_cv_test_table_scores_on_the_test_parts_the_candidate_the_cross_validation_prefers(tmp_path):
    def row(run, candidate, pipe, chosen=False):
        return {"run": run, "candidate": candidate, "held_out": "a", "pipe": pipe, "chosen": chosen,
                "nearest": 0.0, "gpr": 0.0, "gpr_hindsight": 0.0}
    # cross-validation: seed 0 kept weight 0 and prefers 1000; seeds 1 and 2 kept and prefer 1000
    rows = [row("runs/pins/seed_0", "force_weight_0", 50.0, True), row("runs/pins/seed_0", "force_weight_1000", 60.0),
            row("runs/pins/seed_1", "force_weight_0", 50.0), row("runs/pins/seed_1", "force_weight_1000", 60.0, True),
            row("runs/pins/seed_2", "force_weight_0", 50.0), row("runs/pins/seed_2", "force_weight_1000", 60.0, True)]
    test = [{"run": f"runs/pins/seed_{s}", "test": {"force_weight_0": w0, "force_weight_1000": w1000}}
            for s, w0, w1000 in ((0, 70.0, 80.0), (1, 0.0, 72.0), (2, 0.0, 74.0))]
    test_file = tmp_path / "test.jsonl"
    test_file.write_text("".join(json.dumps(r) + "\n" for r in test))
    printed = printed_table("candidate_cv.py", rows, tmp_path, "--table", "--test", str(test_file))
    # kept: 70, 72, 74 (mean 72, std 2); preferred: 80, 72, 74 (mean 75.33); 3.33 <= 2 + 4.16: a tie
    assert (f"| pins | 72.00 ± 2.00 | 75.33 ± {statistics.stdev([80, 72, 74]):.2f} | tie | 1 of 3 |") in printed
    test_file.write_text(json.dumps(test[0]) + "\n")
    with pytest.raises(AssertionError, match="no test row for runs/pins/seed_1, runs/pins/seed_2"):
        printed_table("candidate_cv.py", rows, tmp_path, "--table", "--test", str(test_file))


@pytest.mark.slow
def test_head_ensemble_cv_first_member_is_part_cvs_head_and_the_mean_force_fits_at_least_the_members_mean(
        trained_run, tmp_path):
    rows_file, reference = tmp_path / "rows.jsonl", tmp_path / "reference.jsonl"
    run_script("head_ensemble_cv.py", str(rows_file), str(trained_run.run_dir), "--heads", "3")
    run_script("part_cv.py", str(reference), str(trained_run.run_dir), "--variants", "default")
    rows = {r["held_out"]: r for r in map(json.loads, rows_file.read_text().splitlines())}
    assert sorted(rows) == sorted(("dsub9", "dsub15", "vga"))
    for line in reference.read_text().splitlines():
        own = json.loads(line)
        row = rows[own["held_out"]]
        assert row["members"][0] == pytest.approx(own["fit"], abs=1e-9) == row["ensemble"][0]
        assert len(set(row["members"])) == 3                  # three different initial weights, three heads
        for k in (2, 3):
            alone = statistics.mean(row["members"][:k])
            assert row["ensemble"][k - 1] >= alone - 1e-9 * max(1.0, abs(alone))
    # --own-split: trained on the run's own split, member 1 is the run's own PIPE on its test parts
    own_file = tmp_path / "own.jsonl"
    run_script("head_ensemble_cv.py", str(own_file), str(trained_run.run_dir), "--heads", "2", "--own-split")
    own = {r["split"]: r for r in map(json.loads, own_file.read_text().splitlines())}
    assert sorted(own) == ["test", "val"]
    assert own["test"]["members"][0] == pytest.approx(trained_run.results["pipe"].domain["fit_F"], abs=1e-6)
    assert own["test"]["ensemble"][1] >= statistics.mean(own["test"]["members"]) - 1e-9


def test_head_ensemble_cv_table_gives_each_ensemble_size_over_the_seeds(tmp_path):
    rows = [{"run": "runs/dsub/seed_0", "held_out": "a", "members": [60.0, 40.0], "ensemble": [60.0, 70.0]},
            {"run": "runs/dsub/seed_0", "held_out": "b", "members": [20.0, 40.0], "ensemble": [20.0, 50.0]},
            {"run": "runs/dsub/seed_1", "held_out": "a", "members": [50.0, 30.0], "ensemble": [50.0, 45.0]},
            {"run": "runs/dsub/seed_1", "held_out": "b", "members": [10.0, 50.0], "ensemble": [10.0, 35.0]}]
    printed = printed_table("head_ensemble_cv.py", rows, tmp_path, "--table")
    # one head: seeds 40, 30, median of 60, 20, 50, 10 = 35; members on average: 40, 35 (median of 50, 30, 40,
    # 30 = 35); two heads: 60, 40 (median 47.5); two heads minus one per seed: +20, +10
    sd = statistics.stdev
    assert (f"| dsub | 35.00 ± {sd([40, 30]):.2f} (35.00) | 37.50 ± {sd([40, 35]):.2f} (35.00) | "
            f"50.00 ± {sd([60, 40]):.2f} (47.50) | +20.00, +10.00 |") in printed
    # --own-split's rows: one per run and split, grouped by both
    own = [{"run": "runs/curve/rect/train_100/seed_0", "split": "test", "members": [70.0, 80.0],
            "ensemble": [70.0, 78.0]},
           {"run": "runs/curve/rect/train_100/seed_1", "split": "test", "members": [60.0, 50.0],
            "ensemble": [60.0, 58.0]}]
    printed = printed_table("head_ensemble_cv.py", own, tmp_path, "--table")
    assert (f"| rect/train_100 test | 65.00 ± {sd([70, 60]):.2f} (65.00) | 65.00 ± {sd([75, 55]):.2f} (65.00) | "
            f"68.00 ± {sd([78, 58]):.2f} (68.00) | +8.00, -2.00 |") in printed


@pytest.mark.slow
def test_twins_finds_the_nearest_training_code_and_the_best_copy_fits_at_least_as_well_as_nearest(trained_run,
                                                                                                   tmp_path):
    import torch

    rows_file = tmp_path / "rows.jsonl"
    run_script("twins.py", str(rows_file), str(trained_run.run_dir))
    (row,) = [json.loads(line) for line in rows_file.read_text().splitlines()]       # the one test part, dsub26
    result, codes, index = trained_run.results["pipe"].per_part["dsub26"], trained_run.latents, trained_run.index
    distances = {name: float(torch.dist(codes[index["dsub26"]], codes[index[name]])) for name in ("dsub9", "dsub15")}
    assert [row["twin"], row["second"]] == sorted(distances, key=distances.get)[:2]
    assert row["fit_pipe"] == pytest.approx(result["fit_F"], abs=1e-6)
    # the twin's profile is one of the copies, so the best copy fits at least as well as `nearest`
    assert row["fit_best_copy"] >= row["fit_nearest"]


def test_code_probe_scores_a_parameter_the_codes_hold_near_one_and_one_they_do_not_below_zero():
    import numpy as np
    sys.path.insert(0, str(ROOT / "experiments"))
    from code_probe import probe

    rng = np.random.default_rng(0)
    codes = rng.normal(size=(120, 8))
    held = codes @ rng.normal(size=8) + 0.01 * rng.normal(size=120)     # a linear function of the codes
    unrelated = rng.normal(size=120)
    assert probe(codes[:100], codes[100:], held[:100], held[100:]) > 0.99
    assert probe(codes[:100], codes[100:], unrelated[:100], unrelated[100:]) < 0.1
    # R^2 is taken against the training parts' mean: codes that hold nothing predict that mean and score 0
    flat = np.zeros((120, 8))
    assert probe(flat[:100], flat[100:], unrelated[:100], unrelated[100:]) == pytest.approx(0.0, abs=1e-9)


def test_code_probe_table_gives_each_parameter_over_the_seeds(tmp_path):
    rows = [{"run": f"runs/curve/rect/train_100/seed_{k}", "layer": "codes",
             "r2": {"log width": 0.9 + 0.06 * k, "detents": -0.1}} for k in range(2)]
    printed = printed_table("code_probe.py", rows, tmp_path, "--table")
    assert f"| rect/train_100 | codes | log width | 0.93 ± {statistics.stdev([0.9, 0.96]):.2f} | 2 |" in printed
    assert "| rect/train_100 | codes | detents | -0.10 ± 0.00 | 2 |" in printed


@pytest.mark.slow
def test_encoder_stage1_trains_another_encoder_on_exported_clouds_into_a_run_folder(trained_run, tmp_path):
    import numpy as np
    from omegaconf import OmegaConf

    clouds, out = tmp_path / "clouds.npz", tmp_path / "dgcnn_run"
    run_script("encoder_stage1.py", "export", str(trained_run.run_dir), str(clouds))
    exported = np.load(clouds)
    assert exported["train"].shape[0] == 2 and exported["val"].shape[0] == 1     # dsub9, dsub15; vga
    run_script("encoder_stage1.py", "train", str(trained_run.run_dir), str(clouds), str(out), "--encoder", "dgcnn",
               "--epochs", "1", "--latent-dim", "16")
    cfg = OmegaConf.load(out / "config.yaml")
    assert cfg.encoder._target_.endswith("DGCNNVAE") and cfg.stages.vae.epochs == 1 and cfg.encoder.latent_dim == 16
    # the other scripts read the folder as a run: its config builds a DGCNN that takes the stage-1 weights
    sys.path.insert(0, str(ROOT / "experiments"))
    from common import load_encoder

    from pipe.data.slices import SLICE_SIZE
    from pipe.model.sections import SECTION_SIZE
    from pipe.pipeline import build_components
    encoder, head, _ = build_components(cfg)
    load_encoder(encoder, out)
    assert encoder.latent_dim == 16 and head.latent_dim == 16 + SECTION_SIZE + SLICE_SIZE   # as the run's


def test_contact_points_finds_the_points_on_a_plugs_contacts_alone():
    """Hand-placed points: a D-sub pin's tip (its end face at z = 0.8) and the middle of a rect pad's outer face
    (0.05 mm proud of the tongue, z 1.0 to mate - 0.5) lie on contacts; the D-sub shell's rim (mid-wall of its
    straight top side, z = 0), the rect shell's outer wall, the tongue's front face and the tongue's face
    beside a pad do not."""
    sys.path.insert(0, str(ROOT / "experiments"))
    import numpy as np
    from contact_points import on_contacts

    from pipe.synthetic.catalogue import Plug, dsub_plug
    from pipe.synthetic.meshes import SHELL_WALL

    dsub = dsub_plug("dsub9", "E", False)
    x, y = -2 * dsub.pitch, dsub.row_pitch / 2          # the first row's first pin (5 pins, 2 rows)
    points = np.array([[x, y, 0.8], [0.0, dsub.height / 2 - SHELL_WALL / 2, 0.0]])
    assert on_contacts(dsub, points).tolist() == [True, False]

    rect = Plug("r", "rect", "rect", 4 * 2.5, 2.3 * 2.5, 6.0, (2,), 2.5, 2.5, 0.625, 0, 2.0, (12.0, 7.8, 10.0))
    face = 0.3 * (rect.height / 2 - SHELL_WALL)          # the tongue's upper face: 0.3 of the shell's inside
    points = np.array([[1.25, face + 0.05, 3.0], [0.0, face, 3.0], [0.0, 0.0, 0.6], [rect.width / 2, 0.0, 3.0]])
    assert on_contacts(rect, points).tolist() == [True, False, False, False]


def test_contact_points_summary_gives_points_per_contact_per_family_and_cloud_size():
    sys.path.insert(0, str(ROOT / "experiments"))
    from contact_points import summary

    rows = [{"family": "rect", "points": 1024, "contacts": 4, "on_contacts": 8, "on_contacts_end_on": 0},
            {"family": "rect", "points": 1024, "contacts": 10, "on_contacts": 10, "on_contacts_end_on": 3},
            {"family": "dsub", "points": 1024, "contacts": 9, "on_contacts": 27, "on_contacts_end_on": 9}]
    assert summary(rows).splitlines() == [   # rect: medians of 2 and 1, of 0 and 0.3
        "dsub, 1024 points, 1 parts: 3.00 points per contact (3.00 to 3.00); within 1 mm of the mating end 1.00 "
        "(1.00 to 1.00), none in 0",
        "rect, 1024 points, 2 parts: 1.50 points per contact (1.00 to 2.00); within 1 mm of the mating end 0.15 "
        "(0.00 to 0.30), none in 1"]


def test_read_rows_skips_blank_lines_and_names_a_missing_file(tmp_path):
    sys.path.insert(0, str(ROOT / "experiments"))
    from summarise import read_rows

    rows_file = tmp_path / "rows.jsonl"
    rows_file.write_text('{"a": 1}\n\n{"a": 2}\n')
    assert read_rows(rows_file) == [{"a": 1}, {"a": 2}]
    with pytest.raises(SystemExit, match="no/such.jsonl: no such file of result rows"):
        read_rows(tmp_path / "no/such.jsonl")


def test_mesh_slices_prints_a_d_subs_shell_and_pins_apart(tiny_data):
    """dsub26 is dsub15's shell with 26 pins instead of 15: 2 mm up, 27 regions against 16."""
    printed = run_script("mesh_slices.py", str(tiny_data), "dsub15", "dsub26").splitlines()
    assert printed[0].startswith("part | 0.5 mm: regions, length, area | 2 mm:")
    assert [row.split(" | ")[2].split(",")[0] for row in printed[1:]] == ["16", "27"]


def test_twin_oracle_twins_and_expectation_are_the_generators_same_parts_and_motions(tmp_path):
    import numpy as np

    sys.path.insert(0, str(ROOT / "experiments"))
    from twin_oracle import expected_parts, pooled, twin_parts

    from pipe.data.dataset import load_dataset
    from pipe.data.prepared import PreprocessSettings, prepare_part
    from pipe.data.spec import load_spec
    from pipe.synthetic.families import family_parts
    from pipe.synthetic.generate import TRIALS_PER_PART, generate_dataset

    root = generate_dataset(tmp_path / "pins", family="pins", count=2)
    drawn = family_parts("pins", 2, 0)
    settings = PreprocessSettings(points=256, cloud_seed=0, rate_hz=100.0, steady_samples=1)
    own = [prepare_part(part, load_spec(root), settings) for part in load_dataset(root).parts.values()]

    def forces(parts):
        return [p.force for part in parts for p in part.profiles]

    # the dataset's own stream gives the dataset's trials back to the digit: a twin is the generator's same part
    same = twin_parts(drawn, own, settings, stream=0)
    assert all(np.array_equal(a, b) for a, b in zip(forces(same), forces(own)))
    assert [part.cloud for part in same] == [part.cloud for part in own]
    # another stream draws every trial again (other conditions, other noise), the same way every time
    first, again, second = (twin_parts(drawn, own, settings, stream=s) for s in (1000, 1000, 1001))
    assert all(np.array_equal(a, b) for a, b in zip(forces(first), forces(again)))
    assert not any(len(a) == len(b) and np.allclose(a, b) for a, b in zip(forces(first), forces(own)))
    assert not any(len(a) == len(b) and np.allclose(a, b) for a, b in zip(forces(first), forces(second)))
    # pooled twins: each part with both twins' trials, the first twin's first
    both = pooled([first, second])
    assert [part.name for part in both] == [part.name for part in own]
    assert all(len(part.profiles) == len(part.static_curves) == 2 * TRIALS_PER_PART for part in both)
    assert all(a is b for a, b in zip(forces(both)[:TRIALS_PER_PART], forces(first)))
    assert all(a is b for a, b in zip(forces(both)[TRIALS_PER_PART:2 * TRIALS_PER_PART], forces(second)))
    # the expected force keeps each trial's own motion (its depth within the noise and the file's rounding, where
    # another trial's speed or overtravel would move it by millimetres), starts at rest without bias or noise,
    # and is not the measured force
    expected = expected_parts(drawn, 0, own, settings, draws=3)
    assert set(expected) == {"mean", "fit"}
    for mine, guess, weighted in zip(own, expected["mean"], expected["fit"]):
        # the FIT-weighted mean of the same draws is another mean of them
        assert not np.allclose(weighted.profiles[0].force, guess.profiles[0].force)
        assert len(guess.profiles) == TRIALS_PER_PART and guess.cloud is mine.cloud
        for measured, predicted in zip(mine.profiles, guess.profiles):
            assert len(predicted.depth) == len(measured.depth)
            assert np.abs(predicted.depth - measured.depth).max() < 0.02
            assert np.abs(predicted.force[:5]).max() == 0.0 and np.array_equal(predicted.force, predicted.force_clean)
            assert not np.allclose(predicted.force, measured.force, atol=0.05)


def test_twin_oracle_twins_of_the_embedded_dataset_are_the_catalogues_parts(tmp_path):
    import numpy as np
    from omegaconf import OmegaConf

    sys.path.insert(0, str(ROOT / "experiments"))
    from twin_oracle import drawn_parts, twin_parts

    from pipe.data.dataset import load_dataset
    from pipe.data.prepared import PreprocessSettings, prepare_part
    from pipe.data.spec import load_spec
    from pipe.synthetic.catalogue import CATALOGUE
    from pipe.synthetic.families import family_parts
    from pipe.synthetic.generate import generate_dataset

    # the embedded dataset's config names no family: its parts are the catalogue's; a family's are drawn
    assert drawn_parts(OmegaConf.create({"seed": 0})) is CATALOGUE
    assert drawn_parts(OmegaConf.create({"seed": 0, "family": "rect", "count": 3})) == family_parts("rect", 3, 0)
    with pytest.raises(SystemExit, match="not generated"):
        drawn_parts(None)
    root = generate_dataset(tmp_path / "paper", seed=5, parts=["taper8", "dsub26"])
    settings = PreprocessSettings(points=256, cloud_seed=0, rate_hz=100.0, steady_samples=1)
    own = [prepare_part(part, load_spec(root), settings) for part in load_dataset(root).parts.values()]
    same = twin_parts(CATALOGUE, own, settings, stream=5)      # the dataset's own stream: its trials back
    other = twin_parts(CATALOGUE, own, settings, stream=1000)
    for mine, twin, drawn_again in zip(own, same, other):
        assert all(np.array_equal(a.force, b.force) for a, b in zip(mine.profiles, twin.profiles))
        assert not any(len(a.force) == len(b.force) and np.allclose(a.force, b.force)
                       for a, b in zip(mine.profiles, drawn_again.profiles))


def test_twin_oracle_only_keeps_the_named_test_parts_in_the_splits_order_and_refuses_others():
    from types import SimpleNamespace

    sys.path.insert(0, str(ROOT / "experiments"))
    from twin_oracle import only_parts

    test = [SimpleNamespace(name=name) for name in ("rect_0003", "rect_0010", "rect_0018")]
    assert [p.name for p in only_parts(test, ["rect_0018", "rect_0010"], "rect")] == ["rect_0010", "rect_0018"]
    with pytest.raises(SystemExit, match="--only rect_0099: not a test part of rect"):
        only_parts(test, ["rect_0010", "rect_0099"], "rect")
    # aligned_oracle.py --domain chooses among every part of a paper domain, and says so when refusing
    with pytest.raises(SystemExit, match="--only dsub99: not a part of dsub"):
        only_parts(test, ["dsub99"], "dsub", "a part")


def test_twin_oracle_table_gives_each_fit_over_the_seeds_and_the_median_part(tmp_path):
    rows = [{"family": "pins", "seed": seed, "fit": fit, "fit_F": value, "parts": parts}
            for seed, fit, value, parts in [
                (0, "own", 80.0, {"pins_0000": 90.0, "pins_0001": 70.0}),
                (1, "own", 84.0, {"pins_0000": 92.0, "pins_0001": 76.0}),
                (0, "twins=1", 20.0, {"pins_0000": 88.0, "pins_0001": -48.0})]]
    printed = printed_table("twin_oracle.py", rows, tmp_path, "--table")
    # own: mean 82 ± stdev(80, 84); median of 90, 70, 92, 76 is 83; one twin: one seed, the median part 20
    assert f"| pins | own | 82.00 ± {statistics.stdev([80.0, 84.0]):.2f} | 83.00 | 2 |" in printed
    assert "| pins | twins=1 | 20.00 ± 0.00 | 20.00 | 1 |" in printed
    # per part: the mean over the seeds, each part under its family (a paper part may sit in two domains)
    rows.append({"family": "paper conn", "seed": 0, "fit": "own", "fit_F": 50.0, "parts": {"pins_0000": 50.0}})
    printed = printed_table("twin_oracle.py", rows, tmp_path, "--table", "--parts")
    assert "| paper conn | pins_0000 | 50.00 |  |" in printed
    assert "| pins | pins_0000 | 91.00 | 88.00 |" in printed


def test_expected_head_pooled_normaliser_divides_by_the_parts_mean_variance():
    from types import SimpleNamespace

    import numpy as np
    import torch

    sys.path.insert(0, str(ROOT / "experiments"))
    from expected_head import part_variances, pooled_normaliser_stage

    from pipe.data.batches import TrialBatch

    trial = lambda *force: SimpleNamespace(force=np.array(force))       # noqa: E731
    parts = [SimpleNamespace(name="a", profiles=[trial(0.0, 2.0), trial(0.0, 4.0)]),    # variances 1 and 4
             SimpleNamespace(name="b", profiles=[trial(1.0, 1.0, 4.0)])]                 # variance 2
    variances = part_variances(parts, {"a": 0, "test": 1, "b": 2})
    assert variances.tolist() == [2.5, 1.0, 2.0]        # the part's mean variance; ones where no part is given

    class Constant(torch.nn.Module):        # predicts 1 N everywhere, whatever the part
        encoder = torch.nn.Identity()

        def forward(self, z, depth, dt):
            return torch.ones_like(depth)

    stage = pooled_normaliser_stage(variances)(Constant(), torch.zeros(3, 1), lr=1e-3, loss="nmse")
    batch = TrialBatch(part=torch.tensor([0, 2]), depth=torch.zeros(2, 3),
                       force=torch.tensor([[0.0, 2.0, 2.0], [1.0, 1.0, 4.0]]),
                       mask=torch.tensor([[True, True, False], [True, True, True]]), dt=0.01)
    # trial 1: errors 1 and 1 over 2.5 x its 2 real samples; trial 2: error 9 over 2 x 3 samples
    expected = (2.0 / (2.5 * 2) + 9.0 / (2.0 * 3)) / 2
    assert stage.training_step(batch, 0).item() == pytest.approx(expected)


def test_expected_head_trains_each_target_on_its_own_parts_in_order():
    from types import SimpleNamespace

    sys.path.insert(0, str(ROOT / "experiments"))
    from expected_head import training_targets

    def parts(*names, kind="recorded"):
        return [SimpleNamespace(name=name, kind=kind) for name in names]

    train, val, test = parts("a", "b"), parts("c"), parts("d", "e")
    expected = parts("a", "b", "c", "d", "e", kind="expected")     # the same names: told apart by their kind
    targets = training_targets(train, val, test, expected)
    assert targets["recorded"] == (train, val)
    assert targets["expected"] == (expected[:2], expected[2:3])      # the same parts' expectation, not the test's
    assert targets["expected_test"] == (expected[3:], expected[3:])
    assert training_targets(train, val, test, []) == {"recorded": (train, val)}
    with pytest.raises(ValueError, match="not the training, validation and test parts"):
        training_targets(train, val, test, parts("a", "c", "b", "d", "e", kind="expected"))


@pytest.mark.parametrize("args, message", [
    (["--targets", "recorded,bogus"], "unknown target bogus"),
    (["--section-points", "4096"], "give --input sections+slices"), (["--twins", "0"], "1 or more"),
    (["--with-parameters", "taper"], "give --input sections+slices"),
    (["--input", "sections+slices", "--with-parameters", "taper,bogus"], "bogus: not a parameter of these parts"),
    (["--components", "5"], "give --input sections+slices"),
    (["--input", "sections+slices", "--components", "0"], "K of 1 or more"),
    (["--lead-in"], "give --input sections+slices"),
    (["--input", "sections+slices", "--lead-in", "--with-parameters", "taper"], "neither --with-parameters"),
    (["--bottleneck", "0"], "1 or more")])
def test_expected_head_refuses_what_it_cannot_run_before_any_work(args, message, tmp_path):
    done = run_here("expected_head.py", str(tmp_path / "rows.jsonl"), *args)
    assert done.returncode != 0 and message in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "rows.jsonl").exists()


def test_expected_head_config_is_the_paper_domains_where_one_is_named_else_the_familys_curve():
    sys.path.insert(0, str(ROOT / "experiments"))
    from expected_head import run_config

    paper = run_config("pins", "dsub", 3, ["head.hidden=32"])
    assert (paper.domain.name, list(paper.domain.test), paper.seed, paper.head.hidden) == ("dsub", ["dsub26"], 3, 32)
    assert paper.data.generate.get("family") is None                  # the embedded dataset: the catalogue's parts
    curve = run_config("rect", None, 1, [])
    assert (curve.domain.name, curve.data.generate.family, curve.seed) == ("curve_rect_100", "rect", 1)


def test_expected_head_hand_made_input_is_the_cross_section_and_slices_after_a_code_of_zeros(tiny_data, tmp_path):
    import torch

    from pipe.data.batches import stack_clouds, stack_slices
    from pipe.model.sections import SECTION_SIZE, SectionCode
    from pipe.model.slices import SliceCode
    from pipe.pipeline import build_model, load_domain

    sys.path.insert(0, str(ROOT / "experiments"))
    from expected_head import hand_made_codes

    cfg = smoke_config(tiny_data, tmp_path, "code.sections=true", "code.slices=true")
    data = load_domain(cfg)
    model = build_model(cfg, data)
    train, parts = data.splits["train"], data.splits["train"] + data.splits["val"] + data.splits["test"]
    width = model.encoder.latent_dim
    codes = hand_made_codes(model, parts, width)
    assert codes.shape == (len(parts), model.head.latent_dim)
    assert not codes[:, :width].any()               # no encoder: the code's part is zeros
    # the rest standardised over the training parts alone, as code.sections and code.slices give them
    sections = SectionCode.fitted(stack_clouds(train))(stack_clouds(parts))
    slices = SliceCode.fitted(stack_slices(train))(stack_slices(parts))
    assert torch.allclose(codes[:, width:width + SECTION_SIZE], sections)
    assert torch.allclose(codes[:, width + SECTION_SIZE:], slices.to(codes.dtype))
    assert not torch.equal(codes[0], codes[-1])      # the parts are told apart by them


def test_expected_head_with_parameters_fills_the_code_of_zeros_and_leaves_the_rest():
    import torch

    sys.path.insert(0, str(ROOT / "experiments"))
    from expected_head import with_parameters

    codes = torch.cat([torch.zeros(3, 4), torch.arange(6.0).view(3, 2)], dim=1)    # a code of 4 zeros, then 2
    parameters = torch.tensor([[1.0, -1.0], [2.0, -2.0], [3.0, -3.0]])
    filled = with_parameters(codes, parameters)
    assert torch.equal(filled[:, :2], parameters) and not filled[:, 2:4].any()
    assert torch.equal(filled[:, 4:], codes[:, 4:]) and not codes[:, :4].any()        # the input is not changed


@pytest.mark.parametrize("family, diameter, chamfer", [("dowel", 4.0, 0.6), ("taper", 4.0, 0.12),
                                                       ("taper", 16.0, 0.9), ("dowel", 20.0, 3.5)])
def test_lead_in_is_the_pins_chamfer_length_to_within_the_grids_step(family, diameter, chamfer):
    sys.path.insert(0, str(ROOT / "experiments"))
    from lead_in import GRID_RATIO, lead_in_length

    from pipe.synthetic.catalogue import Pin
    from pipe.synthetic.meshes import pin_mesh

    pin = Pin("p", family, diameter, 5 * diameter, 2.5 * diameter, taper=1 / 50 if family == "taper" else 0.0,
              chamfer=chamfer)
    measured = lead_in_length(pin_mesh(pin))
    assert chamfer <= measured <= chamfer * GRID_RATIO ** 2     # the first grid depth past the chamfer's end
    open_mesh = pin_mesh(pin)
    open_mesh.update_faces(open_mesh.face_normals[:, 2] > -0.9)    # the flat tip cut away: not watertight
    assert not open_mesh.is_watertight and lead_in_length(open_mesh) == measured


def test_lead_in_of_a_part_without_a_chamfer_is_the_grids_first_depth_and_of_a_cone_its_reach():
    import trimesh

    sys.path.insert(0, str(ROOT / "experiments"))
    from lead_in import FIRST_DEPTH_MM, REACH_MM, lead_in_length, section_widths

    box = trimesh.creation.box(extents=(8.0, 3.0, 20.0))
    assert lead_in_length(box) == FIRST_DEPTH_MM
    cone = trimesh.creation.cone(radius=10.0, height=20.0)     # apex up: the width shrinks from the base
    cone.apply_transform(trimesh.transformations.rotation_matrix(math.pi, [1.0, 0.0, 0.0]))   # apex down
    assert math.isclose(lead_in_length(cone), REACH_MM, rel_tol=0.05)
    widths = section_widths(box, [1.0, 19.0, 25.0])
    assert widths[:2] == pytest.approx([8.0, 8.0]) and widths[2] == 0.0       # beyond the part: nothing


@pytest.mark.parametrize("sides, corners", [(4, 4), (5, 5), (6, 0), (16, 0)])
def test_ring_corners_count_turns_sharper_than_the_threshold(sides, corners):
    import shapely

    sys.path.insert(0, str(ROOT / "experiments"))
    from section_corners import ring_corners

    # a regular polygon turns 360 / sides degrees at each vertex: a square's 90 and a pentagon's 72 are corners
    # (above 70), a hexagon's 60 and a 16-gon's 22.5 (a tessellated circle) are not
    ring = shapely.Point(0.0, 0.0).buffer(3.0, quad_segs=1).exterior if sides == 4 else shapely.LinearRing(
        [(3.0 * math.cos(2 * math.pi * k / sides), 3.0 * math.sin(2 * math.pi * k / sides)) for k in range(sides)])
    assert ring_corners(ring) == corners
    # vertices inserted every 0.1 mm along its sides (turns of 0) change nothing
    dense = shapely.LinearRing(shapely.segmentize(shapely.Polygon(ring), 0.1).exterior.coords)
    assert ring_corners(dense) == corners


@pytest.mark.parametrize("pads", [0, 1, 5])
def test_corner_descriptor_counts_a_tongues_pads_and_not_a_round_pin(pads):
    import trimesh

    sys.path.insert(0, str(ROOT / "experiments"))
    from section_corners import corner_descriptor

    from pipe.data.slices import SLICE_DEPTHS_MM

    # a 20 x 2 mm tongue 8 mm long with `pads` 1 mm pads 0.1 mm proud of its top face from 1 mm on: the pads
    # merge with the tongue in a section, whose outline turns through 4 corners plus 4 per pad (2 convex, 2
    # concave); at 0.5 mm the pads have not started, and 10 mm is beyond the part
    tongue = trimesh.creation.box(extents=(20.0, 2.0, 8.0), transform=trimesh.transformations.translation_matrix(
        (0.0, 0.0, 4.0)))
    parts = [tongue] + [trimesh.creation.box(extents=(1.0, 0.2, 7.0), transform=trimesh.transformations
                                             .translation_matrix((-8.0 + 3.0 * k, 1.0, 4.5))) for k in range(pads)]
    plug = trimesh.boolean.union(parts, engine="manifold") if pads else tongue
    counts = dict(zip(SLICE_DEPTHS_MM, map(round, map(math.expm1, corner_descriptor(plug)))))
    assert counts == {0.5: 4, 2.0: 4 + 4 * pads, 5.0: 4 + 4 * pads, 10.0: 0}
    pin = trimesh.creation.cylinder(radius=2.0, height=10.0, sections=16)     # a tessellated circle: no corner
    assert corner_descriptor(pin).tolist() == [0.0, 0.0, 0.0, 0.0]


def test_expected_head_bottleneck_makes_the_head_read_a_rank_k_view_of_its_input():
    import torch

    from pipe.plugins.head.gaussian import GaussianHead

    sys.path.insert(0, str(ROOT / "experiments"))
    from expected_head import with_bottleneck

    torch.manual_seed(0)
    head = GaussianHead(latent_dim=6, num_parameters=2, hidden=8)
    later = {k: v.clone() for k, v in head.state_dict().items() if not k.startswith("trunk.0.")}
    with_bottleneck(head, 2)
    assert all(torch.equal(head.state_dict()[k], v) for k, v in later.items())   # only the first layer changes
    z, depth_max = torch.randn(5, 6), torch.full((5,), 4.0)
    # an input moved along the map's null space gives the same profile: the head reads 2 numbers of the 6
    basis = torch.linalg.svd(head.trunk[0][0].weight.detach())[2]
    moved = z + 3.0 * basis[2:].sum(0)
    for a, b in zip(vars(head(z, depth_max)).values(), vars(head(moved, depth_max)).values()):
        assert torch.allclose(a, b, atol=1e-5)
    assert not torch.allclose(head(z, depth_max).amplitude, head(z + basis[0], depth_max).amplitude)


def test_expected_head_fixed_grid_keeps_the_neutral_sections_and_widths_and_learns_amplitudes():
    import torch

    from pipe.plugins.head.gaussian import GaussianHead

    sys.path.insert(0, str(ROOT / "experiments"))
    from expected_head import with_fixed_grid

    torch.manual_seed(0)
    head = GaussianHead(latent_dim=6, num_parameters=2, hidden=8)
    with_fixed_grid(head)
    depth_max = torch.tensor([4.0, 4.0])
    profile = head(torch.randn(2, 6), depth_max)
    neutral = head.profile(*(torch.zeros(2, 2, head.n),) * 3, depth_max)
    assert torch.allclose(profile.centre, neutral.centre) and torch.allclose(profile.width, neutral.width)
    assert not torch.allclose(profile.amplitude[0], profile.amplitude[1])          # the amplitudes follow z
    trainable = {name for name, p in head.named_parameters() if p.requires_grad}
    assert "section.2.weight" not in trainable and "width.2.bias" not in trainable and "amplitude.2.weight" in trainable


def test_expected_head_standardised_log_is_standardised_over_the_training_parts():
    import numpy as np

    sys.path.insert(0, str(ROOT / "experiments"))
    from expected_head import standardised_log

    values = np.array([1.0, math.e, math.e ** 2, 100.0])
    logs = standardised_log(values, 3)
    assert logs.shape == (4, 1) and logs[:3, 0].tolist() == pytest.approx([-1.0, 0.0, 1.0])
    assert logs[3, 0].item() == pytest.approx(math.log(100.0) - 1.0)


def test_expected_head_principal_input_is_the_measures_standardised_components_in_the_codes_place():
    import torch
    from sklearn.decomposition import PCA

    sys.path.insert(0, str(ROOT / "experiments"))
    from expected_head import principal_input

    generator = torch.Generator().manual_seed(0)
    measures = torch.randn(12, 3, generator=generator) @ torch.tensor([[3.0, 0.0, 0.0], [1.0, 1.0, 0.0],
                                                                       [0.0, 0.0, 0.1]])
    codes = torch.cat([torch.zeros(12, 4), measures], dim=1)       # a code of 4 zeros, then 3 measures
    compact = principal_input(codes, 8, 4, 2)                      # the first 8 parts are the training parts
    assert compact.shape == codes.shape and not compact[:, 2:].any()
    train = compact[:8, :2].double()
    assert torch.allclose(train.mean(0), torch.zeros(2, dtype=torch.float64), atol=1e-6)
    assert torch.allclose(train.std(0), torch.ones(2, dtype=torch.float64), atol=1e-5)
    # scikit-learn's principal components of the training measures, the largest first, each over its spread
    pca = PCA(n_components=2).fit(measures[:8].numpy())
    expected = torch.from_numpy(pca.transform(measures.numpy()) / pca.explained_variance_ ** 0.5)
    assert torch.allclose(compact[:, :2].double().abs(), expected.double().abs(), atol=1e-4)  # up to each one's sign


def test_family_twins_count_test_pins_of_a_training_pins_type_and_diameter_and_of_its_length_too():
    from pipe.synthetic.catalogue import Pin

    sys.path.insert(0, str(ROOT / "experiments"))
    from family_twins import twin_counts

    def pin(family, diameter, length):
        return Pin(f"{family}{diameter}x{length}", family, diameter, length, length / 2)

    train = [pin("dowel", 5.0, 20.0), pin("taper", 6.0, 30.0)]
    test = [pin("dowel", 5.0, 20.0),        # the same size and length: counted twice
            pin("dowel", 5.0, 24.0),        # the same size, another length
            pin("dowel", 6.0, 30.0),        # a taper pin's size, but a dowel: neither
            pin("taper", 8.0, 30.0)]        # another diameter: neither
    assert twin_counts(test, train) == (2, 1)
    assert twin_counts(test, []) == (0, 0)


def test_expected_head_mesh_clouds_are_the_pipelines_clouds_and_replace_the_cross_section_alone(tiny_data, tmp_path):
    import torch

    from pipe.data.batches import stack_clouds
    from pipe.model.sections import SECTION_SIZE, SectionCode
    from pipe.pipeline import build_model, load_domain

    sys.path.insert(0, str(ROOT / "experiments"))
    from expected_head import hand_made_codes, mesh_clouds, with_sections_of

    cfg = smoke_config(tiny_data, tmp_path, "code.sections=true", "code.slices=true")
    data = load_domain(cfg)
    parts = data.splits["train"] + data.splits["test"]
    # at the pipeline's number of points the mesh's sample is each part's own cloud
    same = mesh_clouds(data.dataset_dir, parts, int(cfg.data.points), int(cfg.data.cloud_seed))
    assert torch.allclose(same, stack_clouds(parts), atol=1e-5)
    dense = mesh_clouds(data.dataset_dir, parts, 4 * int(cfg.data.points), int(cfg.data.cloud_seed))
    assert dense.shape == (len(parts), 4 * int(cfg.data.points), 3)
    model = build_model(cfg, data)
    width, train = model.encoder.latent_dim, len(data.splits["train"])
    codes = hand_made_codes(model, parts, width)
    replaced = with_sections_of(codes, dense, train, width)
    section = slice(width, width + SECTION_SIZE)
    assert torch.allclose(replaced[:, section], SectionCode.fitted(dense[:train])(dense))
    assert not torch.allclose(replaced[:, section], codes[:, section])        # another cloud, another cross-section
    assert torch.equal(replaced[:, :width], codes[:, :width]) and torch.equal(replaced[:, width + SECTION_SIZE:],
                                                                              codes[:, width + SECTION_SIZE:])


def test_expected_head_twin_targets_pool_each_part_with_its_first_twins_trials():
    from pipe.data.prepared import PartData

    sys.path.insert(0, str(ROOT / "experiments"))
    from expected_head import twin_targets

    def parts(stream, *names):
        return [PartData(name, None, [f"{name}:{stream}"], [None]) for name in names]

    train, val = parts("own", "a", "b"), parts("own", "c")
    twins = [parts(k, "a", "b", "c") for k in (1, 2, 3)]
    targets = twin_targets(train, val, twins, [1, 3])
    assert list(targets) == ["twins=1", "twins=3"]
    one_train, one_val = targets["twins=1"]
    assert [p.name for p in one_train] == ["a", "b"] and [p.name for p in one_val] == ["c"]
    assert one_train[1].profiles == ["b:own", "b:1"] and one_val[0].profiles == ["c:own", "c:1"]
    three_train, _ = targets["twins=3"]
    assert three_train[0].profiles == ["a:own", "a:1", "a:2", "a:3"]
    assert len(three_train[0].static_curves) == 4
    assert twin_targets(train, val, twins, []) == {}


def test_extrapolation_distance_ratio_and_table_by_hand():
    import torch
    sys.path.insert(0, str(ROOT / "experiments"))
    from extrapolation import distance_ratio, held_out_coverage, table

    # parts at 0, 1, 3 and 7 on a line: nearest others 1, 1, 2 and 4, their median 1.5
    codes = torch.tensor([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0], [7.0, 0.0]])
    assert distance_ratio(codes).tolist() == pytest.approx([2 / 3, 2 / 3, 4 / 3, 8 / 3])
    # held out in turn: 0 is 1 from {1, 3, 7}, whose radius is 4; 1 is 1 from {0, 3, 7} (4); 3 is 2 from
    # {0, 1, 7} (6); 7 is 4 from {0, 1, 3} (2)
    assert held_out_coverage(codes) == pytest.approx([1 / 4, 1 / 4, 1 / 3, 2.0])
    rows = [{"run": "runs/conn/seed_0", "part": "rj45", "ratio": 3.0, "coverage": 1.5, "fit": -100.0},
            {"run": "runs/conn/seed_1", "part": "rj45", "ratio": 2.0, "coverage": 0.9, "fit": -50.0},
            {"run": "runs/conn/seed_0", "part": "vga", "ratio": 0.5, "coverage": 0.2, "fit": 80.0}]
    lines = table(rows).splitlines()
    assert lines[2:4] == ["| conn | rj45 | 2.50 | 1.20 | -75.00 | 2 |", "| conn | vga | 0.50 | 0.20 | 80.00 | 1 |"]
    assert lines[-1] == "Above the coverage radius: 1 of 3 held-out cases; rj45 (conn, FIT -100.0)"


def test_extrapolation_force_summary_by_hand():
    import numpy as np
    sys.path.insert(0, str(ROOT / "experiments"))
    from extrapolation import force_summary

    # peaks of |F| 2 and 1, means -1/3 and 1
    summary = force_summary([np.array([0.0, -2.0, 1.0]), np.array([1.0, 1.0, 1.0])])
    assert summary == pytest.approx({"peak": 1.5, "mean": 1 / 3})


@pytest.mark.slow
def test_extrapolation_rows_match_part_cv_on_the_same_folds(trained_run, tmp_path):
    cv_file, ratio_file, forces_file = tmp_path / "cv.jsonl", tmp_path / "ratio.jsonl", tmp_path / "forces.jsonl"
    run = str(trained_run.run_dir)
    run_script("part_cv.py", str(cv_file), run, "--variants", "default")
    run_script("extrapolation.py", str(ratio_file), run, "--cv", str(cv_file))
    run_script("extrapolation.py", str(forces_file), run, "--forces", "vga")
    cv = {row["held_out"]: row for row in map(json.loads, cv_file.read_text().splitlines())}
    ratios = [json.loads(line) for line in ratio_file.read_text().splitlines()]
    # every non-test part once, with its cross-validated FIT; of three parts the middle one is the median
    assert {row["part"]: row["fit"] for row in ratios} == {part: row["fit"] for part, row in cv.items()}
    assert sorted(row["ratio"] for row in ratios)[1] == pytest.approx(1.0)
    # the folds trained again give part_cv's FIT for PIPE and `nearest`
    (forces,) = [json.loads(line) for line in forces_file.read_text().splitlines()]
    assert forces["part"] == "vga" and forces["measured"]["peak"] > 0
    assert forces["pipe"]["fit"] == pytest.approx(cv["vga"]["fit"], abs=1e-9)
    assert forces["nearest"]["fit"] == pytest.approx(cv["vga"]["nearest"], abs=1e-9)


def test_oracle_loss_table_gives_the_share_of_the_gap_to_each_oracle_and_where_pipe_is_above_it(tmp_path):
    """Hand-computed, two seeds, one part: PIPE 70 and 74 (72 ± 2.83), `nearest` 60; the curve's own oracle 80
    closes (72 - 60) / (80 - 60) = 60 % of the gap, and PIPE is above it in no seed; the refitted oracle 90 and
    96 (93 ± 4.24) closes 12 / 33 = 36.4 %."""
    curve = tmp_path / "curve.jsonl"
    curve.write_text("".join(json.dumps({
        "run": f"runs/curve/rect/train_100/seed_{seed}", "train_parts": 100, "extra": [],
        "fit_F": {"pipe": {"rect_0000": pipe}, "nearest": {"rect_0000": 60.0}, "oracle": {"rect_0000": 80.0}}})
        + "\n" for seed, pipe in ((0, 70.0), (1, 74.0))))
    rows = [{"family": "rect", "seed": seed, "identification": "nmse_via_mse", "target": "force", "extra": [],
             "fit_F": oracle, "parts": {"rect_0000": oracle}} for seed, oracle in ((0, 90.0), (1, 96.0))]
    printed = printed_table("oracle_loss.py", rows, tmp_path, "--table", "--curve", str(curve))
    spread = statistics.stdev([90.0, 96.0])
    assert f"| rect | force | nmse_via_mse | test | 93.00 ± {spread:.2f} (2 seeds) |" in printed
    assert ("| rect | test 20 | 100 | 72.00 ± 2.83 | 60.00 ± 0.00 | 80.00 ± 0.00 (mse, the curve's runs) | 60.0 % "
            "| 0/0 |") in printed
    assert f"| 93.00 ± {spread:.2f} (nmse_via_mse) | 36.4 % | 0/0 |" in printed
    parts = printed_table("oracle_loss.py", rows, tmp_path, "--table", "--curve", str(curve), "--parts",
                          "rect_0000", "--seeds", "1")
    assert "| rect_0000 | 80.00 | 96.00 |" in parts


def test_oracle_loss_on_a_larger_dataset_identifies_only_the_parts_after_the_curves(tmp_path):
    """`--dataset`: the parts numbered from the curve's 130 on become the test split, read from that dataset;
    a dataset without such parts is refused."""
    sys.path.insert(0, str(ROOT / "experiments"))
    from common import on_larger_dataset
    from twin_oracle import family_config
    for name in ("rect_0000", "rect_0129", "rect_0130", "rect_0131", "pins_0000"):
        (tmp_path / "parts" / name).mkdir(parents=True)
    cfg = family_config("rect", 0)
    on_larger_dataset(cfg, tmp_path, "test", keep=False)
    assert list(cfg.domain.test) == ["rect_0130", "rect_0131"]
    assert cfg.data.dir == str(tmp_path) and cfg.data.generate.count == 132
    assert "rect_0130" not in [*cfg.domain.train, *cfg.domain.val]
    with pytest.raises(SystemExit, match="no pins parts numbered from 130"):
        on_larger_dataset(family_config("pins", 0), tmp_path, "test")


def test_oracle_loss_table_joins_the_extra_parts_oracle_to_the_test_parts(tmp_path):
    """Hand-computed, one seed: 20 test parts (PIPE 70, `nearest` 60, oracle 90) and one extra part identified
    in a row of its own (`--dataset`: PIPE 50, `nearest` 40, oracle 60). On the test 20 PIPE closes 10 / 30 =
    33.3 % of the gap, on the extra part 10 / 20 = 50 %, on all 21 (210 / 21) / (620 / 21) = 33.9 %, which
    needs both rows' parts."""
    test = [f"rect_{i:04d}" for i in range(20)]
    fits = {name: {p: value for p in test} | {"rect_0130": extra}
            for name, value, extra in (("pipe", 70.0, 50.0), ("nearest", 60.0, 40.0), ("oracle", 80.0, 45.0))}
    curve = tmp_path / "curve.jsonl"
    curve.write_text(json.dumps({"run": "runs/curve/rect/train_100/seed_0", "train_parts": 100,
                                 "extra": ["rect_0130"], "fit_F": fits}) + "\n")
    common = {"family": "rect", "seed": 0, "identification": "nmse_via_mse", "target": "force"}
    rows = [common | {"held_out": "test", "fit_F": 90.0, "parts": dict.fromkeys(test, 90.0)},
            common | {"held_out": "extra", "fit_F": 60.0, "parts": {"rect_0130": 60.0}}]
    printed = printed_table("oracle_loss.py", rows, tmp_path, "--table", "--curve", str(curve))
    assert "| rect | force | nmse_via_mse | extra | 60.00" in printed
    assert ("| rect | test 20 | 100 | 70.00 ± 0.00 | 60.00 ± 0.00 | 90.00 ± 0.00 (nmse_via_mse) | 33.3 % "
            "| 0 |") in printed
    assert ("| rect | extra 1 | 100 | 50.00 ± 0.00 | 40.00 ± 0.00 | 60.00 ± 0.00 (nmse_via_mse) | 50.0 % | 0 "
            "| 50.0 % |") in printed
    assert "| rect | all 21 | 100 |" in printed and "(nmse_via_mse) | 33.9 % | 0 | 33.9 % |" in printed


def test_identification_ridge_table_gives_each_ridges_static_errors_and_fit(tmp_path):
    """Hand-computed, two parts: static errors 0.1 and 0.5 (largest 0.5, one above 0.3, median 0.3), FIT(F) 90
    and 70 (mean 80, lowest b); a later row of the same domain, settings and ridge replaces the earlier one,
    rows of other settings stay."""
    row = {"domain": "pins", "ridge": 0.1, "settings": "", "seed": 0, "seconds": 12.4,
           "fit_F": {"a": 90.0, "b": 70.0}, "static_rms_rel": {"a": 0.1, "b": 0.5},
           "id_evals": {"a": 300.0, "b": 500.0}}
    earlier = row | {"fit_F": {"a": 0.0, "b": 0.0}}
    smaller = row | {"ridge": 0.03, "static_rms_rel": {"a": 0.2, "b": 0.2}}
    pooled = row | {"settings": "loss=mse"}
    printed = printed_table("identification_ridge.py", [earlier, row, smaller, pooled], tmp_path, "--table")
    lines = [line for line in printed.splitlines() if line.startswith("| pins")]
    assert lines == ["| pins | default | 0.03 | 2 | 12 | 0.200 | 0 | 0.200 | 80.00 | 70.00 (b) |",
                     "| pins | default | 0.1 | 2 | 12 | 0.500 | 1 | 0.300 | 80.00 | 70.00 (b) |",
                     "| pins | loss=mse | 0.1 | 2 | 12 | 0.500 | 1 | 0.300 | 80.00 | 70.00 (b) |"]


def test_gpr_cv_pairs_pipes_folds_with_gprs_seed_by_seed(tmp_path):
    gpr = [{"run": f"runs/pins/seed_{s}", "candidate": "force_weight_0", "held_out": p, "gpr": v,
            "gpr_likelihood": 0.0, "gpr_hindsight": 0.0} for s, p, v in ((0, "a", 10.0), (0, "b", 30.0),
                                                                         (1, "a", 50.0), (1, "b", 50.0))]
    pipe = [{"run": f"runs/pins/seed_{s}", "variant": "default", "held_out": p, "fit": v, "nearest": 0.0}
            for s, p, v in ((0, "a", 40.0), (0, "b", 20.0), (1, "a", 45.0), (1, "b", 65.0))]
    pipe_file = tmp_path / "pipe.jsonl"
    pipe_file.write_text("".join(json.dumps(row) + "\n" for row in pipe))
    printed = printed_table("gpr_cv.py", gpr, tmp_path, "--table", "--pipe", str(pipe_file))
    # per seed: PIPE 30, 55; gpr 20, 50; differences +10, +5; PIPE above gpr in 2 of 4 cases (40 > 10, 65 > 50)
    sd = statistics.stdev
    assert (f"| pins | 42.50 ± {sd([30, 55]):.2f} | 35.00 ± {sd([20, 50]):.2f} | +10.00, +5.00 | "
            f"7.50 ± {sd([10, 5]):.2f} | 2 of 4 |") in printed


def test_kernel_choice_table_shows_one_line_per_distinct_result_of_a_settings_repeats(tmp_path):
    """Two repeats alike give one line and `yes`; two that differ give a line each and `no (2 results)`; runs
    with overrides are their own group, and so are runs of one setting on other kernels (another host)."""
    def row(setting, kernels, fit, loss, overrides=()):
        return {"domain": "dsub", "seed": 0, "overrides": list(overrides), "setting": setting, "kernels": kernels,
                "fit_F": fit, "parts": {"dsub26": {"fit_F": fit, "id_loss": loss, "id_evals": 100.0}}}

    native, generic = "torch AVX2, numba znver3", "torch AVX2, numba generic"
    rows = [row("native", native, 89.87905, 3.8177321), row("native", native, 89.87905, 3.8177321),
            row("numba=generic", generic, 88.5, 4.25), row("numba=generic", generic, 87.25, 4.5),
            row("native", native, 80.0, 9.0, ["evaluation.identification.restarts=1"]),
            row("native", "torch AVX512, numba znver5", 88.0, 4.0)]
    lines = printed_table("kernel_choice.py", rows, tmp_path, "--table").splitlines()
    assert lines[2:] == [
        f"| dsub | 0 | native | {native} | yes | 89.8791 | dsub26 89.8791 (3.81773) |",
        f"| dsub | 0 | numba=generic | {generic} | no (2 results) | 88.5000 | dsub26 88.5000 (4.25) |",
        f"| dsub | 0 | numba=generic | {generic} | no (2 results) | 87.2500 | dsub26 87.2500 (4.5) |",
        f"| dsub evaluation.identification.restarts=1 | 0 | native | {native} | yes | 80.0000 | dsub26 80.0000 (9) |",
        "| dsub | 0 | native | torch AVX512, numba znver5 | yes | 88.0000 | dsub26 88.0000 (4) |"]


def test_kernel_choice_refuses_an_unknown_setting_before_any_work(tmp_path):
    done = run_here("kernel_choice.py", str(tmp_path / "rows.jsonl"), "--settings", "native", "numba")
    assert done.returncode == 1
    assert "unknown kernel setting 'numba': give native, or numba=<cpu>, torch=<level>, openblas=<core>" in done.stderr
    assert not (tmp_path / "rows.jsonl").exists()


@pytest.mark.slow
def test_kernel_choice_runs_each_setting_in_a_process_with_its_kernels(tmp_path, monkeypatch):
    """dsub's oracle from one start: the native run repeats itself to the digit, and each row records the
    kernels its process ran on (numba compiled for `generic` and OpenBLAS on Sandybridge's kernels where the
    setting asks for them; `native` as a process without the switches reads them, which may not be this
    one's: a host's environment can set OPENBLAS_CORETYPE for every process)."""
    monkeypatch.syspath_prepend(str(EXPERIMENTS))
    from kernel_choice import VARIABLES

    native_kernels = subprocess.run(
        [sys.executable, "-c", "from pipe.machine import cpu_kernels; print(cpu_kernels())"], capture_output=True,
        text=True, env={k: v for k, v in os.environ.items() if k not in VARIABLES.values()}, timeout=120).stdout.strip()
    rows_file = tmp_path / "rows.jsonl"
    overrides = ["evaluation.identification.restarts=1", f"data.dir={tmp_path / 'data'}"]
    lowered = "numba=generic,openblas=Sandybridge"
    run_script("kernel_choice.py", str(rows_file), "--domain", "dsub", "--settings", "native", lowered,
               "--repeat", "2", "--override", *overrides)
    rows = [json.loads(line) for line in rows_file.read_text().splitlines()]
    assert [(row["setting"], row["repeat"]) for row in rows] == [("native", 0), (lowered, 0), ("native", 1),
                                                                  (lowered, 1)]
    assert rows[0]["kernels"] == native_kernels and "numba generic, openblas Sandybridge" in rows[1]["kernels"]
    assert rows[0]["parts"] == rows[2]["parts"] and list(rows[0]["parts"]) == ["dsub26"]
    assert 0 < rows[0]["fit_F"] < 100 and rows[0]["overrides"] == overrides
