"""The figure of docs/synthetic.md: force against depth and time for a few parts, trials and ground truth.

    python -m pipe.synthetic.figure docs/figures/synthetic_force_depth.png
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from pipe.data.dataset import ZERO_WINDOW_S, zero_start  # noqa: E402
from pipe.synthetic.generate import simulate_parts  # noqa: E402

FIGURE_PARTS = ["dsub9", "dsub37", "usba", "rj45", "taper8", "dowel6"]


def plot_force_depth(path: str | Path, parts: list[str] = FIGURE_PARTS, seed: int = 0) -> Path:
    trials = simulate_parts(parts, seed)
    fig, axes = plt.subplots(2, len(parts), figsize=(3.2 * len(parts), 6), squeeze=False)
    for col, name in enumerate(parts):
        mine = [t for t in trials if t.part == name]
        top, bottom = axes[0, col], axes[1, col]
        zeroed = [zero_start(t.time, t.force, ZERO_WINDOW_S) for t in mine]  # as the loader delivers it
        for k, (t, force) in enumerate(zip(mine, zeroed)):
            top.plot(t.depth, force, color="tab:blue", lw=0.5, alpha=0.5, label="measured" if k == 0 else None)
            top.plot(t.static_depth, t.static_force, color="k", lw=0.8, alpha=0.6,
                     label="true static" if k == 0 else None)
            bottom.plot(t.time, force, color="tab:blue", lw=0.5, alpha=0.5)
            bottom.plot(t.time, t.depth * max(f.max() for f in zeroed) / t.depth.max(), color="0.4", lw=0.5)
        top.set_title(name)
        top.set_xlabel("depth p_z [mm]")
        bottom.set_xlabel("time [s]")
        if col == 0:
            top.set_ylabel("force F_z [N]")
            bottom.set_ylabel("F_z [N] (grey: p_z, scaled)")
            top.legend(fontsize=7, loc="upper left")
    fig.suptitle(f"Synthetic insertions, 10 trials per part (seed {seed})")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


if __name__ == "__main__":
    print(plot_force_depth(sys.argv[1] if len(sys.argv) > 1 else "docs/figures/synthetic_force_depth.png"))
