"""The mesh's slices near its mating end beside the code (code.slices): the descriptor against values worked out
by hand and on real CAD, its standardisation, the way it travels from the mesh through the prepared parts into
the code PIPE and the baselines read, prediction from a mesh, and the settings a trained folder keeps."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch
import trimesh
from conftest import smoke_config

from pipe.data.batches import stack_geometry, stack_slices
from pipe.data.mesh import load_mesh, orient
from pipe.data.preprocess import cloud_from_mesh
from pipe.data.slices import FLOOR, SLICE_DEPTHS_MM, SLICE_SIZE, slice_descriptor
from pipe.errors import DatasetError, PipeError
from pipe.evaluation.context import EvalContext
from pipe.evaluation.methods import METHODS, code_blocks, code_inputs
from pipe.model.sections import SECTION_SIZE
from pipe.model.slices import SliceCode
from pipe.model.standardiser import MIN_SPREAD
from pipe.pipeline import build_components, build_model, load_domain, run_domain


def tube_with_two_pins(n: int = 16) -> trimesh.Trimesh:
    """A tube (radii 4 and 5, z 0 to 20) with two pins (radius 1, z 1 to 15) inside, as n-gons."""
    tube = trimesh.creation.annulus(4.0, 5.0, 20.0, sections=n).apply_translation((0.0, 0.0, 10.0))
    pins = [trimesh.creation.cylinder(1.0, 14.0, sections=n).apply_translation((x, 0.0, 8.0)) for x in (-2.0, 2.0)]
    return trimesh.util.concatenate([tube, *pins])


def test_slices_count_a_shells_pins_apart_and_measure_their_outlines():
    """0.5 mm up the plane cuts the tube's ring alone, 2 and 5 mm up the ring and both pins, three regions; the
    lengths and areas are the 16-gons' (perimeter 2 n r sin(pi / n), area n r^2 sin(2 pi / n) / 2). A mesh 8 mm
    long has no section 10 mm up: no region, the floors."""
    n = 16
    perimeter = {r: 2 * n * r * math.sin(math.pi / n) for r in (1.0, 4.0, 5.0)}
    area = {r: n * r * r * math.sin(2 * math.pi / n) / 2 for r in (1.0, 4.0, 5.0)}
    ring = (math.log(2), math.log(perimeter[5.0] + perimeter[4.0]), math.log(area[5.0] - area[4.0]))
    ring_and_pins = (math.log(4), math.log(perimeter[5.0] + perimeter[4.0] + 2 * perimeter[1.0]),
                     math.log(area[5.0] - area[4.0] + 2 * area[1.0]))
    found = slice_descriptor(tube_with_two_pins(n), (0.5, 2.0, 5.0))
    assert found == pytest.approx(np.array(ring + ring_and_pins + ring_and_pins), abs=1e-9)
    short = trimesh.creation.cylinder(1.0, 8.0, sections=n)
    assert slice_descriptor(short, (10.0,)) == pytest.approx([0.0, math.log(FLOOR), math.log(FLOOR)])
    assert slice_descriptor(short).shape == (SLICE_SIZE,) and SLICE_SIZE == 3 * len(SLICE_DEPTHS_MM)


def stepped_shaft(shoulder_mm: float, n: int = 16) -> trimesh.Trimesh:
    """A shaft of radius 1 from z 0 to `shoulder_mm`, then a collar of radius 3 to z 5, as n-gons."""
    outline = [[0.0, 0.0], [1.0, 0.0], [1.0, shoulder_mm], [3.0, shoulder_mm], [3.0, 5.0], [0.0, 5.0]]
    return trimesh.creation.revolve(np.array(outline), sections=n)


@pytest.mark.parametrize("rounding_mm", [0.0, 5e-7, -5e-7])
def test_a_shoulder_in_the_cutting_plane_is_cut_beyond_whichever_way_it_was_rounded(rounding_mm):
    """A shoulder 2 mm up, exact or moved 5e-7 mm either way (float32 rounding), is cut on the collar's side:
    one region, the radius-3 16-gon's perimeter and area (n r^2 sin(2 pi / n) / 2). Before, the shoulder
    rounded upwards was cut through the shaft (area 3.06 instead of 27.55)."""
    n, r = 16, 3.0
    expected = [math.log(2), math.log(2 * n * r * math.sin(math.pi / n)),
                math.log(n * r * r * math.sin(2 * math.pi / n) / 2)]
    assert slice_descriptor(stepped_shaft(2.0 + rounding_mm), (2.0,)) == pytest.approx(expected, abs=1e-6)


@pytest.mark.parametrize("offset_mm", [0.3, 7.77, 13.7])
def test_an_stl_slices_as_its_exact_mesh_though_its_float32_coordinates_move_a_shoulder(offset_mm):
    """The stepped shaft placed `offset_mm` up and written as STL (float32): its shoulder lands up to 5e-7 mm off
    2 mm from its end (above at 7.77), and its slices are the exact mesh's all the same."""
    exact = stepped_shaft(2.0).apply_translation((0.0, 0.0, offset_mm))
    stored = trimesh.load(io.BytesIO(exact.export(file_type="stl")), file_type="stl")
    assert slice_descriptor(stored) == pytest.approx(slice_descriptor(exact), abs=1e-5)


