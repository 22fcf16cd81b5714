"""``indoor-loc bench backend --live``: all 24 PUTMC walks replayed concurrently over DDS through one
``backend_node`` process, at 1× and 10× real time.

The walks are shifted onto one clock so they all start together (24 users walking at once); this
process publishes each user's ``pdr/odom`` (the front end's hops, as ``imu_node`` publishes them) and
``wifi/scan`` at their stamps scaled by the rate, the node discovers the users from the ROS graph,
and on SIGINT publishes every user's final path. Reported: the node's per-message processing time
(p50 / p99 / max, from its ``/diagnostics``), messages lost, and the final paths' accuracy next to
the same configuration run offline on the same merged stream (:class:`BackendStage` driven
directly) — scored over each walk's first to last scan.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from indoor_loc.backend.putmc_events import PUTMC_GRAPH_PARAMS
from indoor_loc.bench.backend import Putmc
from indoor_loc.eval.metrics import paper_score, point_segment_distance, scan_time_errors
from indoor_loc.imu.pdr import Pdr, PdrParams
from indoor_loc.params import params_file_text
from indoor_loc.wifi.radiomap import save_radiomap

START_NS = 1_000_000_000_000


def merged_messages(data: Putmc) -> list[tuple[int, str, str, object]]:
    """(stamp on the common clock, user, topic, message) of every walk, in stamp order."""
    from msg_adapters.odom import odom_to_msg
    from msg_adapters.wifi_scan import scan_to_msg
    from indoor_loc.wifi.types import WifiScan

    out = []
    for n in data.walks:
        ev = data.events[n]
        events = ev.events()
        shift = START_NS - events[0][0]
        pdr = Pdr(PdrParams(step_length_m=0.65))
        for stamp, kind, payload in events:
            if kind == 0:
                a, b, steps, yaw = payload
                p = pdr.update(a + shift, b + shift, steps, yaw)
                msg = odom_to_msg(p.stamp_ns, f"{ev.name}/odom", f"{ev.name}/base_link", p.x, p.y, p.yaw, p.cov,
                                  p.speed, p.yaw_rate)
                out.append((stamp + shift, ev.name, "pdr/odom", msg))
            else:
                s: WifiScan = payload
                moved = WifiScan(s.stamp_ns + shift, s.bssid, s.rssi_dbm, s.freq_mhz, s.ssid, s.age_ms,
                                 s.frame_id, s.source)
                out.append((stamp + shift, ev.name, "wifi/scan", scan_to_msg(moved)))
    out.sort(key=lambda m: (m[0], m[2] != "pdr/odom"))
    return out


def score_paths(data: Putmc, paths: dict[str, tuple[np.ndarray, np.ndarray]]) -> tuple[float, ...]:
    """Paths on the common clock -> (paper RMSE, paper mean, true mean, scan mean, scan p95, users)."""
    d_all, s_all = [], []
    for n in data.walks:
        name = data.events[n].name
        if name not in paths:
            continue
        st, xy = paths[name]
        shift = START_NS - data.events[n].events()[0][0]
        scan_t, scan_xy = data.truth[n]
        t = scan_t + shift
        inside = (st >= t[0]) & (st <= t[-1])
        d_all.append(point_segment_distance(xy[inside], data.segments[n]))
        s_all.append(scan_time_errors(st, xy, t, scan_xy)[0])
    d, s = np.concatenate(d_all), np.concatenate(s_all)
    ps = paper_score(d)
    k = d[d * d < 100]
    return ps.rmse, ps.mean, float(np.mean(k)), float(np.mean(s)), float(np.percentile(s, 95)), len(paths)


def offline_reference(data: Putmc, msgs, params_values: dict) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    from msg_adapters.path import path_from_msg
    from indoor_loc.params import params_from_dict
    from indoor_loc.pipeline.backend_stage import BackendParams, BackendStage

    st = BackendStage(params_from_dict(BackendParams, params_values), survey=data.survey)
    for stamp, user, topic, msg in msgs:
        st.process(topic, msg, stamp, user)
    outs = st.finish()
    paths = {}
    for topic, msg in outs:
        if topic.endswith("/path"):
            stamps, xy, _ = path_from_msg(msg)
            paths[topic.split("/")[1]] = (stamps, xy)
    return paths


def run_live(data: Putmc, msgs, rate: float, params_file: Path, domain: int) -> dict:
    """One replay at ``rate``: returns latency figures, losses and the final paths."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry, Path as PathMsg
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from indoor_loc.contract import Qos
    from indoor_loc.nodes.base import qos_profile
    from msg_adapters.diagnostics import diagnostics_from_msg
    from msg_adapters.path import path_from_msg

    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "indoor_loc.nodes.backend_node", "--ros-args", "--params-file",
                             str(params_file)], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    ctx = Context()
    rclpy.init(context=ctx)
    node = Node("bench_backend_live", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    users = sorted({m[1] for m in msgs})
    paths: dict[str, object] = {}
    diags: list = []
    try:
        for u in users:
            node.create_subscription(PathMsg, f"/backend/{u}/path", lambda m, u=u: paths.__setitem__(u, m),
                                     qos_profile(Qos.LATCHED))
        node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, qos_profile(Qos.RELIABLE))
        pubs = {(u, t): node.create_publisher(Odometry if t == "pdr/odom" else DiagnosticArray, f"/{u}/{t}",
                                              qos_profile(Qos.RELIABLE))
                for u in users for t in ("pdr/odom", "wifi/scan")}
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not all(p.get_subscription_count() > 0 for p in pubs.values()):
            ex.spin_once(timeout_sec=0.1)
        t_wall0 = time.monotonic()
        t_data0 = msgs[0][0]
        for stamp, user, topic, msg in msgs:
            due = t_wall0 + (stamp - t_data0) * 1e-9 / rate
            while (left := due - time.monotonic()) > 0:
                ex.spin_once(timeout_sec=min(left, 0.05))
            pubs[(user, topic)].publish(msg)
        replay_s = time.monotonic() - t_wall0

        def snapshot() -> dict:
            for m in reversed(diags):
                d = diagnostics_from_msg(m)
                if "/backend_node" in d:
                    return d["/backend_node"].values
            return {}

        def n_in(values: dict) -> int:
            return sum(int(v) for k, v in values.items() if k.startswith("in.") and k.endswith(".count"))

        # let the node work off its queue: wait until its input count stops growing (at most 120 s)
        end, prev, still = time.monotonic() + 120, -1, 0
        while time.monotonic() < end and still < 3:
            t_next = time.monotonic() + 1.0
            while time.monotonic() < t_next:
                ex.spin_once(timeout_sec=0.05)
            cur = n_in(snapshot())
            still = still + 1 if cur == prev else 0
            prev = cur
        drained_s = time.monotonic() - t_wall0
        last = snapshot()
        proc.send_signal(signal.SIGINT)
        end = time.monotonic() + 60
        while time.monotonic() < end and (len(paths) < len(users) or proc.poll() is None):
            ex.spin_once(timeout_sec=0.1)
    finally:
        ex.shutdown(timeout_sec=0.0)
        node.destroy_node()
        ctx.try_shutdown()
        if proc.poll() is None:
            proc.kill()
        out_text = proc.communicate(timeout=10)[0]
    received = sum(int(v) for k, v in last.items() if k.startswith("in.") and k.endswith(".count"))
    return {"rate": rate, "replay_s": replay_s, "drained_s": drained_s, "p50": float(last.get("process_ms.p50", "nan")),
            "p99": float(last.get("process_ms.p99", "nan")), "max": float(last.get("process_ms.max", "nan")),
            "received": received, "sent": len(msgs),
            "paths": {u: (path_from_msg(m)[0], path_from_msg(m)[1]) for u, m in paths.items()},
            "log_tail": out_text[-2000:]}


