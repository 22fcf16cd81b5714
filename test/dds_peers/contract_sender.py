"""Publishes one message per contract topic under /alice with the contract QoS (see
contract_messages.py). Latched topics are published once, before ``LATCHED_SENT`` is printed;
the others are republished every 0.1 s (best-effort topics may drop a sample) until SIGINT/SIGTERM
or ``--timeout`` seconds."""
from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import rclpy  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402

from contract_messages import ALL_TOPICS, NAMESPACE, build  # noqa: E402
from indoor_loc.contract import TOPICS, Qos, msg_class  # noqa: E402
from indoor_loc.nodes.base import qos_profile  # noqa: E402


def _stop(signum, frame):
    raise KeyboardInterrupt


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--timeout", type=float, default=30.0)
    args = ap.parse_args()
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("contract_sender", namespace=NAMESPACE)
    try:
        pubs = {t: node.create_publisher(msg_class(TOPICS[t].type), t, qos_profile(TOPICS[t].qos)) for t in ALL_TOPICS}
        msgs = {t: build(t) for t in ALL_TOPICS}
        latched = [t for t in ALL_TOPICS if TOPICS[t].qos == Qos.LATCHED]
        for t in latched:
            pubs[t].publish(msgs[t])
        print("LATCHED_SENT " + " ".join(latched), flush=True)
        deadline = time.monotonic() + args.timeout
        while time.monotonic() < deadline:
            for t in ALL_TOPICS:
                if t not in latched:
                    pubs[t].publish(msgs[t])
            rclpy.spin_once(node, timeout_sec=0.1)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    print("SENDER_DONE", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
