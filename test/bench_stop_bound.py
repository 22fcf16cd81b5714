"""Bench (not a test): backend_node with N synthetic users over DDS, stopped with SIGINT while it
still works through a burst of their messages. Prints how long the stop took, how many users'
final paths a live subscriber received, what the node said it cut short, and get_parameters
latencies during the burst.

``ROS_DOMAIN_ID=13 .venv/bin/python test/bench_stop_bound.py 500 [--stop-after S]``
"""
from __future__ import annotations

import argparse
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from backend_synth import survey  # noqa: E402
from helpers_dds import PEERS, Peer, child_env, ros_node, spin_until  # noqa: E402
from indoor_loc.contract import Qos  # noqa: E402
from indoor_loc.nodes.qos import qos_profile  # noqa: E402
from indoor_loc.wifi.radiomap import save_radiomap  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("users", type=int)
    ap.add_argument("--length-m", type=float, default=12.0, help="each user's walk along the corridor")
    ap.add_argument("--stop-after", type=float, default=1.0, help="SIGINT this long after the burst is queued, s")
    a = ap.parse_args()
    import subprocess

    from nav_msgs.msg import Path as PathMsg
    from rcl_interfaces.srv import GetParameters

    n = a.users
    tmp = Path(tempfile.mkdtemp(prefix="stop_bound_"))
    rm = save_radiomap(survey(0, 60, np.random.default_rng(1)), tmp / "map")
    params = tmp / "params.yaml"
    users = ", ".join(f"u{u}" for u in range(n))
    params.write_text(f"/**/backend_node:\n  ros__parameters:\n    radiomap: {rm}\n    users: [{users}]\n"
                      "    wknn: {shared_threshold: 0.75, shared_strict: false}\n")
    t_start = time.monotonic()
    node_proc = Peer([sys.executable, "-m", "indoor_loc.nodes.backend_node", "--ros-args", "--params-file",
                      str(params)], env=child_env())
    load = Peer([sys.executable, str(PEERS / "backend_burst.py"), str(n), "7", str(a.length_m), "stay"],
                env=child_env(), stdin=subprocess.PIPE)
    try:
        with ros_node("bench_probe") as (node, ex):
            paths: dict[str, object] = {}
            for u in range(n):
                node.create_subscription(PathMsg, f"/backend/u{u}/path", lambda m, u=u: paths.__setitem__(f"u{u}", m),
                                         qos_profile(Qos.LATCHED))
            cli = node.create_client(GetParameters, "/backend_node/get_parameters")
            assert spin_until(ex, cli.service_is_ready, 300), node_proc.output()
            assert load.wait_line("matched", 600), load.output()
            assert spin_until(ex, lambda: all(node.count_publishers(f"/backend/u{u}/path") > 0 for u in range(n)), 300)
            print(f"{n} users matched after {time.monotonic() - t_start:.0f} s", flush=True)
            assert load.proc.stdin is not None
            load.proc.stdin.write("go\n")
            load.proc.stdin.flush()
            sent = load.wait_line("sent", 300)
            assert load.wait_line("acked", 300), load.output()
            print(f"burst: {sent}, queued in the node", flush=True)
            lat = []
            until = time.monotonic() + a.stop_after
            while time.monotonic() < until:
                t = time.monotonic()
                fut = cli.call_async(GetParameters.Request(names=["user_timeout_s"]))
                spin_until(ex, fut.done, 30)
                lat.append(time.monotonic() - t)
                spin_until(ex, lambda: False, 0.05)
            t0 = time.monotonic()
            node_proc.signal(signal.SIGINT)
            rc = node_proc.wait(timeout=120)
            took = time.monotonic() - t0
            spin_until(ex, lambda: len(paths) == n, 10)
            arr = np.sort(lat) if lat else np.zeros(1)
            print(f"SIGINT -> exit {took:.1f} s (status {rc}); final paths received: {len(paths)} of {n}")
            print(f"get_parameters during the burst: {len(lat)} requests, median {np.median(arr) * 1e3:.0f} ms, "
                  f"max {arr[-1] * 1e3:.0f} ms")
            for line in node_proc.lines:
                if "stopping" in line or "end of input" in line or "still not ended" in line:
                    print("  node:", line[:400])
            if rc != 0:
                print("\n".join(node_proc.lines[-30:]))
    finally:
        load.stop()
        node_proc.stop()


if __name__ == "__main__":
    main()
