"""The floors of a recorded run over time (``OUT/demo_floors.png`` of ``indoor-loc demo --floors 3``):
per walker, the true floor and each causal estimator's floor (the floor nearest its pose z) against
time, so floor changes, their detection and any wrong floor show at a glance. Written only when the
simulated building has several floors and a walker changes floor."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

SEC = 1_000_000_000
#: (topic relative to the walker, label, style) drawn per walker; ``{user}`` is the walker's name
FLOOR_TOPICS = (("wifi/fix", "wifi/fix", dict(ls="", marker=".", ms=3, color="tab:orange", alpha=0.7)),
                ("pdr_kf/pose", "pdr_kf/pose", dict(lw=1.0, color="tab:purple")),
                ("pf/pose", "pf/pose", dict(lw=1.0, color="tab:red")),
                ("backend/{user}/pose", "backend/<user>/pose", dict(lw=1.0, color="tab:green")))


def _truth_floors(path: Path) -> tuple[np.ndarray, np.ndarray]:
    rows = list(csv.DictReader(open(path)))
    return (np.array([int(r["stamp_ns"]) for r in rows], np.int64), np.array([int(r["floor"]) for r in rows]))


def plot_floors(png: Path, bag: Path, sim_dir: Path, walkers: list[str]) -> Path | None:
    """Draw the figure into ``png``; None (nothing written) when the building has one floor or no
    walker changes floor."""
    from indoor_loc.bag import read_bag
    from indoor_loc.sim.building import load_building

    fz = np.asarray(load_building(Path(sim_dir) / "building.geojson").floor_z, float)
    truths = {w: _truth_floors(Path(sim_dir) / "truth" / f"{w}.csv") for w in walkers
              if (Path(sim_dir) / "truth" / f"{w}.csv").exists()}
    if len(fz) < 2 or not any(len(np.unique(f)) > 1 for _, f in truths.values()):
        return None
    wanted = {}
    for w in truths:
        for rel, label, style in FLOOR_TOPICS:
            t = rel.format(user=w)
            wanted[f"/{t}" if t.startswith("backend/") else f"/{w}/{t}"] = (w, label, style)
    est: dict[str, list] = {}
    for m in read_bag(bag, topics=list(wanted)):
        st = m.msg.header.stamp
        est.setdefault(m.topic, []).append((st.sec * SEC + st.nanosec, m.msg.pose.pose.position.z))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(len(truths), 1, figsize=(11, 2.6 * len(truths)), dpi=100, squeeze=False)
    try:
        for ax, (w, (tt, tf)) in zip(axes[:, 0], truths.items()):
            t0 = tt[0]
            ax.plot((tt - t0) / SEC, tf, color="black", lw=3.0, alpha=0.35, label="ground truth")
            for topic, (who, label, style) in wanted.items():
                if who != w or topic not in est:
                    continue
                a = np.array(sorted(est[topic]))
                fl = np.argmin(np.abs(a[:, 1][:, None] - fz[None]), axis=1)
                ax.step((a[:, 0] - t0) / SEC, fl + 0.04 * (list(wanted.values()).index((who, label, style)) % 4 - 1.5),
                        where="post", label=label, **style)
            ax.set_yticks(range(len(fz)), [f"floor {k} ({z:g} m)" for k, z in enumerate(fz)])
            ax.set_ylim(-0.4, len(fz) - 0.6)
            ax.set_title(f"/{w}: floor over time (each estimate's floor = the floor nearest its pose z)")
            ax.set_xlabel("time since the start (s)")
            ax.legend(loc="upper right", fontsize=8, framealpha=0.85, ncol=5)
        fig.tight_layout()
        png.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(png)
    finally:
        plt.close(fig)
    return png
