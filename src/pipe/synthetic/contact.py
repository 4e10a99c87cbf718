"""Quasi-static contact forces of an insertion as functions of the part's depth, built from its geometry.

The force resisting insertion at part depth x is split into an elastic part E(x) (lead-in chamfer against
the misalignment, contact springs being spread, detents, the mechanical stop, a taper seating) and a
Coulomb friction level C(x) >= 0 (contact springs, shell springs, lateral preload, pin bore). The true
static force-depth curve of slow insertion is E + C. Every magnitude comes from a feature a point cloud
shows: contact count and size, shell perimeter, pin diameter, chamfer size, taper, engagement length.
See docs/synthetic.md for the equations and the constants.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipe.synthetic.catalogue import Pin, Plug
from pipe.synthetic.meshes import outline_polygon

LATERAL_STIFFNESS = 20.0      # N/mm, robot + gripper lateral compliance that a misalignment deflects
CONTACT_NORMAL = 1.4          # N per mm of contact size: spring normal force of one socket contact
CONTACT_FRICTION = 0.3        # friction coefficient of plated contacts
CONTACT_ENTRY = 0.5           # mm over which a contact spring is spread open
SHELL_PRESSURE = 0.15         # N per mm of shell perimeter: shell spring / dimple normal force
SHELL_FRICTION = 0.25
PLUG_LEAD_IN = 0.5            # mm, chamfer of the receptacle opening
DETENT_WIDTH = 0.25           # mm, half-width of a detent's ridge
STOP_STIFFNESS = 400.0        # N/mm, housing hitting the mechanical stop
BORE_PRESSURE = 0.01          # N/mm^2, line pressure of a pin in its reamed bore (fit + roughness)
PIN_FRICTION = 0.15
TAPER_SEAT_STIFFNESS = 0.6    # N/mm^3, normal pressure per mm of diametral interference of a taper pin


@dataclass(frozen=True)
class TrialConditions:
    """What changes from one insertion of the same part to the next."""

    speed: float             # mm/s, commanded insertion speed
    misalignment: float      # mm, lateral offset the lead-in has to correct
    gap: float               # mm, free approach before the first contact
    overtravel: float        # mm, commanded travel beyond the stop (plugs) or the seat (taper pins)
    friction_scale: float    # lubrication / wear: scales all friction coefficients
    contact_offsets: np.ndarray  # mm, per contact: manufacturing spread of where each contact engages
    sensor_bias: float       # N, force-sensor offset (removed by zeroing)


def smoothstep(u: np.ndarray) -> np.ndarray:
    """0 below 0, 1 above 1, C1-smooth in between."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def hump(u: np.ndarray) -> np.ndarray:
    """sin^2 bump on [0, 1], peak 1 at u = 1/2, zero elsewhere."""
    return np.where((u > 0) & (u < 1), np.sin(np.pi * np.clip(u, 0, 1)) ** 2, 0.0)


def detent(s: np.ndarray, crest: float, width: float) -> np.ndarray:
    """Force of a ridge being climbed (+1 peak before the crest) then snapped over (-0.6 after it)."""
    v = (s - crest) / width
    shape = -v * np.exp(0.5 - 0.5 * v * v)
    return np.where(v > 0, 0.6 * shape, shape)


def stop(s: np.ndarray, at: float, stiffness: float, soft: float = 0.01) -> np.ndarray:
    """Stiff spring beyond `at`, smoothed over `soft` mm (a softplus)."""
    return stiffness * soft * np.logaddexp(0.0, (s - at) / soft)


def lead_in_length(part: Plug | Pin) -> float:
    """Chamfer length that guides the part in: the receptacle's for plugs, the pin's own for pins."""
    return PLUG_LEAD_IN if isinstance(part, Plug) else part.lead_in


def contact_start(plug: Plug) -> float:
    """Engaged depth at which the contacts meet: dsub pins sit recessed, blade contacts mate late."""
    return 1.5 if plug.family == "dsub" else 0.4 * plug.mate_length


def target_depth(part: Plug | Pin) -> float:
    """Engaged depth the robot is commanded to (before overtravel): the stop or the insertion depth."""
    return part.mate_length if isinstance(part, Plug) else part.insert_depth


def static_curves(part: Plug | Pin, cond: TrialConditions, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Elastic force E(x) and friction level C(x), in N, at part depths x (mm from the start position)."""
    s = x - cond.gap                      # engaged depth
    lead = lead_in_length(part)
    e = cond.misalignment
    engaged = smoothstep(s / lead)
    # lateral spring energy k e^2 / 2 released over the chamfer: mean axial force k e^2 / (2 lead)
    elastic = LATERAL_STIFFNESS * e * e / lead * hump(s / lead)
    preload = 0.3 * LATERAL_STIFFNESS * e * engaged
    if isinstance(part, Plug):
        mu_c, mu_s = CONTACT_FRICTION * cond.friction_scale, SHELL_FRICTION * cond.friction_scale
        normal = CONTACT_NORMAL * part.contact_size
        s0 = contact_start(part)
        friction = mu_s * (SHELL_PRESSURE * outline_polygon(part.outline, part.width, part.height).length
                           * engaged + preload)
        for offset in cond.contact_offsets:
            u = (s - s0 - offset) / CONTACT_ENTRY
            elastic = elastic + normal * hump(u)
            friction = friction + mu_c * normal * smoothstep(u)
        crest = (0.9 if part.family == "rj45" else 0.55) * part.mate_length
        elastic = elastic + part.detents * part.detent_strength * detent(s, crest, DETENT_WIDTH)
        elastic = elastic + stop(s, part.mate_length, STOP_STIFFNESS)
        return elastic, friction
    mu = PIN_FRICTION * cond.friction_scale
    bore = BORE_PRESSURE * np.pi * part.diameter * np.clip(s, 0.0, None) * engaged
    friction = mu * (bore + preload)
    if part.taper > 0:  # the 1:50 taper closes the bore clearance at the commanded depth
        seat = part.insert_depth
        interference = part.taper * np.clip(s - seat, 0.0, None)
        normal = TAPER_SEAT_STIFFNESS * np.pi * part.diameter * seat * interference
        elastic = elastic + normal * part.taper / 2
        friction = friction + mu * normal
    return elastic, friction
