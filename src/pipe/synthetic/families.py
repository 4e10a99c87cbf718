"""Parametric part families: as many parts as wanted, drawn from the standard sizes of real parts.

Besides the paper's 27 parts (`catalogue`), a family generates parts whose geometry varies over the sizes
the standards define, with the same contact physics, meshes and trials (`pipe data generate OUT --family
pins --count 200`). Part k of a family depends only on (seed, family, k): a family of 50 parts is the first
50 of one of 200. The distributions are documented in docs/synthetic.md.

- dsub: D-sub shells E, A, B, C (IEC 60807-3 / MIL-DTL-24308 dimensions, as the catalogue's), standard or
  high density, fully or partly loaded, with the dimple strength and backshell length of the make;
- rect: rectangular plugs (a sheet-metal shell with a contact tongue, as USB/HDMI plugs) at the standard
  wire-to-board pitches, 1 or 2 rows of 2 to 12 contacts, 0 to 2 latches;
- pins: ISO 8734 dowel pins and ISO 2339 taper pins (1:50) at the standard diameters and lengths, with the
  lead-in chamfer of the make.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable

import numpy as np

from pipe.data.domain import numbered_part
from pipe.errors import PipeError
from pipe.synthetic.catalogue import DSUB_ROWS, DSUB_SHELLS, Pin, Plug, dsub_plug

# Wire-to-board pitches [mm]: PicoBlade 1.25, JST PH 2.0, JST XH 2.5, 0.1" headers 2.54, Micro-Fit 3.0,
# Mini-Fit Jr 4.2.
RECT_PITCHES = (1.25, 2.0, 2.5, 2.54, 3.0, 4.2)
# ISO 8734 / ISO 2339 nominal diameters and the preferred length series [mm].
PIN_DIAMETERS = (3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0, 16.0, 20.0)
PIN_LENGTHS = (8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30, 32, 35, 40, 45, 50, 55, 60, 65, 70, 75, 80, 85,
               90, 95, 100, 120, 140)
DEFAULT_COUNT = 100    # parts of a family when no count is given


def _loaded(rows: tuple[int, ...], rng: np.random.Generator) -> tuple[int, ...]:
    """Contacts per row: half the inserts fully loaded, the others with a share of 30 to 90 % of the
    positions populated (at least one per row)."""
    if rng.random() < 0.5:
        return rows
    share = rng.uniform(0.3, 0.9)
    return tuple(max(1, round(share * n)) for n in rows)


def draw_dsub(name: str, rng: np.random.Generator) -> Plug:
    """A D-sub plug: shell E/A/B/C uniform, high density with probability 0.4."""
    shell = str(rng.choice(list(DSUB_SHELLS)))
    high_density = bool(rng.random() < 0.4)
    rows = _loaded(DSUB_ROWS[high_density][shell], rng)
    return dsub_plug(name, shell, high_density, rows, detent_strength=0.9 * rng.uniform(0.7, 1.3),
                     backshell_length=rng.uniform(10.0, 20.0))


def draw_rect(name: str, rng: np.random.Generator) -> Plug:
    """A rectangular plug: a pitch of RECT_PITCHES, 1 or 2 rows of 2 to 12 contacts, 0/1/2 latches with
    probabilities 0.3/0.5/0.2; housing (n - 1) p + 1.96 p wide and (rows + 1.3) p high (the JST XH pattern),
    contacts 0.25 p wide, a mating length of 2.4 p (3 to 10 mm) +-10 %."""
    pitch = float(rng.choice(RECT_PITCHES))
    rows = int(rng.integers(1, 3))
    per_row = int(rng.integers(2, 13))
    latches = int(rng.choice(3, p=(0.3, 0.5, 0.2)))
    width = (per_row - 1) * pitch + 1.96 * pitch
    height = (rows + 1.3) * pitch
    mate = float(np.clip(2.4 * pitch, 3.0, 10.0)) * rng.uniform(0.9, 1.1)
    return Plug(name, "rect", "rect", width, height, mate, (per_row,) * rows, pitch, pitch, 0.25 * pitch,
                detents=latches, detent_strength=rng.uniform(1.5, 4.0),
                body=(width + 2.0, height + 2.0, rng.uniform(8.0, 16.0)))


def draw_pin(name: str, rng: np.random.Generator) -> Pin:
    """A pin: a taper pin (1:50) with probability 0.4, else a dowel pin; a diameter of PIN_DIAMETERS; a
    length of PIN_LENGTHS from 2.5 to 7 diameters; inserted 0.6 (taper) or 0.5 (dowel) of its length; a
    lead-in chamfer of 0.03 to 0.08 d (taper) or 0.10 to 0.20 d (dowel)."""
    taper = bool(rng.random() < 0.4)
    diameter = float(rng.choice(PIN_DIAMETERS))
    lengths = [length for length in PIN_LENGTHS if 2.5 * diameter <= length <= 7 * diameter]
    length = float(rng.choice(lengths))
    if taper:
        return Pin(name, "taper", diameter, length, 0.6 * length, taper=1 / 50,
                   chamfer=rng.uniform(0.03, 0.08) * diameter)
    return Pin(name, "dowel", diameter, length, 0.5 * length, chamfer=rng.uniform(0.10, 0.20) * diameter)


FAMILIES: dict[str, Callable[[str, np.random.Generator], Plug | Pin]] = {
    "dsub": draw_dsub, "rect": draw_rect, "pins": draw_pin}


def family_part_names(family: str, count: int) -> list[str]:
    """The names of a family's first `count` parts, `<family>_0000` ..., without drawing them."""
    if family not in FAMILIES:
        raise PipeError(f"unknown part family {family!r}; the families are: {', '.join(FAMILIES)}")
    if count < 1:
        raise PipeError(f"--count must be at least 1, not {count}")
    return [numbered_part(family, k) for k in range(count)]


def family_parts(family: str, count: int, seed: int = 0) -> dict[str, Plug | Pin]:
    """Parts `<family>_0000` ... of a family, part k drawn from its own stream (seed, family, k)."""
    names = family_part_names(family, count)
    draw = FAMILIES[family]
    return {name: draw(name, np.random.default_rng([seed, zlib.crc32(family.encode()), k]))
            for k, name in enumerate(names)}
