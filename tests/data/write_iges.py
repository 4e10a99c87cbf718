"""How tests/data/dowel6x20_{mm,in}.igs were written: an ISO 8734 dowel pin, 6 mm across and 20 mm long with
0.6 mm chamfers, as a B-rep solid through OpenCascade's own IGES writer, once with millimetres and once with
inches as the file's unit. Not part of the test run: it needs OpenCascade's Python binding
(`pip install cadquery-ocp`), which pipe does not depend on. Usage: python write_iges.py MM|IN OUT.igs"""

import sys

from OCP.BRepFilletAPI import BRepFilletAPI_MakeChamfer
from OCP.BRepPrimAPI import BRepPrimAPI_MakeCylinder
from OCP.IGESControl import IGESControl_Writer
from OCP.Interface import Interface_Static
from OCP.TopAbs import TopAbs_EDGE
from OCP.TopExp import TopExp_Explorer
from OCP.TopoDS import TopoDS

unit, out = sys.argv[1], sys.argv[2]
scale = 1.0 if unit == "MM" else 1.0 / 25.4
cylinder = BRepPrimAPI_MakeCylinder(3.0 * scale, 20.0 * scale).Shape()
chamfer = BRepFilletAPI_MakeChamfer(cylinder)
edges = TopExp_Explorer(cylinder, TopAbs_EDGE)
while edges.More():
    chamfer.Add(0.6 * scale, TopoDS.Edge_s(edges.Current()))
    edges.Next()
Interface_Static.SetCVal_s("write.iges.unit", unit)
writer = IGESControl_Writer(unit, 1)     # 1: B-rep mode (a solid of trimmed faces)
writer.AddShape(chamfer.Shape())
writer.ComputeModel()
assert writer.Write(out)
