"""Triangle meshes of the catalogue's parts, built with trimesh (extrusions, revolutions, manifold booleans).

Every part is inserted along -z with its mating face (plug) or small end (pin) at z = 0.
"""

from __future__ import annotations

import math

import numpy as np
import trimesh
from shapely.geometry import Point, Polygon, box

from pipe.synthetic.catalogue import Pin, Plug

SHELL_WALL = 0.4   # mm, sheet-metal shell
SECTIONS = 24      # facets of round features


def prism(outline: Polygon, z0: float, z1: float) -> trimesh.Trimesh:
    """Extrude a 2-D outline (x, y in mm) between heights z0 and z1."""
    mesh = trimesh.creation.extrude_polygon(outline, z1 - z0)
    mesh.apply_translation((0.0, 0.0, z0))
    return mesh


def rounded(poly: Polygon, radius: float) -> Polygon:
    """Round the corners of a convex-ish outline without changing its size."""
    return poly.buffer(-radius, join_style="mitre").buffer(radius, quad_segs=6)


def outline_polygon(shape: str, width: float, height: float) -> Polygon:
    """Cross-section of a plug's shell, centred on the origin, widest side at +y."""
    w, h = width / 2, height / 2
    if shape == "dsub":  # D shape: sides inclined 10 degrees, wide side on top
        inset = height * math.tan(math.radians(10))
        return rounded(Polygon([(-w, h), (w, h), (w - inset, -h), (-w + inset, -h)]), min(1.0, 0.2 * height))
    if shape == "hdmi":  # lower corners bevelled
        c = 0.3 * height
        return Polygon([(-w, h), (w, h), (w, -h + c), (w - c, -h), (-w + c, -h), (-w, -h + c)])
    if shape == "dp":  # one lower corner bevelled (keyed)
        c = 0.4 * height
        return Polygon([(-w, h), (w, h), (w, -h + c), (w - c, -h), (-w, -h)])
    if shape == "usbb":  # upper corners bevelled
        c = 0.2 * width
        return Polygon([(-w, -h), (w, -h), (w, h - c), (w - c, h), (-w + c, h), (-w, h - c)])
    if shape == "stadium":  # USB-C: rounded ends
        return rounded(box(-w, -h, w, h), h * 0.999)
    if shape == "micro":  # micro-B: trapezoid, narrow side down
        c = 0.6 * height
        return Polygon([(-w, h), (w, h), (w, -h + c), (w - c, -h), (-w + c, -h), (-w, -h + c)])
    if shape == "mini":  # mini-B: lower corners cut deeply
        c = 0.35 * height
        return Polygon([(-w, h), (w, h), (w, -h + c), (w - 1.5 * c, -h), (-w + 1.5 * c, -h), (-w, -h + c)])
    if shape in ("rect", "rj45"):
        return rounded(box(-w, -h, w, h), 0.3)
    raise ValueError(f"unknown outline {shape!r}")


def contact_positions(plug: Plug) -> np.ndarray:
    """(n, 2) x, y positions of the contacts: rows centred, each row centred on its own count."""
    rows = len(plug.rows)
    points = []
    for j, count in enumerate(plug.rows):
        y = ((rows - 1) / 2 - j) * plug.row_pitch
        xs = (np.arange(count) - (count - 1) / 2) * plug.pitch
        points.extend((x, y) for x in xs)
    return np.asarray(points)


