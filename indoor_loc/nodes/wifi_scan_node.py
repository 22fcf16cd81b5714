"""``ros2 run indoor_loc wifi_scan_node``: WiFi scan ingestion (see pipeline/wifi_scan_stage.py).

With ``source: topic`` this is a plain :class:`StageNode`. With ``source: iw`` / ``nmcli`` a
background thread runs the scan command every ``scan_period_s`` (the command may block for
seconds; the executor never waits on it) and hands each attempt to the executor through a guard
condition, where the stage normalises and publishes it like any other input.
"""
from __future__ import annotations

import queue
import sys
import threading
import time
from typing import Any


from indoor_loc.nodes.process import run_stage_node
from indoor_loc.nodes.stage_node import StageNode
from indoor_loc.pipeline.wifi_scan_stage import IFACE_INPUT, WifiScanStage
from indoor_loc.wifi.iface import TOOLS, ScanAttempt

#: parameter values that change the node's topics, named in its ``--help``
PORT_PARAMS = {"source": TOOLS}


class WifiScanNode(StageNode):
    """StageNode for :class:`WifiScanStage` plus the interface scan thread."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__(WifiScanStage, **node_kwargs)
        self.stage: WifiScanStage
        self._attempts: queue.SimpleQueue[ScanAttempt] = queue.SimpleQueue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._told_fallback = False
        if self.stage.scanner is not None:
            self._guard = self.create_guard_condition(self._drain)
            self._thread = threading.Thread(target=self._scan_loop, name="wifi_scan", daemon=True)
            self._thread.start()
            self.get_logger().info(f"scanning with `{' '.join(self.stage.scanner.command)}` every "
                                   f"{self.stage.params.scan_period_s:g} s")

    def _scan_loop(self) -> None:
        period = self.stage.params.scan_period_s
        next_t = time.monotonic()
        while not self._stop.is_set():
            attempt = self.stage.acquire(lambda: self.get_clock().now().nanoseconds)
            self._attempts.put(attempt)
            self._guard.trigger()
            next_t += period
            delay = next_t - time.monotonic()
            if delay < 0:                 # the scan took longer than the period: don't burst
                next_t, delay = time.monotonic(), 0.0
            self._stop.wait(delay)

    def _drain(self) -> None:
        while True:
            try:
                attempt = self._attempts.get_nowait()
            except queue.Empty:
                return
            if attempt.fallback and not self._told_fallback and self.stage.scanner is not None:
                self._told_fallback = True
                self.get_logger().warning(f"{self.stage.scanner.fallback_reason}; using "
                                          f"`{' '.join(self.stage.scanner.dump_command)}` (cached results)")
            self._publish(self.stage.process(IFACE_INPUT, attempt, attempt.stamp_ns))
            self._log_rejections()

    def destroy_node(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.stage.params.scan_timeout_s + 1.0)
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_stage_node(WifiScanStage, args, node_factory=WifiScanNode, port_params=PORT_PARAMS)


if __name__ == "__main__":
    sys.exit(main())
