"""PNG plots of an estimated trajectory against the ground truth on the floor plan (matplotlib, Agg).

The floor plan image is drawn with ``extent`` (x_min, x_max, y_min, y_max) in metres of the map
frame (for PUTMC: (0, 3049/28.50518, 0, 1049/28.50518), ENU, bottom-left corner at (0, 0)).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from indoor_loc.eval.metrics import interpolate_xy
from indoor_loc.eval.trajectory import Trajectory, Truth


def plot_walk(out_png: str | Path, truth: Truth, traj: Trajectory | None = None, *,
              floor_plan: str | Path | None = None, extent: tuple[float, float, float, float] | None = None,
              title: str = "") -> Path:
    """Draw the GT route (green), the true scan positions (black ×), the trajectory (blue) and, per
    scan, a red line from the trajectory at the scan time to the true position. Returns the path."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(14, 5.5), dpi=110)
    try:
        if floor_plan is not None and Path(floor_plan).exists() and extent is not None:
            img = plt.imread(str(floor_plan))
            ax.imshow(img, extent=extent, origin="upper", cmap="gray" if img.ndim == 2 else None, alpha=0.6,
                      zorder=0)
        for k, (a, b) in enumerate(np.asarray(truth.segments)):
            ax.plot([a[0], b[0]], [a[1], b[1]], color="tab:green", lw=2.5, alpha=0.8, zorder=1,
                    label="GT route" if k == 0 else None)
        if len(truth.scan_xy):
            ax.scatter(truth.scan_xy[:, 0], truth.scan_xy[:, 1], marker="x", color="black", s=30, zorder=3,
                       label="true scan positions")
        if traj is not None and len(traj):
            ax.plot(traj.xy[:, 0], traj.xy[:, 1], "-o", color="tab:blue", ms=2.5, lw=1.0, zorder=2,
                    label=f"estimate ({len(traj)} poses)")
            if len(truth.scan_ns):
                est, _ = interpolate_xy(traj.stamps_ns, traj.xy, truth.scan_ns)
                for (x0, y0), (x1, y1) in zip(est, truth.scan_xy):
                    ax.plot([x0, x1], [y0, y1], color="tab:red", lw=0.8, zorder=2)
        if extent is not None:
            ax.set_xlim(extent[0], extent[1])
            ax.set_ylim(extent[2], extent[3])
        ax.set_aspect("equal")
        ax.set_xlabel("x [m] (map, ENU)")
        ax.set_ylabel("y [m]")
        ax.set_title(title or truth.name)
        ax.legend(loc="upper right", fontsize=8)
        fig.tight_layout()
        fig.savefig(out_png)
    finally:
        plt.close(fig)
    return out_png
