"""From a raw recording to one insertion trial in pipe's conventions, with a report of what was cut.

The rule (README, "Bringing your own recordings"):
1. Depth is the TCP's displacement along the insertion axis (`axis` of the base frame, or of the tool frame
   with `frame="tool"`, where each sample's own tool axis is used), counted positive in `direction`.
2. The resisting force is the force along that axis opposing the motion: minus the force acting on the tool
   (UR's `actual_TCP_force`) along the direction of motion; `force_sign=-1` for sensors that report the
   force the tool exerts. Its bias, the mean over the first `bias_s` of the recording (free space), is
   removed.
3. Contact starts at the first sample from which the resisting force stays above `contact_threshold_n`
   for at least `contact_min_s`. The trial keeps `approach_s` before it.
4. The retreat is cut: after the deepest point, from the first sample more than `retreat_mm` shallower.
5. Time starts at 0 and depth at 0 at the first kept sample.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from pipe.errors import DatasetError
from pipe.importing.recording import AXES, Recording

FRAMES = ("base", "tool")


@dataclass(frozen=True)
class InsertionSettings:
    axis: str = "z"
    direction: int | None = None       # +1 or -1; default -1 in the base frame (a UR inserting downwards),
    frame: str = "base"                #   +1 in the tool frame (along the tool's approach axis)
    force_sign: int = 1
    contact_threshold_n: float = 1.0
    contact_min_s: float = 0.02
    approach_s: float = 0.2
    retreat_mm: float = 0.2
    bias_s: float = 0.1

    def __post_init__(self) -> None:
        if self.axis not in AXES:
            raise DatasetError(f"insertion axis {self.axis!r} is not one of x, y, z")
        if self.frame not in FRAMES:
            raise DatasetError(f"frame {self.frame!r} is not one of {', '.join(FRAMES)}")
        for name in ("direction", "force_sign"):
            value = getattr(self, name)
            if value not in (1, -1) and not (name == "direction" and value is None):
                raise DatasetError(f"{name} must be 1 or -1, got {value!r}")
        for name in ("contact_threshold_n", "contact_min_s", "approach_s", "retreat_mm", "bias_s"):
            if not getattr(self, name) >= 0:
                raise DatasetError(f"{name} must be a number >= 0, got {getattr(self, name)!r}")

    @property
    def sign(self) -> int:
        if self.direction is not None:
            return self.direction
        return 1 if self.frame == "tool" else -1


@dataclass
class Insertion:
    """One imported trial (time s from 0, depth mm from 0, resisting force N) and what was done to it."""

    time: np.ndarray
    depth: np.ndarray
    force: np.ndarray
    report: dict = field(default_factory=dict)


def project(recording: Recording, settings: InsertionSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth along the insertion direction (N,), the resisting force along it (N,) and the force in the
    frame of the axis (N, 3), before any cutting or zeroing."""
    k = AXES.index(settings.axis)
    unit = np.zeros(3)
    unit[k] = settings.sign
    needs_rotation = settings.frame == "tool" or recording.force_in_tool_frame
    if needs_rotation and recording.rotation is None:
        raise DatasetError("this recording has no tool orientation, which the tool frame needs "
                           "(--frame tool, or a force in the tool frame); give rotation columns or use the base frame",
                           recording.path)
    rotation = Rotation.from_rotvec(recording.rotation) if needs_rotation else None
    if settings.frame == "tool":
        direction = rotation.apply(unit)                                      # (N, 3) in the base frame
        force = recording.force if recording.force_in_tool_frame else rotation.inv().apply(recording.force)
    else:
        direction = np.broadcast_to(unit, recording.position.shape)
        force = rotation.apply(recording.force) if recording.force_in_tool_frame else recording.force
    depth = np.einsum("ij,ij->i", recording.position - recording.position[0], direction)
    resisting = -settings.force_sign * settings.sign * force[:, k]
    return depth, resisting, force


