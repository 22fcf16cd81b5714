"""Publishes serialized samples as they are (empty ones too) on one topic, for the liveness and
zero-length tests: ``raw_sender.py SAMPLES TOPIC TYPE PERIOD_S [--best-effort]``.

SAMPLES is a file of length-prefixed samples (4-byte little-endian length, then the bytes). The
sender waits for a subscription to match, then publishes one sample every PERIOD_S and prints
``sent N`` after each.
"""
from __future__ import annotations

import struct
import sys
import time
from pathlib import Path

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from indoor_loc.contract import msg_class  # noqa: E402


def read_samples(path: str) -> list[bytes]:
    data = Path(path).read_bytes()
    out, pos = [], 0
    while pos < len(data):
        (n,) = struct.unpack_from("<I", data, pos)
        out.append(data[pos + 4:pos + 4 + n])
        pos += 4 + n
    return out


def write_samples(path: Path, samples: list[bytes]) -> None:
    path.write_bytes(b"".join(struct.pack("<I", len(s)) + s for s in samples))


def main() -> None:
    samples_file, topic, type_name, period = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
    reliability = ReliabilityPolicy.BEST_EFFORT if "--best-effort" in sys.argv else ReliabilityPolicy.RELIABLE
    samples = read_samples(samples_file)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = Node("raw_sender")
    pub = node.create_publisher(msg_class(type_name), topic, QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=reliability, durability=DurabilityPolicy.VOLATILE))
    while pub.get_subscription_count() == 0:
        time.sleep(0.02)
    print("matched", flush=True)
    for n, data in enumerate(samples, 1):
        pub.publish(data)
        print(f"sent {n}", flush=True)
        time.sleep(period)
    time.sleep(2.0)         # time for the last ones to be acknowledged
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