def test_a_pin_ending_in_the_cutting_plane_is_cut_beyond_its_end():
    """A pin 10 mm long, its end exactly in the 10 mm plane or rounded 5e-7 mm beyond it, has no section there
    (before, the longer one was cut through its end: a full disc)."""
    for length in (10.0, 10.0 + 5e-7):
        pin = trimesh.creation.cylinder(1.0, length, sections=16).apply_translation((0.0, 0.0, length / 2))
        assert slice_descriptor(pin, (10.0,)) == pytest.approx([0.0, math.log(FLOOR), math.log(FLOOR)])


def test_real_cad_slices_into_finite_numbers_and_a_pins_outline_is_its_circumference(real_meshes):
    """Real CAD (STL in mm, OBJ in m, some not watertight) slices without error; a 5 mm positioning pin and an
    8 mm peg cut 2 mm from their end are one region of outline pi d (to 1 %)."""
    found = {path.name: slice_descriptor(load_mesh(path, "auto")) for path in real_meshes}
    assert all(np.isfinite(values).all() for values in found.values())
    for name, diameter in (("labit_positioning_pin_d5_20.stl", 5.0), ("factory_round_peg_8mm_tight.obj", 8.0)):
        regions, length = math.expm1(found[name][3]), math.exp(found[name][4])      # the 2 mm slice
        assert regions == pytest.approx(1.0) and length == pytest.approx(math.pi * diameter, rel=0.01)


def test_the_cloud_carries_the_slices_of_the_mesh_turned_onto_its_insertion_axis(tmp_path):
    """A part inserted along x: its slices are cut across x, from its lowest end along it."""
    path = tmp_path / "tube.stl"
    mesh = tube_with_two_pins()
    mesh.apply_transform(trimesh.geometry.align_vectors([0.0, 0.0, 1.0], [1.0, 0.0, 0.0]))   # axis now x
    mesh.export(path)
    cloud = cloud_from_mesh(path, "mm", 64, axis="x")
    expected = slice_descriptor(orient(load_mesh(path, "mm"), "x", path))
    np.testing.assert_array_equal(cloud.slices, expected)
    assert math.expm1(cloud.slices[3]) == pytest.approx(3.0)                      # the ring and both pins


