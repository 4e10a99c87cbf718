"""A part's trials aligned on their final depth (`data.align_final_depth`).

A recorded depth p_z counts from where the robot started, and the start's distance to the mating part (the gap)
changes from trial to trial, so the same feature of the part (a lead-in's peak, a detent, the seat) lies at a
different p_z in every trial. An insertion ends seated, so its deepest point is the same place of the part up to
the overtravel. Shifting each trial's depth so that its deepest point is the part's median over its trials puts a
part's features at one depth in all of its trials, from the motions alone (no force is read). A single trial
(e.g. `predict.py`'s trajectory) is its own median and is left as it is.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pipe.data.prepared import PartData


def final_depth_shifts(deepest: list[float]) -> list[float]:
    """Per trial, the shift in mm that moves its deepest point to the median of all of them."""
    common = float(np.median(deepest))
    return [common - end for end in deepest]


def align_final_depth(part: PartData) -> PartData:
    """The part with each trial's depth (and true static curve) shifted by `final_depth_shifts`; a part without
    trials as it is."""
    if not part.profiles:
        return part
    shifts = final_depth_shifts([float(np.max(profile.depth)) for profile in part.profiles])
    profiles = [replace(profile, depth=profile.depth + shift) for profile, shift in zip(part.profiles, shifts)]
    statics = [None if curve is None else replace(curve, depth=curve.depth + shift)
               for curve, shift in zip(part.static_curves, shifts)]
    return replace(part, profiles=profiles, static_curves=statics)
