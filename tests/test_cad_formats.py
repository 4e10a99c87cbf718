"""CAD in every common format, in millimetres, turned onto its insertion axis: a 10 x 20 x 30 mm box written
in each format (STEP by hand, as a faceted B-rep) must come back 10 x 20 x 30 mm, as must a real IGES pin
written by OpenCascade in mm and in inches; the real screw that lies along x must come out along z."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from pipe.data.check import check_dataset
from pipe.data.mesh import iges_units, load_mesh, orient
from pipe.data.preprocess import cloud_from_mesh
from pipe.errors import DatasetError

BOX_MM = (10.0, 20.0, 30.0)
DATA = Path(__file__).resolve().parent / "data"


def step_box(size: tuple[float, float, float], prefix: str | None) -> str:
    """STEP AP214 text of an axis-aligned box with one corner at the origin, a faceted B-rep of six planar
    faces bounded by polygon loops, its lengths in metres times the SI `prefix` (MILLI, or None: metres)."""
    x, y, z = size
    corners = [(i * x, j * y, k * z) for k in (0, 1) for j in (0, 1) for i in (0, 1)]
    faces = [((0, 2, 3, 1), (0, 0, -1), (1, 0, 0)), ((4, 5, 7, 6), (0, 0, 1), (1, 0, 0)),
             ((0, 1, 5, 4), (0, -1, 0), (1, 0, 0)), ((2, 6, 7, 3), (0, 1, 0), (1, 0, 0)),
             ((0, 4, 6, 2), (-1, 0, 0), (0, 1, 0)), ((1, 3, 7, 5), (1, 0, 0), (0, 1, 0))]
    lines: list[str] = []

    def add(entity: str) -> str:
        lines.append(f"#{len(lines) + 1}={entity};")
        return f"#{len(lines)}"

    def direction(v: tuple[int, int, int]) -> str:
        return add(f"DIRECTION('',({v[0]:.1f},{v[1]:.1f},{v[2]:.1f}))")

    points = [add(f"CARTESIAN_POINT('',({a:.6f},{b:.6f},{c:.6f}))") for a, b, c in corners]
    face_ids = []
    for loop, normal, reference in faces:
        polygon = add("POLY_LOOP('',(" + ",".join(points[i] for i in loop) + "))")
        bound = add(f"FACE_OUTER_BOUND('',{polygon},.T.)")
        placement = add(f"AXIS2_PLACEMENT_3D('',{points[loop[0]]},{direction(normal)},{direction(reference)})")
        plane = add(f"PLANE('',{placement})")
        face_ids.append(add(f"FACE_SURFACE('',({bound}),{plane},.T.)"))
    shell = add("CLOSED_SHELL('',(" + ",".join(face_ids) + "))")
    brep = add(f"FACETED_BREP('',{shell})")
    unit = f".{prefix}." if prefix else "$"
    length = add(f"(LENGTH_UNIT()NAMED_UNIT(*)SI_UNIT({unit},.METRE.))")
    angle = add("(NAMED_UNIT(*)PLANE_ANGLE_UNIT()SI_UNIT($,.RADIAN.))")
    solid = add("(NAMED_UNIT(*)SI_UNIT($,.STERADIAN.)SOLID_ANGLE_UNIT())")
    accuracy = add(f"UNCERTAINTY_MEASURE_WITH_UNIT(LENGTH_MEASURE(1.E-06),{length},'distance_accuracy_value','')")
    context = add(f"(GEOMETRIC_REPRESENTATION_CONTEXT(3)GLOBAL_UNCERTAINTY_ASSIGNED_CONTEXT(({accuracy}))"
                  f"GLOBAL_UNIT_ASSIGNED_CONTEXT(({length},{angle},{solid}))REPRESENTATION_CONTEXT('',''))")
    shape = add(f"FACETED_BREP_SHAPE_REPRESENTATION('box',({brep}),{context})")
    application = add("APPLICATION_CONTEXT('automotive design')")
    add(f"APPLICATION_PROTOCOL_DEFINITION('international standard','automotive_design',2000,{application})")
    product_context = add(f"PRODUCT_CONTEXT('',{application},'mechanical')")
    product = add(f"PRODUCT('box','box','',({product_context}))")
    formation = add(f"PRODUCT_DEFINITION_FORMATION('','',{product})")
    definition_context = add(f"PRODUCT_DEFINITION_CONTEXT('part definition',{application},'design')")
    definition = add(f"PRODUCT_DEFINITION('design','',{formation},{definition_context})")
    definition_shape = add(f"PRODUCT_DEFINITION_SHAPE('','',{definition})")
    add(f"SHAPE_DEFINITION_REPRESENTATION({definition_shape},{shape})")
    return ("ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION((''),'2;1');\n"
            "FILE_NAME('box.step','2026-01-01T00:00:00',(''),(''),'','','');\nFILE_SCHEMA(('AUTOMOTIVE_DESIGN'));\n"
            "ENDSEC;\nDATA;\n" + "\n".join(lines) + "\nENDSEC;\nEND-ISO-10303-21;\n")


@pytest.mark.parametrize("suffix", [".stl", ".obj", ".ply", ".off", ".3mf", ".glb", ".gltf"])
def test_mesh_formats_read_in_mm(tmp_path: Path, suffix: str) -> None:
    """STL, OBJ, PLY and OFF in the declared unit (mm here); 3MF in its own unit (mm); glTF in metres, its
    specification's unit, so the box is written in metres."""
    in_metres = suffix in (".glb", ".gltf")
    box = trimesh.creation.box(np.array(BOX_MM) / (1000.0 if in_metres else 1.0))
    box.export(tmp_path / f"box{suffix}")
    mesh = load_mesh(tmp_path / f"box{suffix}", "mm")
    np.testing.assert_allclose(np.sort(mesh.extents), BOX_MM, rtol=1e-5)
    assert mesh.is_watertight and mesh.metadata["file_units"] == ("m" if in_metres else "mm")


