"""The node process: SIGINT/SIGTERM as a clean stop (what was already received is processed
first), spinning, ``main()`` of every stage node (:func:`run_stage_node`), and a node that cannot
start saying so in ``/diagnostics`` and ending within a bounded time."""
from __future__ import annotations

import os
import signal
import sys
import threading
import time
from typing import Any, Callable, Mapping, Sequence

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from indoor_loc.contract import Qos
from indoor_loc.errors import IndoorLocError
from indoor_loc.nodes.help import node_usage, params_file_args
from indoor_loc.nodes.qos import qos_profile
from indoor_loc.nodes.stage_node import StageNode
from indoor_loc.pipeline.stage import Stage
from msg_adapters.diagnostics import status_array

#: How often the spin loop returns to Python so SIGINT/SIGTERM are handled promptly (s).
_SPIN_PERIOD_S = 0.1
#: On SIGINT/SIGTERM a node processes what was queued for it before the signal for at most this
#: long (s; below ``indoor-loc up``'s 10 s between SIGINT and SIGTERM).
DRAIN_TIMEOUT_S = 8.0


#: Set by the first SIGINT/SIGTERM (a stop was asked for), and by the second (stop at once).
_STOP = threading.Event()
_STOP_NOW = threading.Event()
#: When the first SIGINT/SIGTERM came (system clock, ns; 0 before).
_STOP_AT_NS = [0]


def _request_stop(signum: int, frame: Any) -> None:
    # Only a flag: an exception raised from a signal handler can surface inside a pybind11 call
    # (rclpy's take_message) as a RuntimeError ("Unable to convert call argument") instead of a
    # KeyboardInterrupt and end the process with a traceback. The spin loops poll the flag.
    if not _STOP.is_set():
        _STOP_AT_NS[0] = time.time_ns()
    (_STOP_NOW if _STOP.is_set() else _STOP).set()


def stop_time_ns() -> int:
    """When the first SIGINT/SIGTERM arrived (system clock, ns), or now if none did: messages DDS
    received before it are the ones a stopping node still handles."""
    return _STOP_AT_NS[0] if _STOP.is_set() and _STOP_AT_NS[0] else time.time_ns()


def stop_requested() -> bool:
    """Whether SIGINT/SIGTERM asked this process to stop (see :func:`raise_on_signals`)."""
    return _STOP.is_set()


