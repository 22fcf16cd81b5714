"""Helpers for tests that talk DDS: an rclpy node with its own context, spinning until a condition
holds (with a deadline, never a bare sleep), and child processes whose output is collected."""
from __future__ import annotations

import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

PEERS = Path(__file__).resolve().parent / "dds_peers"


@contextmanager
def ros_node(name: str, namespace: str = "", **node_kwargs) -> Iterator[tuple[Node, SingleThreadedExecutor]]:
    """A node on a fresh rclpy context (the domain comes from ROS_DOMAIN_ID, set by ``ros_domain``)."""
    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    node = Node(name, namespace=namespace, context=ctx, **node_kwargs)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        yield node, ex
    finally:
        ex.remove_node(node)
        ex.shutdown(timeout_sec=0.0)
        node.destroy_node()
        ctx.try_shutdown()


def follow_diagnostics(mon: Node, name: str) -> tuple[list[dict[str, str]], Callable[[str], str]]:
    """Follow ``/diagnostics`` for the status ``name`` (``/rs/pdr_kf_node``): every values mapping
    received, in order, and ``value(key)`` of the newest ('' before any, or for a key it lacks)."""
    from diagnostic_msgs.msg import DiagnosticArray

    from indoor_loc.contract import Qos
    from indoor_loc.nodes.qos import qos_profile
    from msg_adapters.diagnostics import diagnostics_from_msg
    got: list[dict[str, str]] = []

    def on_diag(msg: DiagnosticArray) -> None:
        d = diagnostics_from_msg(msg).get(name)
        if d is not None:
            got.append(d.values)
    mon.create_subscription(DiagnosticArray, "/diagnostics", on_diag, qos_profile(Qos.RELIABLE))
    return got, lambda key: got[-1].get(key, "") if got else ""


def spin_until(ex: SingleThreadedExecutor, cond: Callable[[], bool], timeout: float) -> bool:
    """Spin ``ex`` until ``cond()`` is true or ``timeout`` s pass; returns ``cond()``."""
    deadline = time.monotonic() + timeout
    while not cond():
        left = deadline - time.monotonic()
        if left <= 0:
            return cond()
        ex.spin_once(timeout_sec=min(0.05, left))
    return True


def spin_for(ex: SingleThreadedExecutor, seconds: float) -> None:
    deadline = time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        ex.spin_once(timeout_sec=min(0.05, left))


def child_env(**extra: str) -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra)
    return env


class Peer:
    """A child process whose stdout+stderr lines are collected by a thread (``lines``)."""

    def __init__(self, cmd: list[str], *, env: dict[str, str] | None = None, cwd: str | None = None,
                 stdin: int | None = subprocess.DEVNULL) -> None:
        self.cmd = cmd
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=stdin,
                                     env=env or child_env(), cwd=cwd, text=True, bufsize=1)
        self.lines: list[str] = []
        self._q: queue.Queue[str | None] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))
            self._q.put(line.rstrip("\n"))
        self._q.put(None)

    def wait_line(self, pattern: str, timeout: float) -> str | None:
        """The first (new) output line matching regex ``pattern`` within ``timeout`` s, else None."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = self._q.get(timeout=left)
            except queue.Empty:
                return None
            if line is None:
                return None
            if rx.search(line):
                return line
        return None

    def wait_seen(self, pattern: str, timeout: float) -> str | None:
        """The first output line matching regex ``pattern``, printed before this call or within
        ``timeout`` s (unlike :meth:`wait_line`, lines already passed over count), else None."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout
        while True:
            done = not self._reader.is_alive()          # read before the lines: nothing comes after
            found = next((line for line in list(self.lines) if rx.search(line)), None)
            if found is not None or done or time.monotonic() >= deadline:
                return found
            time.sleep(0.05)

    def signal(self, sig: int = signal.SIGINT) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)

    def wait(self, timeout: float) -> int:
        rc = self.proc.wait(timeout=timeout)
        self._reader.join(timeout=10.0)   # returns at EOF; bounded for a stuck pipe
        return rc

    def output(self) -> str:
        return "\n".join(self.lines)

    def stop(self) -> None:
        """Make sure the process is gone (SIGINT, then SIGKILL)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5.0)
        self._reader.join(timeout=10.0)   # returns at EOF; bounded for a stuck pipe


def python_peer(script: str, *args: str, **kw) -> Peer:
    """Run ``test/dds_peers/<script>`` with this interpreter."""
    return Peer([sys.executable, str(PEERS / script), *args], **kw)