@pytest.mark.parametrize("prefix", ["MILLI", None])
def test_step_is_read_in_the_unit_it_declares(tmp_path: Path, prefix: str | None) -> None:
    pytest.importorskip("cascadio", reason="the optional extra cad is not installed (pip install 'pipe-sysid[cad]')")
    size = BOX_MM if prefix else tuple(e / 1000.0 for e in BOX_MM)
    (tmp_path / "box.step").write_text(step_box(size, prefix))
    mesh = load_mesh(tmp_path / "box.step", "in")          # the declared unit is for unitless formats only
    np.testing.assert_allclose(mesh.extents, BOX_MM, rtol=1e-4)
    assert mesh.is_watertight and mesh.metadata["file_units"] == "m"
    cloud = cloud_from_mesh(tmp_path / "box.step", "mm", 256, axis="x")
    np.testing.assert_allclose(np.ptp(cloud.points, axis=0), [30.0, 20.0, 10.0], atol=1.0)   # x turned onto z


@pytest.mark.parametrize("unit", ["mm", "in"])
def test_iges_is_read_in_the_unit_it_declares(unit: str) -> None:
    """A real IGES B-rep written by OpenCascade (tests/data/write_iges.py: a dowel pin 6 mm across and 20 mm
    long, chamfered) in mm and in inches comes back 6 x 6 x 20 mm, closed, with about the chamfered
    cylinder's volume (pi 3^2 20 less the chamfers: 559.15 mm^3 by OpenCascade's own integration).
    cascadio passes IGES coordinates on in the file's unit, not in metres as it does STEP's."""
    pytest.importorskip("cascadio", reason="the optional extra cad is not installed (pip install 'pipe-sysid[cad]')")
    mesh = load_mesh(DATA / f"dowel6x20_{unit}.igs", "m")     # the declared unit is for unitless formats only
    np.testing.assert_allclose(np.sort(mesh.extents), [6.0, 6.0, 20.0], atol=0.1)
    assert mesh.is_watertight and mesh.metadata["file_units"] == unit
    assert mesh.volume == pytest.approx(559.15, rel=0.02)


def test_iges_units_from_the_global_section() -> None:
    """The unit flag is the global section's 14th parameter; flag 3 names the unit in the 15th; a file may
    choose its own delimiter (parameter 1) and strings are Hollerith (nH...), which may hold the delimiter."""
    def iges(global_section: str) -> bytes:
        lines = [global_section[i:i + 72] for i in range(0, len(global_section), 72)]
        return "".join(f"{line:<72}G{n + 1:07d}\n" for n, line in enumerate(lines)).encode()

    fields = ",,4Ha,b;,8Hpart.igs,5Hmaker,3H7.8,32,308,15,308,15,,1.,{flag},{name},1,0.01,13H260101.000000,1E-07;"
    assert iges_units(iges(fields.format(flag=1, name="4HINCH"))) == "in"
    assert iges_units(iges(fields.format(flag=10, name="2HCM"))) == "cm"
    assert iges_units(iges(fields.format(flag=3, name="2HMM"))) == "mm"
    assert iges_units(iges("1H//1H;/" + fields[2:].replace(",", "/").format(flag=6, name="1HM"))) == "m"
    with pytest.raises(DatasetError, match="IGES unit flag 3 .*FURLONG"):
        iges_units(iges(fields.format(flag=3, name="7HFURLONG")))
    with pytest.raises(DatasetError, match="no unit flag"):
        iges_units(b"not an IGES file\n")


