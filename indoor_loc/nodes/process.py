"""The node process: SIGINT/SIGTERM as a clean stop (what was already received is processed
first) within a bounded time, spinning (service requests answered between two callbacks whatever
is queued, :class:`ServicePoll`), ``main()`` of every stage node (:func:`run_stage_node`), and a node that
cannot start saying so in ``/diagnostics`` and ending within a bounded time.

A stage node's stop, from the first SIGINT/SIGTERM (one deadline for the whole sequence):

1. the messages DDS delivered before the signal are processed (:func:`drain`) until
   :data:`STOP_WORK_S` minus the stage's end-of-input budget (``finish_budget_s`` if it has one)
   minus :data:`ACK_RESERVE_S`;
2. the stage's ``finish()`` outputs are published (the back-end bounds its own by ``finish_budget_s``);
3. the subscribers' acknowledgements of every reliable output are awaited together until
   :data:`STOP_WORK_S` after the signal;
4. the node and the middleware are shut down; a guard ends the process :data:`STOP_BOUND_S` after
   the signal whatever it is still doing (:func:`arm_exit_guard`; destroying the thousands of DDS
   entities of a back-end with hundreds of users alone can take seconds), and at once on a second
   signal.

What a deadline cut short is logged (messages perhaps left undrained, subscribers that did not
acknowledge; the back-end names the users whose final optimisation did not complete).
"""
from __future__ import annotations

import faulthandler
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
from indoor_loc.nodes.responsive import Responsive, ServicesView
from indoor_loc.nodes.stage_node import StageNode
from indoor_loc.pipeline.stage import Stage
from msg_adapters.diagnostics import status_array

#: How often the spin loop returns to Python so SIGINT/SIGTERM are handled promptly (s).
_SPIN_PERIOD_S = 0.1
#: On SIGINT/SIGTERM a node processes what was queued for it before the signal for at most this
#: long (s; a stage node drains for less: see :func:`stop_plan`).
DRAIN_TIMEOUT_S = 8.0
#: A stage node ends at most this long after the first SIGINT/SIGTERM, whatever its load (s): below
#: ``indoor-loc up``'s ``stop_timeout_s`` (10 s) between SIGINT and SIGTERM.
STOP_BOUND_S = 9.5
#: ... its clean stop (drain, end-of-input outputs, their acknowledgements) is over this long after
#: the signal (s), which leaves the rest of the bound for the middleware's own shutdown.
STOP_WORK_S = 7.5
#: ... of which publishing the end-of-input outputs (a thousand messages for the back-end with 500
#: users: about a second on a loaded machine) and their acknowledgements get at least this long (s).
ACK_RESERVE_S = 2.0


#: Set by the first SIGINT/SIGTERM (a stop was asked for), and by the second (stop at once).
_STOP = threading.Event()
_STOP_NOW = threading.Event()
#: When the first SIGINT/SIGTERM came (system clock, ns; 0 before), and on the monotonic clock (s).
_STOP_AT_NS = [0]
_STOP_AT_MONO = [0.0]
#: The signal that asked to stop at once (0 before).
_STOP_NOW_SIG = [0]
#: The exit guard armed for this process (:func:`arm_exit_guard`): (node name, bound s), or None.
_GUARD: list[tuple[str, float] | None] = [None]
#: Set when the guarded process got to its end by itself (the guard's thread then returns).
_GUARD_DONE = threading.Event()
#: Set once a stopping node's end-of-input outputs are published and acknowledged (or said not to be):
#: an exit at the bound after it loses nothing (status 0).
_OUTPUTS_DONE = threading.Event()


def _request_stop(signum: int, frame: Any) -> None:
    # Only a flag: an exception raised from a signal handler can surface inside a pybind11 call
    # (rclpy's take_message) as a RuntimeError ("Unable to convert call argument") instead of a
    # KeyboardInterrupt and end the process with a traceback. The spin loops poll the flag.
    if not _STOP.is_set():
        _STOP_AT_NS[0] = time.time_ns()
        _STOP_AT_MONO[0] = time.monotonic()
        _start_exit_guard()
    else:
        _STOP_NOW_SIG[0] = signum
    (_STOP_NOW if _STOP.is_set() else _STOP).set()


def arm_exit_guard(name: str, bound_s: float = STOP_BOUND_S) -> None:
    """From the first SIGINT/SIGTERM on, this process ends within ``bound_s`` whatever it is doing,
    and at once on a second signal: a daemon thread says why on stderr and ends it (``os._exit``,
    half a second before the bound: status 0 if only the middleware's shutdown was left — the
    end-of-input outputs published and acknowledged, :func:`outputs_done` — else 1 with every
    thread's stack; 128 + the signal on a second signal); should that thread
    not get the GIL, faulthandler's watchdog ends it at the bound (status 1, every thread's stack on
    stderr). The clean stop's own deadlines end
    well before; the guard is for what has none (the middleware's shutdown, a stage stuck in a
    computation). :func:`disarm_exit_guard` when the process ends by itself."""
    _GUARD[0] = (name, bound_s)
    _GUARD_DONE.clear()
    _OUTPUTS_DONE.clear()