def _bumps(outline: Polygon, count: int, z: float, radius: float) -> list[trimesh.Trimesh]:
    """Detent dimples / spring tabs: small spheres on the long sides of the shell."""
    minx, miny, maxx, maxy = outline.bounds
    xs = np.linspace(minx, maxx, count // 2 + 2)[1:-1] if count > 1 else np.array([0.0])
    spots = [(x, maxy) for x in xs] + ([(x, miny) for x in xs] if count > 1 else [])
    return [trimesh.creation.icosphere(1, radius).apply_translation((x, y, z)) for x, y in spots[:count]]


def plug_mesh(plug: Plug) -> trimesh.Trimesh:
    outer = outline_polygon(plug.outline, plug.width, plug.height)
    length = plug.mate_length
    bw, bh, bl = plug.body
    parts: list[trimesh.Trimesh] = []
    if plug.family == "rj45":  # solid plastic plug with a latch lever on top and contact blades at the front
        parts.append(prism(outer, 0.0, bl))
        latch = Polygon([(-1.6, 0), (1.6, 0), (1.6, 1.0), (-1.6, 1.0)])
        lever = prism(latch, 2.0, 16.0)
        lever.apply_transform(trimesh.transformations.rotation_matrix(math.radians(-6), (1, 0, 0), (0, 0, 2.0)))
        lever.apply_translation((0, plug.height / 2 - 0.3, 0))
        parts.append(lever)
        for x, _ in contact_positions(plug):
            blade = box(x - 0.15, plug.height / 2 - 2.6, x + 0.15, plug.height / 2 - 0.4)
            parts.append(prism(blade, -0.1, 4.0))
    else:
        inner = outer.buffer(-SHELL_WALL, join_style="mitre")
        parts.append(prism(outer.difference(inner), 0.0, length))
        # insulator: dsub pins stand on it at the back of the shell; other plugs carry a contact tongue
        if plug.family == "dsub":
            parts.append(prism(inner.buffer(0.05), length - 1.5, length))
            for x, y in contact_positions(plug):
                parts.append(prism(Point(x, y).buffer(plug.contact_size / 2, quad_segs=4), 0.8, length - 1.4))
        else:
            ix0, iy0, ix1, iy1 = inner.bounds
            tongue = box(0.82 * ix0, 0.3 * iy0, 0.82 * ix1, 0.3 * iy1)
            parts.append(prism(tongue, 0.6, length))
            for x, y in contact_positions(plug):
                row_side = 0.3 * (iy1 if y >= 0 else iy0)
                pad = box(x - plug.contact_size / 2, row_side - 0.05, x + plug.contact_size / 2, row_side + 0.05)
                parts.append(prism(pad, 1.0, length - 0.5))
        parts.extend(_bumps(outer, plug.detents, 0.55 * length, 0.45))
        if plug.flange is not None:
            fw, fh, holes = plug.flange
            plate = rounded(box(-fw / 2, -fh / 2, fw / 2, fh / 2), 1.0)
            for x in (-holes / 2, holes / 2):
                plate = plate.difference(Point(x, 0).buffer(1.55, quad_segs=6))
            parts.append(prism(plate, length, length + 1.0))
            body_z = length + 1.0
        else:
            body_z = length
        parts.append(prism(rounded(box(-bw / 2, -bh / 2, bw / 2, bh / 2), 1.0), body_z, body_z + bl))
    return trimesh.boolean.union(parts, engine="manifold")


def pin_mesh(pin: Pin) -> trimesh.Trimesh:
    """Surface of revolution about z: the 1:50 taper (taper pins) or a cylinder, with the lead-in at z = 0."""
    r0 = pin.diameter / 2
    r1 = r0 + pin.taper * pin.length / 2
    c, e = pin.lead_in, 0.1 * r0
    if pin.family == "taper":  # both ends slightly domed (the small end's dome is its lead-in)
        profile = [(0, 0), (r0 - c, 0), (r0, c), (r1, pin.length - e), (r1 - e, pin.length), (0, pin.length)]
    else:  # ISO 8734: chamfered lead-in at the inserted end, rounded back end
        profile = [(0, 0), (r0 - c, 0), (r0, c), (r0, pin.length - e), (r0 - e, pin.length), (0, pin.length)]
    return trimesh.creation.revolve(np.asarray(profile, dtype=float), sections=SECTIONS * 2)


def part_mesh(part: Plug | Pin) -> trimesh.Trimesh:
    """The watertight mesh of a catalogue part, in mm."""
    mesh = plug_mesh(part) if isinstance(part, Plug) else pin_mesh(part)
    mesh.metadata["name"] = part.name
    return mesh