def contact_start(time: np.ndarray, above: np.ndarray, min_s: float) -> int | None:
    """The first index from which `above` holds for at least `min_s` seconds (to the run's last sample)."""
    edges = np.diff(np.concatenate([[0], above.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    for start, end in zip(starts, ends):
        if time[end] - time[start] >= min_s:
            return int(start)
    return None


def extract_insertion(recording: Recording, settings: InsertionSettings) -> Insertion:
    """Cut one insertion out of a recording by the module's rule; `DatasetError` when it has no contact."""
    time = recording.time
    depth, resisting, force = project(recording, settings)
    bias_count = max(1, int(np.searchsorted(time - time[0], settings.bias_s, side="right")))
    bias = float(resisting[:bias_count].mean())
    resisting = resisting - bias
    inserting = slice(0, int(np.argmax(depth)) + 1)         # contact is sought up to the deepest point
    start = contact_start(time[inserting], resisting[inserting] > settings.contact_threshold_n, settings.contact_min_s)
    if start is None:
        raise DatasetError(f"no contact found: up to the deepest point the resisting force along {settings.axis} "
                           f"never stays above {settings.contact_threshold_n:g} N for {settings.contact_min_s:g} "
                           f"s{no_contact_hint(time[inserting], depth, resisting[inserting], settings)}",
                           recording.path)
    first = int(np.searchsorted(time, time[start] - settings.approach_s, side="left"))
    relative = depth - depth[first]
    deepest = first + int(np.argmax(relative[first:]))
    shallower = np.flatnonzero(relative[deepest:] < relative[deepest] - settings.retreat_mm)
    end = deepest + int(shallower[0]) if shallower.size else len(time)
    kept = slice(first, end)
    warnings = contradictions(recording, settings, depth, force, kept)
    if time[start] - time[0] < settings.approach_s:
        warnings.append(f"only {time[start] - time[0]:.3f} s before contact were recorded "
                        f"({settings.approach_s:g} s asked)")
    report = {
        "file": str(recording.path), "samples": len(time), "kept_samples": end - first,
        "start_stamp_s": float(time[first]),       # the first kept sample's time stamp in the recording's clock
        "kept_from_s": float(time[first] - time[0]), "kept_to_s": float(time[end - 1] - time[0]),
        "contact_at_s": float(time[start] - time[first]), "cut_before_s": float(time[first] - time[0]),
        "cut_retreat_s": float(time[-1] - time[end - 1]), "retreat_cut": bool(shallower.size),
        "depth_max_mm": float(relative[deepest]), "force_max_n": float(resisting[kept].max()),
        "force_bias_n": bias, "settings": asdict(settings) | {"direction": settings.sign}, "warnings": warnings,
    }
    return Insertion(time[kept] - time[first], relative[kept], resisting[kept], report)


def no_contact_hint(time: np.ndarray, depth: np.ndarray, resisting: np.ndarray, settings: InsertionSettings) -> str:
    """Why contact may not have been found: a reversed direction or force sign."""
    if depth.max() < settings.retreat_mm and depth.min() < -settings.retreat_mm:
        return f": the tool moved {-depth.min():.2f} mm against the insertion direction (check --direction)"
    if contact_start(time, -resisting > settings.contact_threshold_n, settings.contact_min_s) is not None:
        return (": the force exceeds it in the other direction, so its sign looks reversed (check --force-sign; "
                "-1 for a sensor that reports the force the tool exerts)")
    return ""


def contradictions(recording: Recording, settings: InsertionSettings, depth: np.ndarray, force: np.ndarray,
                   kept: slice) -> list[str]:
    """Warnings where the data disagree with the chosen axis and direction: the tool moved or was pushed
    mostly along another axis, or moved against the direction."""
    k = AXES.index(settings.axis)
    warnings = []
    travel = np.ptp(recording.position[kept], axis=0)
    if settings.frame == "base" and travel.argmax() != k and travel.max() > 2 * travel[k]:
        warnings.append(f"the tool moved mostly along {AXES[travel.argmax()]} ({travel.max():.2f} mm) and only "
                        f"{travel[k]:.2f} mm along the insertion axis {settings.axis}: check --axis")
    push = np.ptp(force[kept], axis=0)
    if push.argmax() != k and push.max() > 2 * push[k]:
        warnings.append(f"the force changed mostly along {AXES[push.argmax()]} ({push.max():.2f} N) and only "
                        f"{push[k]:.2f} N along the insertion axis {settings.axis}: check --axis and --frame")
    if depth[kept].min() - depth[kept][0] < -max(settings.retreat_mm, 0.5 * np.ptp(depth[kept])):
        warnings.append("the tool moved against the insertion direction for most of the trial: check --direction")
    return warnings