def test_unreadable_iges_is_refused_by_name(tmp_path: Path, monkeypatch) -> None:
    """When OpenCascade returns nothing (cascadio's sign of a file it cannot read), the error names the file."""
    cascadio = pytest.importorskip("cascadio", reason="the optional extra cad is not installed")
    monkeypatch.setattr(cascadio, "load", lambda data, file_type: b"")
    (tmp_path / "box.igs").write_bytes(b"an IGES file")
    with pytest.raises(DatasetError, match="box.igs.*OpenCascade could not read this IGES file"):
        load_mesh(tmp_path / "box.igs", "mm")


def test_step_without_the_extra_names_it(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "cascadio", None)      # import cascadio now raises ImportError
    (tmp_path / "part.STEP").write_text(step_box(BOX_MM, "MILLI"))
    with pytest.raises(DatasetError, match=r"part.STEP: reading STEP needs the optional extra 'cad'.*sysid\[cad\]"):
        load_mesh(tmp_path / "part.STEP", "mm")


def test_orient_turns_the_named_axis_onto_z() -> None:
    box = trimesh.creation.box(BOX_MM)
    for axis, along_z in (("x", 10.0), ("-x", 10.0), ("y", 20.0), ("-y", 20.0), ("z", 30.0), ("principal", 30.0)):
        assert orient(box, axis).extents[2] == pytest.approx(along_z), axis
    point = np.array([[0.0, -7.0, 0.0]])                    # a point on -y goes to +z with axis -y
    turned = orient(trimesh.Trimesh(vertices=np.vstack([point, np.eye(3)]), faces=[[1, 2, 3]], process=False), "-y")
    np.testing.assert_allclose(turned.vertices[0], [0.0, 0.0, 7.0], atol=1e-12)
    with pytest.raises(DatasetError, match="insertion axis 'w' is not one of"):
        orient(box, "w")


def test_the_real_screw_along_x_is_turned_onto_z(real_meshes) -> None:
    screw = next(p for p in real_meshes if p.name == "labit_screw_m5_12.stl")
    for axis in ("x", "principal"):
        extents = np.ptp(cloud_from_mesh(screw, "mm", 512, axis=axis).points, axis=0)
        assert extents.argmax() == 2 and extents[2] == pytest.approx(17.0, abs=0.3), axis
    assert np.ptp(cloud_from_mesh(screw, "mm", 512).points, axis=0).argmax() == 0


def test_a_part_axis_in_dataset_yaml_reaches_the_cloud_and_a_bad_one_is_named(dataset_copy: Path) -> None:
    from pipe.data.prepared import prepare_domain

    spec_path = dataset_copy / "dataset.yaml"
    spec = yaml.safe_load(spec_path.read_text())
    data_cfg = {"points": 256, "cloud_seed": 0, "rate_hz": 50, "steady_samples": 1}
    domain = {"name": "t", "train": ["dsub9"], "val": [], "test": ["taper8"]}
    before = prepare_domain(dataset_copy, data_cfg, domain).splits["test"][0].cloud.points
    spec["parts"]["taper8"]["axis"] = "x"
    spec_path.write_text(yaml.safe_dump(spec))
    after = prepare_domain(dataset_copy, data_cfg, domain).splits["test"][0].cloud.points
    assert np.ptp(before, axis=0).argmax() == 2 and np.ptp(after, axis=0).argmax() == 0
    spec["parts"]["taper8"]["axis"] = "up"
    spec_path.write_text(yaml.safe_dump(spec))
    with pytest.raises(DatasetError, match=r"dataset.yaml: parts.taper8.axis is 'up'; use one of z, x"):
        prepare_domain(dataset_copy, data_cfg, domain)


def test_a_mesh_in_metres_declared_mm_is_warned_about(dataset_copy: Path) -> None:
    mesh_path = dataset_copy / "parts" / "taper8" / "mesh.stl"
    mesh = trimesh.load(mesh_path)
    mesh.apply_scale(0.001)
    mesh.export(mesh_path)
    report = check_dataset(dataset_copy)
    assert report.ok
    assert any("mesh.stl: the part is only" in str(w) and "units: {mesh: m}" in str(w) for w in report.warnings)