def test_a_mesh_that_cannot_be_sliced_is_a_dataset_error_naming_its_file(tmp_path, monkeypatch, capsys):
    """trimesh's section failing on broken geometry (simulated: no mesh at hand makes it fail) is the user's
    error: the file and trimesh's reason, exit 2 from the CLI, no traceback."""
    from pipe.cli import main

    path = tmp_path / "broken.stl"
    tube_with_two_pins().export(path)

    def fail(*args, **kwargs):
        raise IndexError("index 3 is out of bounds for axis 0 with size 3")

    monkeypatch.setattr(trimesh.Trimesh, "section", fail)
    with pytest.raises(DatasetError, match="cannot be sliced near its mating end .IndexError: index 3") as error:
        cloud_from_mesh(path, "mm", 64)
    assert error.value.path == path
    assert main(["data", "pointcloud", str(path)]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert f"{path}: the mesh cannot be sliced" in err and "Traceback" not in err


def test_the_training_parts_slices_are_standardised_with_a_floored_spread():
    train = torch.tensor([[1.0, 2.0], [3.0, 2.0]], dtype=torch.float64).repeat(1, SLICE_SIZE // 2)
    code = SliceCode.fitted(train)
    # mean (2, 2), spread (sqrt 2, 0 -> MIN_SPREAD)
    other = torch.tensor([[5.0, 7.0]], dtype=torch.float64).repeat(1, SLICE_SIZE // 2)
    assert code(other)[0, :2].tolist() == pytest.approx([3 / math.sqrt(2), 5 / MIN_SPREAD], rel=1e-6)
    assert code(train)[:, :2].flatten().tolist() == pytest.approx([-1 / math.sqrt(2), 0.0, 1 / math.sqrt(2), 0.0])
    assert code(train).dtype == torch.float32
    with pytest.raises(ValueError, match="slices' spread needs at least 2 training parts"):
        SliceCode.fitted(train[:1])


def test_the_code_is_the_encoders_the_sections_and_the_slices_without_spread(tiny_data, tmp_path):
    cfg = smoke_config(tiny_data, tmp_path, "code.slices=true")
    data = load_domain(cfg)
    model = build_model(cfg, data)
    width = model.encoder.latent_dim
    assert model.head.latent_dim == width + SECTION_SIZE + SLICE_SIZE
    test = data.splits["test"]
    clouds, slices = stack_geometry(test)
    assert torch.equal(slices, torch.from_numpy(test[0].cloud.slices)[None])
    mu, logvar = model.latent_distribution(clouds, slices)
    own_mu, own_logvar = model.encoder.eval().encode(clouds)
    assert torch.equal(mu[:, :width], own_mu) and torch.equal(logvar[:, :width], own_logvar)
    assert torch.equal(mu[:, width:width + SECTION_SIZE], model.sections(clouds))
    assert torch.equal(mu[:, width + SECTION_SIZE:], model.slices(slices))
    train_slices = stack_slices(data.splits["train"])
    assert torch.allclose(model.slices.mean, train_slices.mean(0))
    assert torch.isneginf(logvar[:, width:]).all()
    with pytest.raises(ValueError, match="reads the meshes' slices beside their clouds"):
        model.latent_distribution(clouds)
    alone = smoke_config(tiny_data, tmp_path, "code.slices=true", "code.sections=false")
    assert build_components(alone)[1].latent_dim == width + SLICE_SIZE
    assert build_model(alone, data).sections is None


def test_slices_need_two_training_parts_that_carry_them(tiny_data, tmp_path):
    cfg = smoke_config(tiny_data, tmp_path, "code.slices=true", "code.sections=false", "domain.train=[dsub9]")
    with pytest.raises(PipeError, match="code.slices standardises the mesh's slices over the training parts, and "
                                        "domain tiny has 1"):
        build_model(cfg, load_domain(cfg))
    cfg = smoke_config(tiny_data, tmp_path, "code.slices=true")
    data = load_domain(cfg)
    for part in data.splits["train"]:
        object.__setattr__(part.cloud, "slices", None)             # a cloud not sampled from a mesh file
    assert stack_slices(data.splits["train"]) is None
    with pytest.raises(PipeError, match="parts carry none"):
        build_model(cfg, data)


def slices_context(tiny_data, tmp_path) -> EvalContext:
    cfg = smoke_config(tiny_data, tmp_path, "code.slices=true")
    data = load_domain(cfg)
    model = build_model(cfg, data)
    parts = data.splits["train"] + data.splits["val"] + data.splits["test"]
    latents, logvars = model.latent_distribution(*stack_geometry(parts))
    return EvalContext(model=model, latents=latents, index={p.name: i for i, p in enumerate(parts)},
                       train=data.splits["train"], val=data.splits["val"], dt=0.02, settings={"blackbox_steps": 20},
                       logvars=logvars)


def test_the_baselines_may_read_any_combination_of_the_code_the_sections_and_the_slices(tiny_data, tmp_path):
    ctx = slices_context(tiny_data, tmp_path)
    width = ctx.model.encoder.latent_dim
    sections, total = width + SECTION_SIZE, width + SECTION_SIZE + SLICE_SIZE
    assert code_blocks(ctx) == {"code": range(0, width), "sections": range(width, sections),
                                "slices": range(sections, total)}
    inputs = code_inputs(ctx)
    assert list(inputs) == ["code+sections+slices", "code+sections", "code+slices", "sections+slices", "code",
                            "sections", "slices"]
    z = ctx.latents[0]
    assert torch.equal(z[inputs["code+sections+slices"]], z)
    assert torch.equal(z[inputs["code+slices"]], torch.cat([z[:width], z[sections:]]))
    assert torch.equal(z[inputs["sections+slices"]], z[width:])
    assert inputs["slices"] == slice(sections, None) and inputs["code+sections"] == slice(0, sections)
    nearest = METHODS["nearest"]()
    nearest.fit(ctx)
    reads = nearest.diagnostics(ctx, ctx.val[0])
    assert set(reads) == {"nearest_reads_code", "nearest_reads_sections", "nearest_reads_slices"}
    assert [name for name in ("code", "sections", "slices") if reads[f"nearest_reads_{name}"]] == \
        nearest.inputs.split("+")


def test_a_run_with_slices_predicts_a_mesh_as_it_encoded_its_part(tiny_data, tmp_path):
    """Trained and registered with code.slices, the model predicts a part from its mesh file alone as the
    evaluation's latent code of that part does; the baselines say which blocks they read."""
    from hydra import compose, initialize_config_module

    from pipe.predict import load_model, predict_with

    result = run_domain(smoke_config(tiny_data, tmp_path / "run", "code.slices=true", "evaluation.baselines=[nearest]"))
    assert result.model.slices is not None
    assert {"nearest_reads_slices", "nearest_reads_sections"} <= set(result.results["nearest"].per_part["dsub26"])
    model, card, _ = load_model(result.mlflow_run_id, None, tmp_path)
    mesh = next((tiny_data / "parts" / "dsub26").glob("mesh.*"))
    with initialize_config_module(config_module="pipe.conf", version_base="1.3"):
        cfg = compose(config_name="predict", overrides=[f"mesh={mesh}", f"run={result.mlflow_run_id}", "units=mm"])
    predicted = predict_with(model, card, cfg, [mesh])[0]
    z = result.latents[result.index["dsub26"]]
    depth_max = float(predicted.depth_grid[-1])
    grid = torch.from_numpy(predicted.depth_grid)[None].float()
    theta = result.model.profile(z[None], torch.tensor([depth_max]))(grid)
    np.testing.assert_allclose(predicted.theta, theta[0].detach().numpy(), rtol=1e-5)
    alone = model.latent(*stack_geometry(result.test))
    assert torch.allclose(alone[0], z, atol=1e-6)


def test_a_folder_trained_without_slices_is_evaluated_only_with_that_setting(tiny_data, tmp_path):
    trained, sliced = tmp_path / "trained", tmp_path / "sliced"
    run_domain(smoke_config(tiny_data, trained, "mlflow.enabled=false", "evaluation.baselines=[nearest]",
                            "code.slices=false"))
    run_domain(smoke_config(tiny_data, sliced, "mlflow.enabled=false", "phase=train"))
    with pytest.raises(PipeError, match=r"trained: was trained with code.slices=false; continue or evaluate"):
        run_domain(smoke_config(tiny_data, tmp_path / "other", "mlflow.enabled=false", "code.slices=true",
                                "phase=evaluate", f"resume={trained}"))
    with pytest.raises(PipeError, match=r"sliced: was trained with code.sections=true, code.slices=true; continue"):
        run_domain(smoke_config(tiny_data, tmp_path / "again", "mlflow.enabled=false", "code.sections=false",
                                "code.slices=false", "phase=evaluate", f"resume={sliced}"))
    for folder in (trained, sliced):            # folders without their settings: their weights tell
        (folder / "config.yaml").unlink()
    with pytest.raises(PipeError, match=r"differ in slices.mean, slices.std, head.trunk.0.weight \(it was trained "
                                        r"with code.slices=false\)"):
        run_domain(smoke_config(tiny_data, tmp_path / "other", "mlflow.enabled=false", "code.slices=true",
                                "phase=evaluate", f"resume={trained}"))
    with pytest.raises(PipeError, match=r"it was trained with code.sections=true and code.slices=true\)"):
        run_domain(smoke_config(tiny_data, tmp_path / "again", "mlflow.enabled=false", "code.sections=false",
                                "code.slices=false", "phase=evaluate", f"resume={sliced}"))


def test_a_model_pickled_before_the_slices_existed_loads_reading_none(tiny_data, tmp_path):
    """An MLflow model registered before code.slices has no `slices` attribute; unpickled, it reads none."""
    import pickle

    cfg = smoke_config(tiny_data, tmp_path, "code.slices=false")
    model = build_model(cfg, load_domain(cfg))
    del model.__dict__["slices"]                                  # as the model was before the option
    loaded = pickle.loads(pickle.dumps(model))
    assert loaded.slices is None
    sliced = pickle.loads(pickle.dumps(build_model(smoke_config(tiny_data, tmp_path), load_domain(cfg))))
    assert isinstance(sliced.slices, SliceCode)
