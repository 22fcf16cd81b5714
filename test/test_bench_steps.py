"""``indoor-loc bench steps``: dataset readers (true counts as the datasets README defines them),
the stage-driven counter against the core, and the summary figures."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import DATASETS, dataset
from indoor_loc.bench.steps import (load_dev_walk, load_validation_walk, stage_steps, summary,
                                    validation_files)
from indoor_loc.imu.stepometer import stepometer_batch, total_steps
from test_stepometer import walk_signal


def test_dev_walk_true_count_is_rising_edges_of_both_channels():
    root = dataset("oxford_steps/optimisation_dev")
    w = load_dev_walk(root / "Samsung_Carmelo_Hard_InHand_2")     # notes.txt: "301 steps"
    assert w.true_steps == 301 == len(w.step_ns)
    assert w.position == "hand" and w.person == "Carmelo" and w.set == "dev"
    sc = np.loadtxt(root / "Samsung_Carmelo_Hard_InHand_2" / "stepcounter.csv", delimiter=",", dtype=np.int64)
    assert w.stamps_ns[0] >= sc[0, 0] and w.stamps_ns[-1] <= sc[-1, 0]
    assert np.all(np.diff(w.stamps_ns) >= 0) and w.acc.shape == (len(w.stamps_ns), 3)


def test_validation_walk_counts_and_phone_counters():
    dataset("oxford_steps/validation")
    files = {p.stem.split("_")[0] + "_" + p.stem.split("_")[1]: p for p in validation_files(DATASETS)}
    w = load_validation_walk(files["user2_bag"])
    d = np.loadtxt(files["user2_bag"], delimiter=",")
    d = d[np.any(d[:, 1:4] != 0, axis=1)]
    assert w.true_steps == round(d[-1, 5] - d[0, 5]) == len(w.step_ns)
    assert w.phone["algo_steps"] == d[-1, 4] - d[0, 4] and "hw_steps" in w.phone
    assert w.position == "bag"


def test_stage_counter_equals_core_batch(rng):
    """Through ImuStage (messages in, pdr/odom out, steps = |Δp| / step length) = the core's count."""
    stamps, acc = walk_signal(rng, duration_s=30.0, rate_hz=100.0)
    via_stage, info = stage_steps(stamps, acc)
    assert info["rejected"] == 0 and info["odom"] > 50
    assert via_stage == pytest.approx(total_steps(stepometer_batch(stamps, acc)), rel=1e-9)


def test_summary_figures():
    rows = [{"x_err_pct": e} for e in (-1.0, 0.5, 2.0, -4.0, 0.0)]
    s = summary(rows, "x")
    assert s["n"] == 5 and s["median"] == 1.0 and s["max"] == 4.0
    assert s["p90"] == pytest.approx(np.percentile([1, 0.5, 2, 4, 0], 90))
    assert s["mean_signed"] == pytest.approx(-0.5)
    assert summary(rows, "y") == {}


def test_carpet_walk_holds_at_a_quarter_of_its_amplitude():
    """Pixel, in hand, carpet (development walk): the count holds when the |a| variation is scaled to
    25 % (a softer floor / smoother gait); the former 0.5 m/s² amplitude gate lost most of it."""
    from indoor_loc.imu.stepometer_types import StepometerParams
    w = load_dev_walk(dataset("oxford_steps/optimisation_dev") / "Pixel_Jamie_Carpet_InHand_3")
    mag = np.linalg.norm(w.acc, axis=1)
    g = mag.mean()
    soft = w.acc * ((g + 0.25 * (mag - g)) / mag)[:, None]
    for acc in (w.acc, soft):
        err = (total_steps(stepometer_batch(w.stamps_ns, acc)) - w.true_steps) / w.true_steps
        assert abs(err) < 0.025
    old_gate = total_steps(stepometer_batch(w.stamps_ns, soft, StepometerParams(min_std_m_s2=0.5)))
    assert old_gate < 0.7 * w.true_steps


def test_tuning_walks_are_development_walks():
    """The walks named as tuned on exist among the development walks (a renamed folder would silently
    move a walk into the held-out group)."""
    from indoor_loc.bench.steps import TUNING_WALKS, dev_walk_dirs
    names = {p.name for p in dev_walk_dirs(dataset("oxford_steps/optimisation_dev").parents[1])}
    assert len(TUNING_WALKS) == 15 and TUNING_WALKS <= names and len(names - TUNING_WALKS) == 13
