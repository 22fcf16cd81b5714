"""``make demo``'s default run (``indoor-loc demo`` defaults, ``--robots 1``): its walkers change floors
in the two-floor sample building with a barometer in every phone, and the floors picture shows it."""
from __future__ import annotations

import argparse
import csv

import numpy as np

from indoor_loc import demo
from indoor_loc.floors_plot import plot_floors


def test_the_default_demo_has_walkers_changing_floors_and_draws_them(tmp_path):
    parser = argparse.ArgumentParser()
    demo.add_arguments(parser)
    args = parser.parse_args(["--robots", "1", "--out", str(tmp_path)])        # as `make demo`
    sim = demo._simulate(tmp_path, args)
    changed = []
    for w in sim["walkers"]:
        rows = list(csv.DictReader(open(sim["dir"] / "truth" / f"{w}.csv")))
        floors = np.array([int(r["floor"]) for r in rows])
        t = np.array([int(r["stamp_ns"]) for r in rows])
        if len(np.unique(floors)) > 1:
            changed.append((w, (t[np.argmax(floors != floors[0])] - t[0]) / 1e9))
    assert changed and min(s for _, s in changed) < args.duration - 10, changed   # seen for a while
    params = (sim["dir"] / "params.yaml").read_text()
    assert "heights_m" in params                          # the estimators know the building's floors
    assert "&id" not in params and "*id" not in params    # no yaml alias: rcl refuses the whole file
    from indoor_loc.bag.reader import bag_topics
    assert any(t.endswith("/baro/pressure") for t in bag_topics(sim["bag"]))
    png = plot_floors(tmp_path / "demo_floors.png", sim["bag"], sim["dir"], sim["walkers"])
    assert png is not None and png.stat().st_size > 10_000
