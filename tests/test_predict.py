"""predict.py: a new part's Theta(p_z) and force from its mesh and a model in MLflow."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
import trimesh
from conftest import ROOT, run_noting_imports


def run_predict(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "predict.py"), *args], capture_output=True, text=True,
                          timeout=300, cwd="/", env=os.environ)


def test_predict_names_what_it_must_be_given_and_a_wrong_ramp_before_reading_the_model(tmp_path):
    missing = run_predict("mesh=part.stl", f"hydra.run.dir={tmp_path / 'a'}")
    assert missing.returncode == 2 and "Traceback" not in missing.stderr
    assert "error: run= must be given, e.g. python predict.py mesh=part.stl run=" in missing.stderr
    ramp = run_noting_imports("predict.py", "mesh=part.stl", "run=no-such-run", "ramp.speed_mm_s=0",
                              f"hydra.run.dir={tmp_path / 'b'}", cwd=tmp_path)
    assert ramp.returncode == 2 and "Traceback" not in ramp.stderr
    assert "error: ramp.speed_mm_s takes a number, above 0, not 0" in ramp.stderr
    assert ramp.stdout.strip() == "[]"      # refused before torch and MLflow load


@pytest.mark.slow
def test_predict_on_real_meshes_in_both_units(trained_run, real_meshes, tmp_path):
    for name in ("labit_positioning_pin_d5_20.stl", "factory_round_peg_8mm_tight.obj"):
        mesh = next(p for p in real_meshes if p.name == name)
        out = tmp_path / name
        result = run_predict(f"mesh={mesh}", f"run={trained_run.mlflow_run_id}", f"hydra.run.dir={out}")
        assert result.returncode == 0, result.stderr[-3000:]
        assert ("read in mm" if name.endswith(".stl") else "read in m ") in result.stdout
        theta = np.genfromtxt(out / "theta.csv", delimiter=",", names=True)
        names = ("a0", "a1", "a2", "b0")
        assert theta.dtype.names == ("p_z", *names, *(f"{n}_lower" for n in names), *(f"{n}_upper" for n in names))
        assert np.all(np.isfinite(theta.view((float, 13)))) and np.all(theta["a2"] > 0)
        assert all(np.all(theta[f"{n}_lower"] <= theta[f"{n}_upper"]) for n in names)
        force = np.genfromtxt(out / "force.csv", delimiter=",", names=True)
        assert force["p_z"].max() == pytest.approx(json.loads((out / "theta.json").read_text())["depth_mm"][-1])
        assert np.all(np.isfinite(force["F_z"])) and (out / "prediction.png").is_file()
        doc = json.loads((out / "theta.json").read_text())
        assert len(doc["local_models"]["b0"]["centre_mm"]) == 10
        # the force band: the latent band widened by the offset the training run calibrated
        offset = trained_run.card.band.offset_n
        assert doc["band"]["calibrated_offset_N"] == pytest.approx(offset) and offset > 0
        assert np.all(force["F_z_upper"] - force["F_z_lower"] >= 2 * offset - 1e-4)


def test_predict_follows_a_given_trajectory(trained_run, real_meshes, tmp_path):
    trajectory = tmp_path / "traj.csv"
    t = np.arange(0, 2.0, 0.01)
    np.savetxt(trajectory, np.column_stack([t, 3 * np.clip(t, 0, 1)]), delimiter=",", header="t,p_z", comments="")
    mesh = next(p for p in real_meshes if p.name == "labit_positioning_pin_d5_20.stl")
    result = run_predict(f"mesh={mesh}", "run=models:/pipe-tiny/latest", f"trajectory={trajectory}",
                         f"hydra.run.dir={tmp_path / 'out'}")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "Downloading artifacts" not in result.stderr + result.stdout    # MLflow's bars, before its own output
    force = np.genfromtxt(tmp_path / "out" / "force.csv", delimiter=",", names=True)
    assert force["p_z"].max() == pytest.approx(3.0) and force["t"][-1] == pytest.approx(1.98, abs=0.03)


@pytest.mark.slow
def test_predict_errors_are_clear(trained_run, real_meshes, tmp_path):
    mesh = next(p for p in real_meshes if p.name == "labit_nut_tube.stl")
    cases = [
        ([f"mesh={tmp_path / 'missing.stl'}", f"run={trained_run.mlflow_run_id}"], "mesh file does not exist"),
        ([f"mesh={mesh}", "run=0123456789abcdef"], "no trained model at runs:/0123456789abcdef/model"),
    ]
    micrometres = tmp_path / "part_um.stl"
    trimesh.load(mesh).apply_scale(1000.0).export(micrometres)   # a part stored in micrometres
    cases.append(([f"mesh={micrometres}", f"run={trained_run.mlflow_run_id}"], "once read in mm"))
    for args, message in cases:
        result = run_predict(*args, f"hydra.run.dir={tmp_path / 'x'}")
        assert result.returncode == 2, result.stdout
        assert message in " ".join(result.stderr.split()) and "Traceback" not in result.stderr
    told = run_predict(f"mesh={micrometres}", "units=micron", f"run={trained_run.mlflow_run_id}",
                       f"hydra.run.dir={tmp_path / 'y'}")
    assert told.returncode == 0 and "read in micron" in told.stdout and "warning: the part is" not in told.stdout
    # a unit the user states is trusted, but a size far from the training parts is flagged
    wrong = run_predict(f"mesh={mesh}", "units=m", f"run={trained_run.mlflow_run_id}",
                        f"hydra.run.dir={tmp_path / 'z'}")
    assert wrong.returncode == 0 and "warning: the part is 1.848e+04 mm large" in " ".join(wrong.stdout.split())


def predict_config(mesh: str):
    from hydra import compose, initialize_config_module

    with initialize_config_module(config_module="pipe.conf", version_base="1.3"):
        return compose("predict", overrides=[f"mesh={mesh}", "run=unused"])


def test_a_batch_of_meshes_predicts_what_each_mesh_alone_does(trained_run, real_meshes):
    from pipe.predict import mesh_files, predict_with

    names = ("labit_positioning_pin_d5_20.stl", "factory_round_peg_8mm_tight.obj", "labit_pin_pcb.stl")
    meshes = [p for p in real_meshes if p.name in names]
    cfg = predict_config("[" + ",".join(str(m) for m in meshes) + "]")
    assert mesh_files(cfg.mesh) == meshes
    batch = predict_with(trained_run.model, trained_run.card, cfg, meshes)
    for mesh, together in zip(meshes, batch):
        alone = predict_with(trained_run.model, trained_run.card, cfg, [mesh])[0]
        assert together.mesh == mesh and together.notes == alone.notes
        for field in ("force", "theta", "force_band", "theta_band"):   # float32 sums of another batch size
            np.testing.assert_allclose(getattr(together, field), getattr(alone, field), rtol=1e-4, atol=1e-4)
    assert not np.allclose(batch[0].force, batch[1].force)      # three parts, three predictions


def test_predict_tells_how_far_a_part_is_from_the_training_parts(trained_run, tiny_data, real_meshes, tmp_path):
    """The card holds what the head read of each training part; a training part's own mesh is at 0 of the coverage
    radius, and a real pin's distance to the tiny model's two D-subs is the brute-force one over their distance."""
    from pipe.predict import predict_with, sample_mesh, write_predictions

    card = trained_run.card
    reference = np.array(card.reference_codes)
    expected = np.stack([trained_run.latents[trained_run.index[name]].numpy() for name in card.train_parts])
    assert card.train_parts == ("dsub9", "dsub15")
    np.testing.assert_allclose(reference, expected, rtol=1e-6, atol=1e-7)
    pin = next(p for p in real_meshes if p.name == "labit_positioning_pin_d5_20.stl")
    meshes = [tiny_data / "parts" / "dsub9" / "mesh.stl", pin]
    cfg = predict_config("[" + ",".join(str(m) for m in meshes) + "]")
    own, new = predict_with(trained_run.model, card, cfg, meshes)
    assert own.novelty.nearest == "dsub9" and own.novelty.ratio < 1e-5 and not own.novelty.extrapolates
    cloud = sample_mesh(pin, cfg, card)[0]
    code = trained_run.model.latent(torch.from_numpy(cloud.points[None]), torch.from_numpy(cloud.slices[None]))
    distances = np.linalg.norm(reference - code.numpy(), axis=1)
    radius = np.linalg.norm(reference[0] - reference[1])
    assert new.novelty.nearest == card.train_parts[distances.argmin()]
    assert new.novelty.ratio == pytest.approx(distances.min() / radius, rel=1e-5)
    assert new.novelty.extrapolates
    assert new.notes[-1].startswith(f"warning: nearest training part {new.novelty.nearest} at")

    written = write_predictions([own, new], tmp_path, "runs:/x/model")
    with open(tmp_path / "predictions.csv", newline="") as file:
        rows = list(csv.DictReader(file))
    assert [row["nearest_training_part"] for row in rows] == ["dsub9", new.novelty.nearest]
    assert float(rows[1]["novelty_ratio"]) == pytest.approx(new.novelty.ratio, rel=1e-3)
    assert "extrapolates" in rows[1]["notes"] and "extrapolates" not in rows[0]["notes"]
    doc = json.loads(next(p for p in written if p.name == "theta.json" and pin.stem in str(p)).read_text())
    assert doc["novelty"]["extrapolates"] is True and doc["novelty"]["ratio"] == pytest.approx(new.novelty.ratio)


def test_mesh_files_reads_a_folder_a_list_or_a_file(tmp_path):
    from pipe.errors import PipeError
    from pipe.predict import mesh_files, output_names

    for name in ("b.stl", "a.obj", "a.STL", "notes.txt"):
        (tmp_path / name).write_text("")
    assert [p.name for p in mesh_files(str(tmp_path))] == ["a.STL", "a.obj", "b.stl"]
    assert output_names(mesh_files(str(tmp_path))) == ["a.STL", "a.obj", "b"]
    assert mesh_files([str(tmp_path / "b.stl")]) == [tmp_path / "b.stl"] == mesh_files(str(tmp_path / "b.stl"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(PipeError, match="empty: folder holds no mesh files"):
        mesh_files(str(tmp_path / "empty"))
    # a missing file is named before the model is read (it was after, once the run's artifacts had come down)
    with pytest.raises(PipeError, match="missing.stl: mesh file does not exist"):
        mesh_files([str(tmp_path / "b.stl"), str(tmp_path / "missing.stl")])


@pytest.mark.slow
def test_predict_screens_a_folder_of_meshes(trained_run, real_meshes, tmp_path):
    library = tmp_path / "library"
    library.mkdir()
    for name in ("labit_positioning_pin_d5_20.stl", "labit_pin_pcb.stl", "factory_round_peg_8mm_tight.obj"):
        (library / name).symlink_to(next(p for p in real_meshes if p.name == name))
    out = tmp_path / "out"
    result = run_predict(f"mesh={library}", "run=models:/pipe-tiny/latest", f"hydra.run.dir={out}")
    assert result.returncode == 0, result.stderr[-3000:]
    rows = np.genfromtxt(out / "predictions.csv", delimiter=",", names=True, dtype=None, encoding=None)
    assert list(rows["folder"]) == ["factory_round_peg_8mm_tight", "labit_pin_pcb", "labit_positioning_pin_d5_20"]
    for row in rows:
        force = np.genfromtxt(out / row["folder"] / "force.csv", delimiter=",", names=True)
        assert row["peak_force_N"] == pytest.approx(force["F_z"].max(), rel=1e-4)
        assert (out / row["folder"] / "prediction.png").is_file()

    (library / "broken.stl").write_text("solid broken\nendsolid broken\n")
    failed = run_predict(f"mesh={library}", "run=models:/pipe-tiny/latest", f"hydra.run.dir={tmp_path / 'out2'}")
    assert failed.returncode == 2 and "broken.stl" in failed.stderr and "Traceback" not in failed.stderr
    assert not (tmp_path / "out2" / "predictions.csv").exists()
