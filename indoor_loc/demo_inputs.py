"""Did every played input reach the node that consumes it? Counted for the demo's score table.

The player's messages per topic come from the simulated bag; what each node received, lost in DDS
(sequence gaps) and missed before its subscription matched comes from the last ``/diagnostics``
status of that node in the recording (each node publishes a last status when it stops, before the
recorder stops).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

#: (relative input topic, the node that consumes it in the demo's namespaces)
CONSUMED = [("imu/data_raw", "imu_node"), ("imu/mag", "imu_node"), ("wifi/scan", "wifi_fix_node")]


@dataclass(frozen=True)
class InputCount:
    walker: str
    topic: str
    node: str
    played: int
    received: int | None          # None: the node's status was not recorded
    lost: int
    missed_at_start: int

    @property
    def complete(self) -> bool:
        return self.received is not None and self.received >= self.played


def last_statuses(bag: Path) -> dict[str, dict[str, str]]:
    """{status name: its values} of the last ``/diagnostics`` status of each name in a bag."""
    from indoor_loc.bag import read_bag
    out: dict[str, dict[str, str]] = {}
    for m in read_bag([bag], topics=["/diagnostics"]):
        for st in m.msg.status:
            out[st.name] = {kv.key: kv.value for kv in st.values}
    return out


def count_inputs(live: Path, sim_bag: Path, walkers: list[str]) -> list[InputCount]:
    from indoor_loc.bag import bag_info
    played = {name: info.count for name, info in bag_info([sim_bag]).items()}
    statuses = last_statuses(live)
    rows = []
    for w in walkers:
        for topic, node in CONSUMED:
            n = played.get(f"/{w}/{topic}", 0)
            if n == 0:
                continue
            values = statuses.get(f"/{w}/{node}")
            received = int(values[f"in.{topic}.count"]) if values and f"in.{topic}.count" in values else None
            rows.append(InputCount(w, topic, node, n, received,
                                   int((values or {}).get(f"lost.{topic}", 0)),
                                   int((values or {}).get(f"missed_at_start.{topic}", 0))))
    return rows


def format_inputs(rows: list[InputCount]) -> str:
    if rows and all(r.complete for r in rows):
        total = sum(r.played for r in rows)
        return (f"inputs: every played message reached its node ({total} messages: "
                + ", ".join(f"{t} -> {n}" for t, n in CONSUMED) + ", each walker's)")
    lines = ["inputs NOT complete (the scores above lack these messages):"]
    for r in rows:
        if not r.complete:
            got = "no status recorded" if r.received is None else f"{r.received} received"
            lines.append(f"   /{r.walker}/{r.topic}: played {r.played}, /{r.walker}/{r.node} {got} "
                         f"(lost {r.lost}, of which published before its subscription matched {r.missed_at_start})")
    return "\n".join(lines)
