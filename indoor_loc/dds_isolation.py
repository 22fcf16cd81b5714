"""Keep a demo on its machine: localhost-only discovery and a DDS domain nothing else here uses.

ROS 2 nodes on ``ROS_DOMAIN_ID`` 0 with default discovery see (and are seen by) every ROS 2 system
on the LAN: a demo's simulated walkers would show up on a robot next door. Unless the user set them,
the demo runs with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and on the first domain from
``FIRST_DOMAIN`` whose RTPS port range no local socket has bound.

RTPS (DDSI-RTPS 2.x, section 9.6.1.1, default port mapping) gives domain ``d`` the UDP ports
``7400 + 250 d`` to ``7400 + 250 d + 249``: a participant on this machine in domain ``d`` has bound
some of them (Fast DDS: ``7410 + 250 d + 2 id`` and the next for each participant ``id``).
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

PORT_BASE, DOMAIN_GAIN, PORTS_PER_DOMAIN = 7400, 250, 250
#: the highest domain id Fast DDS accepts (its port numbers overflow above)
MAX_DOMAIN = 232
FIRST_DOMAIN = 100


def bound_udp_ports(proc_net: Path = Path("/proc/net")) -> set[int]:
    """Local UDP ports bound on this machine (Linux ``/proc/net/udp``, ``udp6``); empty elsewhere."""
    ports: set[int] = set()
    for name in ("udp", "udp6"):
        try:
            lines = (proc_net / name).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) > 1 and ":" in fields[1]:
                ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


def domain_in_use(domain: int, ports: set[int]) -> bool:
    low = PORT_BASE + DOMAIN_GAIN * domain
    return any(low <= p < low + PORTS_PER_DOMAIN for p in ports)


def isolated_env(environ: Mapping[str, str], ports: set[int] | None = None) -> tuple[dict[str, str], str]:
    """``ROS_DOMAIN_ID`` and ``ROS_AUTOMATIC_DISCOVERY_RANGE`` for the demo's processes and a sentence
    saying what was chosen: the user's values when set, else localhost and an unused domain."""
    ports = bound_udp_ports() if ports is None else ports
    env: dict[str, str] = {}
    said = []
    if environ.get("ROS_DOMAIN_ID", "").strip():
        env["ROS_DOMAIN_ID"] = environ["ROS_DOMAIN_ID"].strip()
        said.append(f"ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']} (yours)")
    else:
        free = next((d for d in range(FIRST_DOMAIN, MAX_DOMAIN + 1) if not domain_in_use(d, ports)), FIRST_DOMAIN)
        env["ROS_DOMAIN_ID"] = str(free)
        said.append(f"ROS_DOMAIN_ID={free} (no other DDS participant on this machine uses it; set ROS_DOMAIN_ID "
                    f"to choose)")
    rng = environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").strip()
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = rng or "LOCALHOST"
    said.append(f"discovery {env['ROS_AUTOMATIC_DISCOVERY_RANGE']}" + (
        " (yours)" if rng else ": nothing leaves this machine (set ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET to be "
                               "seen on the network)"))
    return env, "; ".join(said)