def run(data: Putmc, rates=(1.0, 10.0)) -> None:
    msgs = merged_messages(data)
    with tempfile.TemporaryDirectory() as tmp:
        rm = save_radiomap(data.survey, Path(tmp) / "survey")
        values = dict(PUTMC_GRAPH_PARAMS, radiomap=str(rm))       # what `indoor-loc import putmc` writes
        params = Path(tmp) / "params.yaml"
        params.write_text(params_file_text({"backend_node": values}))
        offline = score_paths(data, offline_reference(data, msgs, values))
        print("\n## Live over DDS: 24 walks at once through one backend_node (the importer's configuration: "
              "joint + SLE, measured noise, Huber; window 30)\n")
        print(f"{len(msgs)} messages, {(msgs[-1][0] - msgs[0][0]) * 1e-9:.0f} s of data on one clock\n")
        print("| run | replay s (node idle after s) | messages in / sent | processing ms p50 / p99 / max | paper RMSE / mean | "
              "true mean m | scan mean / p95 m |")
        print("|---|---|---|---|---|---|---|")
        print(f"| offline, same merged stream | – | – | – | {offline[0]:.2f} / {offline[1]:.2f} | {offline[2]:.3f} | "
              f"{offline[3]:.2f} / {offline[4]:.2f} |")
        # Fast DDS computes ports from the domain id: ids above 232 have none (wrap like bench live)
        domain = 1 + (int(os.environ.get("INDOOR_LOC_DOMAIN_BASE", "1")) + 40) % 232
        for rate in rates:
            r = run_live(data, msgs, rate, params, domain)
            if len(r["paths"]) < len(data.walks):
                print(f"| {rate:g}x | {r['replay_s']:.0f} ({r['drained_s']:.0f}) | {r['received']} / {r['sent']} | {r['p50']:.1f} / "
                      f"{r['p99']:.1f} / {r['max']:.0f} | only {len(r['paths'])} final paths | | |")
                continue
            s = score_paths(data, r["paths"])
            print(f"| {rate:g}x | {r['replay_s']:.0f} ({r['drained_s']:.0f}) | {r['received']} / {r['sent']} | "
                  f"{r['p50']:.1f} / {r['p99']:.1f} / {r['max']:.0f} | {s[0]:.2f} / {s[1]:.2f} | {s[2]:.3f} "
                  f"({100 * (s[2] / offline[2] - 1):+.1f} %) | {s[3]:.2f} / {s[4]:.2f} |")
