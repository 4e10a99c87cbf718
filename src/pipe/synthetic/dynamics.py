"""Robot, gripper and force-sensor dynamics of an insertion, integrated for many trials at once.

Three second-order subsystems in series, integrated with semi-implicit Euler at 10 kHz:
  robot:   the TCP p follows the commanded trajectory (position control, critically damped);
  gripper: the part (mass m) hangs on the TCP through a compliant grip (k, c) and meets the contact
           force E(x) + f, where the friction f follows Dahl's model (presliding, stick in the hold);
  sensor:  the wrist sensor's low-pass filter turns the grip force into the reading.
The measured depth is the TCP position p, the measured force the filtered grip force.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

INTERNAL_RATE_HZ = 10_000
ROBOT_BANDWIDTH_HZ = 8.0
GRIP_STIFFNESS = 40.0          # N/mm
GRIP_DAMPING_RATIO = 0.15
PART_MASS = 0.08               # kg: part plus gripper fingers
SENSOR_BANDWIDTH_HZ = 100.0
SENSOR_DAMPING_RATIO = 0.7
DAHL_LENGTH = 0.02             # mm of presliding before friction is fully developed


@dataclass(frozen=True)
class ContactTables:
    """E(x) and C(x) of each trial sampled on a common uniform depth grid starting at 0."""

    step: float                # mm
    elastic: np.ndarray        # (trials, grid) N
    friction: np.ndarray       # (trials, grid) N

    def lookup(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pos = np.clip(x / self.step, 0.0, self.elastic.shape[1] - 1.000001)
        i = pos.astype(np.intp)
        w = pos - i
        rows = np.arange(len(x))
        e = self.elastic[rows, i] * (1 - w) + self.elastic[rows, i + 1] * w
        c = self.friction[rows, i] * (1 - w) + self.friction[rows, i + 1] * w
        return e, c


def simulate(command: np.ndarray, tables: ContactTables, decimation: int) -> tuple[np.ndarray, np.ndarray]:
    """Integrate all trials; return the TCP depth [mm] and the sensor force [N] every `decimation` steps.

    `command` is (trials, steps) of commanded TCP depth at INTERNAL_RATE_HZ, all trials starting at rest.
    """
    n_trials, n_steps = command.shape
    dt = 1.0 / INTERNAL_RATE_HZ
    w_r = 2 * np.pi * ROBOT_BANDWIDTH_HZ
    w_s = 2 * np.pi * SENSOR_BANDWIDTH_HZ
    k = GRIP_STIFFNESS * 1e3                                   # N/m
    c = 2 * GRIP_DAMPING_RATIO * np.sqrt(k * PART_MASS)        # N s/m
    to_accel = 1e3 / PART_MASS                                 # N -> mm/s^2
    p, v = np.zeros(n_trials), np.zeros(n_trials)              # TCP [mm, mm/s]
    x, u = np.zeros(n_trials), np.zeros(n_trials)              # part
    f = np.zeros(n_trials)                                     # Dahl friction [N]
    y, yd = np.zeros(n_trials), np.zeros(n_trials)             # sensor reading and its rate
    n_out = (n_steps - 1) // decimation + 1
    depth, force = np.empty((n_trials, n_out)), np.empty((n_trials, n_out))
    for step in range(n_steps):
        if step % decimation == 0:
            depth[:, step // decimation] = p
            force[:, step // decimation] = y
        v += dt * (w_r * w_r * (command[:, step] - p) - 2 * w_r * v)
        p += dt * v
        elastic, level = tables.lookup(x)
        target = level * np.sign(u)
        f = target + (f - target) * np.exp(-np.abs(u) * dt / DAHL_LENGTH)
        grip = k * 1e-3 * (p - x) + c * 1e-3 * (v - u)             # N (mm -> m)
        u += dt * to_accel * (grip - elastic - f)
        x += dt * u
        yd += dt * (w_s * w_s * (grip - y) - 2 * SENSOR_DAMPING_RATIO * w_s * yd)
        y += dt * yd
    return depth, force


def static_tcp_depth(x: np.ndarray, static_force: np.ndarray) -> np.ndarray:
    """TCP depth at which the part sits at depth x under a quasi-static force: the grip deflects by F / k."""
    return x + static_force / GRIP_STIFFNESS


def command_profile(gap: float, depth: float, speed: float, rest_s: float, hold_s: float,
                    accel: float = 150.0) -> np.ndarray:
    """Commanded TCP depth at INTERNAL_RATE_HZ: rest, trapezoidal-velocity move to gap + depth, hold."""
    distance = gap + depth
    t_acc = min(speed / accel, np.sqrt(distance / accel))
    v_top = accel * t_acc
    t_move = 2 * t_acc + (distance - accel * t_acc**2) / v_top
    t = np.arange(int(np.ceil((rest_s + t_move + hold_s) * INTERNAL_RATE_HZ)) + 1) / INTERNAL_RATE_HZ
    tm = np.clip(t - rest_s, 0.0, t_move)
    t_dec = t_move - t_acc
    pos = np.where(tm < t_acc, 0.5 * accel * tm**2,
                   np.where(tm < t_dec, 0.5 * accel * t_acc**2 + v_top * (tm - t_acc),
                            distance - 0.5 * accel * (t_move - tm) ** 2))
    return pos