def outputs_done() -> None:
    """A stopping node's end-of-input outputs are published and their acknowledgements awaited."""
    _OUTPUTS_DONE.set()


def disarm_exit_guard() -> None:
    _GUARD[0] = None
    _GUARD_DONE.set()
    faulthandler.cancel_dump_traceback_later()


def _start_exit_guard() -> None:
    guard = _GUARD[0]
    if guard is None:
        return
    name, bound_s = guard
    start = time.monotonic()
    # the backstop needs no GIL: a call into the middleware that holds the GIL and blocks (deleting a
    # writer whose reader stopped answering) keeps the thread below from running; faulthandler's
    # watchdog then dumps every thread's stack to stderr (where it was stuck) and ends the process
    faulthandler.dump_traceback_later(bound_s, exit=True)
    soft_s = bound_s - min(0.5, bound_s / 4)

    def watch() -> None:
        while not _GUARD_DONE.is_set():
            left = soft_s - (time.monotonic() - start)
            if _STOP_NOW.wait(min(max(left, 0.0), 0.1)):
                if _GUARD_DONE.is_set():
                    return
                print(f"[{name}] asked again: stopping at once (the end-of-input outputs not published "
                      f"or not acknowledged are lost)", file=sys.stderr, flush=True)
                os._exit(128 + (_STOP_NOW_SIG[0] or signal.SIGTERM))
            if left <= 0 and not _GUARD_DONE.is_set():
                if _OUTPUTS_DONE.is_set():     # only the middleware's shutdown is left: nothing is lost
                    print(f"[{name}] end-of-input outputs published; the middleware's shutdown not over "
                          f"{soft_s:g} s after the stop signal (its bound is {bound_s:g} s): exiting",
                          file=sys.stderr, flush=True)
                    os._exit(0)
                print(f"[{name}] still not ended {soft_s:g} s after the stop signal (its bound is {bound_s:g} s): "
                      f"exiting; it was here:", file=sys.stderr, flush=True)
                faulthandler.dump_traceback(all_threads=True)
                os._exit(1)

    threading.Thread(target=watch, name="exit-guard", daemon=True).start()


def stop_elapsed_s() -> float:
    """Seconds since the first SIGINT/SIGTERM (0 if none came)."""
    return time.monotonic() - _STOP_AT_MONO[0] if _STOP.is_set() and _STOP_AT_MONO[0] else 0.0


def stop_plan(finish_budget_s: float = 0.0) -> tuple[float, float]:
    """A stage node's stop as two deadlines on the monotonic clock, from the first signal (now if
    none came): until when it drains (:data:`STOP_WORK_S` minus the stage's ``finish_budget_s`` minus
    :data:`ACK_RESERVE_S`, at most :data:`DRAIN_TIMEOUT_S`), until when the last outputs' acknowledgements
    are awaited (:data:`STOP_WORK_S`)."""
    t0 = _STOP_AT_MONO[0] if _STOP.is_set() and _STOP_AT_MONO[0] else time.monotonic()
    drain_s = min(DRAIN_TIMEOUT_S, max(0.0, STOP_WORK_S - finish_budget_s - ACK_RESERVE_S))
    return t0 + drain_s, t0 + STOP_WORK_S


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
    _STOP_AT_MONO[0] = 0.0
    _STOP_NOW_SIG[0] = 0
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
          timeout_s: float = DRAIN_TIMEOUT_S, *, deadline: float | None = None,
          poll: Callable[[], None] | None = None) -> int:
    """Run the callbacks of the messages DDS delivered before the stop signal (:func:`stop_time_ns`)
    until none is left (three idle spins in a row), a message received after it was handled (``node.last_rx_ns``: a publisher
    still running must not hold the node up), or ``timeout_s`` passes (or the monotonic ``deadline``);
    ``taken()`` counts the messages handled so far; ``poll()`` is called after each callback
    (:meth:`ServicePoll.poll`). Returns how many were handled here; a negative
    count (minus that number, minus one) when the time ran out while messages were still coming."""
    start = taken()
    stop_ns = stop_time_ns()
    deadline = time.monotonic() + timeout_s if deadline is None else deadline
    idle = 0
    while (idle < 3 and time.monotonic() < deadline and node.context.ok() and not _STOP_NOW.is_set()
           and int(getattr(node, "last_rx_ns", 0)) <= stop_ns):
        before = taken()
        executor.spin_once(timeout_sec=0.02)
        if poll is not None:
            poll()
        idle = idle + 1 if taken() == before else 0
    n = taken() - start
    cut = idle < 3 and time.monotonic() >= deadline and int(getattr(node, "last_rx_ns", 0)) <= stop_ns
    return -n - 1 if cut else n


