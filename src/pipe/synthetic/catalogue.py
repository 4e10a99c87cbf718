"""The paper's Table I parts with their standard dimensions (mm).

Plugs are described by the outline of the metal shell (or plastic body) that enters the receptacle, the
contacts inside it and the detent features (shell dimples, spring tabs, latches). Pins follow
ISO 2339 (taper pins, 1:50 taper, nominal diameter at the small end) and ISO 8734 (dowel pins).
Dimensions are nominal values from the connector standards and common datasheets, rounded to 0.01 mm.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Plug:
    """A connector plug; it is inserted along -z with its mating face at z = 0."""

    name: str
    family: str                 # dsub, hdmi, displayport, dvi, rj45, usb
    outline: str                # shape of the shell cross-section, see meshes.outline_polygon
    width: float                # outside of the mating shell, widest
    height: float
    mate_length: float          # insertion depth from the first shell contact to the stop
    rows: tuple[int, ...]       # contacts per row
    pitch: float                # contact pitch within a row
    row_pitch: float
    contact_size: float         # pin diameter or blade width
    detents: int                # shell dimples / spring tabs / latches that snap during insertion
    detent_strength: float      # N per detent at its crest
    body: tuple[float, float, float]  # overmold or backshell held by the gripper: width, height, length
    flange: tuple[float, float, float] | None = None  # D-sub flange: width, height, mounting-hole spacing

    @property
    def contacts(self) -> int:
        return sum(self.rows)


@dataclass(frozen=True)
class Pin:
    """A taper or dowel pin, inserted small end first along -z."""

    name: str
    family: str                 # taper, dowel
    diameter: float             # nominal: small end of a taper pin
    length: float
    insert_depth: float         # how deep the robot inserts it
    taper: float = 0.0          # diameter change per mm of length (1/50 for taper pins)
    chamfer: float | None = None  # length of the lead-in at the small end; None: the standard's (see lead_in)

    @property
    def contacts(self) -> int:
        return 0

    @property
    def lead_in(self) -> float:
        """Length of the lead-in at the small end: the chamfer, by default 0.15 d (ISO 8734 dowel pins) or
        the 0.05 d domed end of an ISO 2339 taper pin."""
        if self.chamfer is not None:
            return self.chamfer
        return 0.15 * self.diameter if self.family == "dowel" else 0.05 * self.diameter


# D-sub shells (standard density: pitch 2.77 mm, rows 2.84 mm, pins 1.0 mm; high density: 2.29 / 1.98 /
# 0.76 mm). Shell E/A/B/C: flange 30.81/39.14/53.04/69.32 wide, mounting holes 24.99/33.32/47.04/63.50
# apart, male D 16.92/25.25/38.96/55.42 wide and 7.9 high, flange 12.55 high, 6.0 mm mating length.
DSUB_SHELLS = {"E": (16.92, 30.81, 24.99), "A": (25.25, 39.14, 33.32), "B": (38.96, 53.04, 47.04),
               "C": (55.42, 69.32, 63.50)}


# Full inserts per shell: standard density in 2 rows, high density in 3.
DSUB_ROWS = {
    False: {"E": (5, 4), "A": (8, 7), "B": (13, 12), "C": (19, 18)},
    True: {"E": (5, 5, 5), "A": (9, 9, 8), "B": (15, 15, 14), "C": (21, 21, 20)},
}


def dsub_plug(name: str, shell: str, high_density: bool, rows: tuple[int, ...] | None = None,
              detent_strength: float = 0.9, backshell_length: float = 14.0) -> Plug:
    """A D-sub plug in shell E/A/B/C; `rows` (contacts per row) defaults to the full insert."""
    width, flange_w, holes = DSUB_SHELLS[shell]
    pitch, row_pitch, pin = (2.29, 1.98, 0.76) if high_density else (2.77, 2.84, 1.0)
    rows = DSUB_ROWS[high_density][shell] if rows is None else rows
    return Plug(name, "dsub", "dsub", width, 7.9, 6.0, rows, pitch, row_pitch, pin, detents=4,
                detent_strength=detent_strength, body=(flange_w - 4.0, 15.5, backshell_length),
                flange=(flange_w, 12.55, holes))


PLUGS = [
    dsub_plug("dsub9", "E", False),
    dsub_plug("dsub15", "A", False),
    dsub_plug("dsub25", "B", False),
    dsub_plug("dsub37", "C", False),
    dsub_plug("vga", "E", True),
    dsub_plug("dsub26", "A", True),
    dsub_plug("dsub44", "B", True),
    # DVI-I: D-shaped shell, 3 x 8 digital contacts plus 4 analog around the blade (counted as 5).
    Plug("dvi", "dvi", "dsub", 24.3, 8.9, 8.0, (8, 8, 8, 5), 1.905, 1.905, 0.6, 4, 1.1, (39.0, 16.0, 18.0)),
    Plug("hdmi", "hdmi", "hdmi", 13.9, 4.45, 9.0, (10, 9), 1.0, 1.0, 0.5, 2, 2.2, (21.0, 11.0, 30.0)),
    Plug("hdmimini", "hdmi", "hdmi", 10.42, 2.42, 7.0, (10, 9), 0.8, 0.8, 0.3, 2, 1.6, (16.0, 7.0, 25.0)),
    Plug("hdmimicro", "hdmi", "hdmi", 6.4, 2.8, 5.9, (10, 9), 0.8, 0.8, 0.2, 2, 1.2, (11.0, 6.0, 22.0)),
    Plug("displayport", "displayport", "dp", 16.1, 4.76, 9.0, (10, 10), 1.0, 1.0, 0.5, 2, 4.5, (22.0, 10.0, 32.0)),
    Plug("rj45", "rj45", "rj45", 11.68, 8.0, 14.0, (8,), 1.02, 1.02, 0.5, 1, 6.0, (11.68, 8.0, 24.0)),
    Plug("usba", "usb", "rect", 12.0, 4.5, 12.0, (4,), 2.5, 2.5, 1.0, 4, 1.8, (16.0, 8.0, 26.0)),
    Plug("usbb", "usb", "usbb", 8.0, 7.26, 9.5, (2, 2), 2.5, 2.0, 1.0, 2, 2.5, (12.0, 11.0, 26.0)),
    Plug("usbc", "usb", "stadium", 8.25, 2.4, 6.65, (12, 12), 0.5, 0.5, 0.25, 2, 2.8, (12.0, 6.5, 24.0)),
    Plug("usbmicro", "usb", "micro", 6.85, 1.8, 5.6, (5,), 0.65, 0.65, 0.35, 2, 1.4, (10.5, 6.0, 20.0)),
    Plug("usbmini", "usb", "mini", 6.8, 3.0, 6.8, (5,), 0.8, 0.8, 0.4, 2, 1.6, (10.5, 7.0, 22.0)),
]

# ISO 2339 taper pins: 1:50 taper, nominal diameter at the small end; ISO 8734 dowel pins (hardened, m6).
PINS = [
    *(Pin(f"taper{d}", "taper", float(d), float(length), 0.6 * length, taper=1 / 50)
      for d, length in ((6, 40), (8, 50), (10, 60), (12, 70), (14, 80))),
    *(Pin(f"dowel{d}", "dowel", float(d), float(length), 0.5 * length)
      for d, length in ((5, 20), (6, 24), (8, 30), (12, 40))),
]

CATALOGUE: dict[str, Plug | Pin] = {p.name: p for p in [*PLUGS, *PINS]}
PART_NAMES: list[str] = list(CATALOGUE)