def raise_on_signals() -> dict[int, Any]:
    """From now on SIGINT and SIGTERM set :func:`stop_requested`, which the spin loops turn into a
    KeyboardInterrupt between two callbacks (rclpy's own handlers must be off:
    ``rclpy.init(signal_handler_options=SignalHandlerOptions.NO)``, so the context stays valid for a
    clean stop; SIGINT explicitly too: a child started in the background inherits it ignored).
    Returns the previous handlers for :func:`restore_signals` (empty off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    _STOP.clear()
    _STOP_NOW.clear()
    _STOP_AT_NS[0] = 0
    return {sig: signal.signal(sig, _request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}


def check_stop() -> None:
    """Raise KeyboardInterrupt if a signal asked to stop (call between two units of work)."""
    if _STOP.is_set():
        raise KeyboardInterrupt("stop requested by a signal")


def ignore_signals(old: dict[int, Any]) -> None:
    """During clean-up: a second signal must not cut it short."""
    for sig in old:
        signal.signal(sig, signal.SIG_IGN)


def restore_signals(old: dict[int, Any]) -> None:
    for sig, handler in old.items():
        signal.signal(sig, handler)


def drain(executor: SingleThreadedExecutor, node: Node, taken: Callable[[], int],
          timeout_s: float = DRAIN_TIMEOUT_S) -> int:
    """Run the callbacks of the messages DDS delivered before the stop signal (:func:`stop_time_ns`)
    until none is left (three idle spins in a row), a message received after it was handled (``node.last_rx_ns``: a publisher
    still running must not hold the node up), or ``timeout_s`` passes; ``taken()`` counts the
    messages handled so far. Returns how many were handled here."""
    start = taken()
    stop_ns = stop_time_ns()
    deadline = time.monotonic() + timeout_s
    idle = 0
    while (idle < 3 and time.monotonic() < deadline and node.context.ok() and not _STOP_NOW.is_set()
           and int(getattr(node, "last_rx_ns", 0)) <= stop_ns):
        before = taken()
        executor.spin_once(timeout_sec=0.02)
        idle = idle + 1 if taken() == before else 0
    return taken() - start


def spin_node(node: Node, taken: Callable[[], int] | None = None) -> None:
    """Spin until SIGINT/SIGTERM (raised here as KeyboardInterrupt) or an external shutdown.

    rclpy's own signal handlers are off (see :func:`run_stage_node`); the executor wakes up every
    ``_SPIN_PERIOD_S`` to look at :func:`stop_requested`; the context stays valid afterwards. On a
    signal, what is already queued for the node is processed first (:func:`drain`, with
    ``taken`` or the node's ``taken`` counter); a second signal interrupts that. Ends with
    KeyboardInterrupt on a signal.
    """
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    count = taken or (lambda: int(getattr(node, "taken", 0)))
    try:
        while node.context.ok() and not _STOP.is_set():
            executor.spin_once(timeout_sec=_SPIN_PERIOD_S)
        if _STOP.is_set():
            n = drain(executor, node, count)
            if n:
                node.get_logger().info(f"stopping: processed the {n} message(s) already received")
            raise KeyboardInterrupt("stop requested by a signal")
    finally:
        executor.remove_node(node)
        executor.shutdown(timeout_sec=0.0)


def run_stage_node(stage_cls: type[Stage], args: list[str] | None = None, *,
                   node_factory: Callable[[], StageNode] | None = None,
                   port_params: Mapping[str, Sequence[Any]] | None = None) -> int:
    """``main()`` of every stage node: ``-h``/``--help`` prints :func:`node_usage` (with the topics
    the values of ``port_params`` select); otherwise
    ``rclpy.init(args)`` (``--ros-args -r __ns:=/alice --params-file F -p k:=v`` as usual), build
    the node (``node_factory()`` or ``StageNode(stage_cls)``) and spin until SIGINT/SIGTERM.

    Returns 0 on a clean stop, 2 on invalid parameters/arguments (message on stderr).
    """
    argv = list(sys.argv if args is None else args)
    user_args = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if any(a in ("-h", "--help") for a in user_args):
        print(node_usage(stage_cls, port_params))
        return 0
    name = stage_cls.NODE_NAME
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except (RuntimeError, ValueError) as err:     # rclpy's RCLError is a RuntimeError
        print(f"[{name}] invalid arguments: {err}", file=sys.stderr)
        return 2
    old = raise_on_signals()      # both signals end the spin as KeyboardInterrupt
    node: StageNode | None = None
    status = 0
    try:
        node = node_factory() if node_factory is not None else StageNode(stage_cls)
        node.check_params_files(params_file_args(argv))
        spin_node(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (IndoorLocError, ParameterException) as err:
        print(f"[{name}] configuration error: {err}", file=sys.stderr)
        status = 2
        if node is None:          # start-up failed: say so in /diagnostics too, not only on stderr
            exit_after(STARTUP_ERROR_WAIT_S + STARTUP_ERROR_ACK_S + STARTUP_ERROR_GRACE_S, status, name)
            report_startup_error(name, f"configuration error: {err}")
    finally:
        ignore_signals(old)
        if node is not None:
            if node.context.ok():
                try:
                    node.shutdown()
                except Exception as err:  # noqa: BLE001 - a stage bug in finish() must not skip clean-up
                    print(f"[{name}] finish() failed: {type(err).__name__}: {err}", file=sys.stderr)
                    status = status or 1
            node.destroy_node()
        rclpy.try_shutdown()
        restore_signals(old)
    return status


#: A node that cannot start waits this long at most for a /diagnostics subscriber to match (s).
STARTUP_ERROR_WAIT_S = 10.0
#: ... but gives up after this long if it has seen no other node at all (s): a little over Fast
#: DDS's periodic participant announcement (3 s), so one lost initial announcement burst is covered.
STARTUP_ERROR_ALONE_S = 4.0
#: ... and for the subscribers it found to acknowledge its ERROR (s; returns as soon as they did). A
#: subscriber whose own side of the match completes later gets the message resent only while this
#: node still exists, which on a loaded machine can take seconds.
STARTUP_ERROR_ACK_S = 5.0
#: ... and the report plus the middleware's shutdown get this much more before the process exits
#: regardless (s): a node that cannot start always ends, also if DDS stalls in its shutdown.
STARTUP_ERROR_GRACE_S = 15.0


def exit_after(seconds: float, status: int, name: str) -> threading.Timer:
    """Make sure this process ends within ``seconds`` with ``status``: a daemon timer that says so on
    stderr and ends the process at once (``os._exit``: no clean-up is left to wait for). For a node
    that is already exiting with an error, whose last steps talk to the middleware."""
    def _exit() -> None:
        print(f"[{name}] still not ended {seconds:g} s after its start-up error: exiting", file=sys.stderr,
              flush=True)
        os._exit(status)
    timer = threading.Timer(seconds, _exit)
    timer.daemon = True
    timer.start()
    return timer


def report_startup_error(node_name: str, message: str, *, wait_s: float = STARTUP_ERROR_WAIT_S,
                         alone_s: float = STARTUP_ERROR_ALONE_S) -> bool:
    """Publish one ``/diagnostics`` ERROR for a node that cannot start (name and namespace from the
    command line's ``--ros-args``, as the node would have had), so a monitor sees it beside the
    running nodes and not only the terminal. A new participant is discovered asynchronously, and on
    a loaded machine that takes seconds: the node waits up to ``wait_s`` for subscribers to match
    (the count must then hold still for a moment, since several monitors match one after another),
    or only ``alone_s`` while it sees no other node in the domain; then it publishes and waits up to
    :data:`STARTUP_ERROR_ACK_S` for the acknowledgements. Returns whether a subscriber acknowledged
    it; never raises (the caller is already reporting an error)."""
    try:
        node = Node(node_name)
    except Exception:  # noqa: BLE001 - the node itself cannot be made: stderr has said it all
        return False
    try:
        pub = node.create_publisher(DiagnosticArray, "/diagnostics", qos_profile(Qos.RELIABLE))
        start = time.monotonic()
        last, since, others = -1, start, False
        while not _STOP.is_set():
            now = time.monotonic()
            if now - start >= wait_s or (not others and now - start >= alone_s):
                break
            n = pub.get_subscription_count()
            if n != last:
                last, since = n, now
            elif n > 0 and now - since >= 0.3:
                break
            others = others or len(node.get_node_names()) > 1
            time.sleep(0.02)
        pub.publish(status_array(node.get_fully_qualified_name(), 2, message, {"error": message}, time.time_ns()))
        return bool(pub.get_subscription_count() > 0
                    and pub.wait_for_all_acked(Duration(seconds=STARTUP_ERROR_ACK_S)))
    except Exception:  # noqa: BLE001 - best effort: the error is on stderr already
        return False
    finally:
        node.destroy_node()