def spin_node(node: Node, taken: Callable[[], int] | None = None, *, finish_budget_s: float | None = None) -> None:
    """Spin until SIGINT/SIGTERM (raised here as KeyboardInterrupt) or an external shutdown.

    rclpy's own signal handlers are off (see :func:`run_stage_node`); the executor wakes up every
    ``_SPIN_PERIOD_S`` to look at :func:`stop_requested`; the context stays valid afterwards. On a
    signal, what is already queued for the node is processed first (:func:`drain`, with
    ``taken`` or the node's ``taken`` counter, for :data:`DRAIN_TIMEOUT_S`, or with
    ``finish_budget_s`` until :func:`stop_plan`'s drain deadline); a second signal interrupts that.
    Service requests are answered between two callbacks (:class:`ServicePoll`).
    Ends with KeyboardInterrupt on a signal.
    """
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    services = ServicePoll(node)
    responsive = Responsive(node)      # /diagnostics and parameter reads while a callback is long
    count = taken or (lambda: int(getattr(node, "taken", 0)))
    try:
        while node.context.ok() and not _STOP.is_set():
            executor.spin_once(timeout_sec=_SPIN_PERIOD_S)
            responsive.beat()
            services.poll()
        if _STOP.is_set():
            n = drain(executor, node, count, poll=services.poll,
                      deadline=None if finish_budget_s is None else stop_plan(finish_budget_s)[0])
            if n < 0:
                node.get_logger().warning(
                    f"stopping: processed {-n - 1} message(s) already received, then the drain's deadline "
                    f"({stop_elapsed_s():.1f} s after the signal) came first: messages still queued were NOT processed")
            elif n:
                node.get_logger().info(f"stopping: processed the {n} message(s) already received")
            raise KeyboardInterrupt("stop requested by a signal")
    finally:
        responsive.stop()
        services.shutdown()
        executor.remove_node(node)
        executor.shutdown(timeout_sec=0.0)


class ServicePoll(ServicesView):
    """Answers a node's service requests between two callbacks, whatever else is queued.

    rclpy's executor takes one callback of every ready entity per wait, services last: behind a
    burst of messages a parameter request waited for one callback of every subscription with a
    message queued (2.5 s for the back-end after a 200-user burst). :meth:`poll`, called by the spin
    loop after each callback, runs a second executor over a view of the node that shows it only the
    node's services (zero timeout: it answers what has come and returns), at most every
    :data:`POLL_PERIOD_S`. Everything stays in the one thread, so a service that enters the stage
    (tll_pf's ``~/global_localization``) never runs beside a message callback. The node's own
    executor still has the services too (an idle node answers at once); a request taken by one is
    not there for the other (rclpy then finds nothing to take and calls nothing)."""

    #: The spin loop looks for service requests at most this often (s).
    POLL_PERIOD_S = 0.01

    def __init__(self, node: Node) -> None:
        super().__init__(node)
        self._executor = SingleThreadedExecutor(context=node.context)
        self._executor.add_node(self)   # type: ignore[arg-type]
        self._next = 0.0

    def poll(self) -> None:
        """Answer the requests that have come (none waited for)."""
        now = time.monotonic()
        if now < self._next:
            return
        self._next = now + self.POLL_PERIOD_S
        self._executor.spin_once(timeout_sec=0.0)      # one request; more at the next poll

    def shutdown(self) -> None:
        self._executor.shutdown(timeout_sec=0.0)


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
    if "--multi-user" in user_args:     # one process for many users (indoor_loc.nodes.multi_user_node)
        from indoor_loc.nodes.multi_user_node import multi_user_factory
        stage_cls, node_factory = multi_user_factory(stage_cls)
        argv.remove("--multi-user")
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
    arm_exit_guard(name)
    node: StageNode | None = None
    status = 0
    try:
        node = node_factory() if node_factory is not None else StageNode(stage_cls)
        node.check_params_files(params_file_args(argv))
        spin_node(node, finish_budget_s=node.finish_budget_s())
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (IndoorLocError, ParameterException) as err:
        print(f"[{name}] configuration error: {err}", file=sys.stderr)
        status = 2
        if node is None:          # start-up failed: say so in /diagnostics too, not only on stderr
            exit_after(STARTUP_ERROR_WAIT_S + STARTUP_ERROR_ACK_S + STARTUP_ERROR_GRACE_S, status, name)
            report_startup_error(name, f"configuration error: {err}")
    finally:
        # signals stay with _request_stop: a first one arms the exit guard, a second ends at once
        if node is not None:
            if node.context.ok():
                node.stop_deadline = stop_plan(node.finish_budget_s())[1]
                try:
                    node.shutdown()
                except Exception as err:  # noqa: BLE001 - a stage bug in finish() must not skip clean-up
                    print(f"[{name}] finish() failed: {type(err).__name__}: {err}", file=sys.stderr)
                    status = status or 1
                outputs_done()
                if stop_requested():
                    node.get_logger().info(f"stopping: end-of-input outputs published, shutting down "
                                           f"({stop_elapsed_s():.1f} s after the signal)")
            node.destroy_node()
        rclpy.try_shutdown()
        disarm_exit_guard()
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
