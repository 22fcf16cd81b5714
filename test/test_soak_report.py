"""The soak's report (bench/chaos_soak.py): CPU per 1000 messages per window, its slope per simulated
hour and the flatness line, from the samples alone (no processes)."""
from __future__ import annotations

from types import SimpleNamespace

from indoor_loc.bench.chaos_soak import cpu_per_1000, format_soak, summarise


def _samples(cost_growth: float) -> list[dict]:
    """A node taking 10 000 messages per simulated hour whose CPU per 1000 messages starts at 0.5 s
    and grows by ``cost_growth`` s per hour; its memory flat at 100 MB."""
    out, cpu, taken = [], 0.0, 0
    for i in range(17):
        h = i * 0.5
        out.append({"sim_h": h, "wall_s": 60.0 * i, "sent": taken,
                    "nodes": {"/a/tll_pf": {"rss_kb": 100 * 1024, "cpu_s": cpu, "taken": taken, "p50_ms": 1.0,
                                            "lost": 0}}})
        cpu += 5.0 * (0.5 + cost_growth * (h + 0.25))        # 5 000 messages in the next half hour
        taken += 5000
    return out


def _harness() -> SimpleNamespace:
    return SimpleNamespace(nodes={"/a/tll_pf": SimpleNamespace(deaths=[], diag_gaps=[], probes_unanswered=0)})


def test_cpu_per_1000_messages_per_window():
    rows = [(s["sim_h"], s["nodes"]["/a/tll_pf"]) for s in _samples(0.1)]
    t, cost = cpu_per_1000(rows)
    assert len(t) == 16 and abs(cost[0] - 0.525) < 1e-9 and abs(cost[-1] - (0.5 + 0.1 * 7.75)) < 1e-9
    t, cost = cpu_per_1000(rows, min_msgs=10_000)          # windows spanning two samples each
    assert len(t) == 8 and abs(t[0] - 0.5) < 1e-9 and abs(cost[0] - (0.525 + 0.575) / 2) < 1e-9


def test_a_growing_per_message_cost_is_reported_and_a_flat_one_is_not():
    grows = summarise(_samples(0.1), _harness(), warmup_h=0.1)["/a/tll_pf"]
    flat = summarise(_samples(0.0), _harness(), warmup_h=0.1)["/a/tll_pf"]
    assert abs(grows["cpu_per_1000_per_h"] - 0.1) < 1e-6 and abs(flat["cpu_per_1000_per_h"]) < 1e-9
    assert any("CPU per message grows" in b for b in grows["broken"]) and not flat["broken"]
    report = format_soak(_samples(0.1), {"/a/tll_pf": grows})
    assert "CPU s per 1000 msgs" in report and "MB/h (flat), CPU +0.1000 s per 1000 msgs per h (NOT flat)" in report
    assert abs(grows["cpu_per_1000_per_h_2nd_half"] - 0.1) < 1e-6 and abs(flat["rss_mb_per_h_2nd_half"]) < 1e-9
