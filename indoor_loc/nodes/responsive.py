"""What a node answers while its executor's thread is busy: ``/diagnostics`` and the read-only parameter
services, from a thread of their own (:class:`Responsive`, started by
:func:`~indoor_loc.nodes.process.spin_node`).

A node's stage runs in the one executor thread and one callback can be long: a raw IMU input takes
up to ``TAKE_MAX`` (2048) queued messages at once, which on a loaded machine (the process given a
tenth of a core) is tens of seconds of wall clock. ``/diagnostics`` (a timer of that executor) and
parameter requests (answered between two callbacks, :class:`~indoor_loc.nodes.process.ServicePoll`)
waited for it: ``imu_node`` silent 55 s in ``indoor-loc bench chaos --faults hostile`` on the IMU
ports with 7 parameter requests unanswered for 10 s; ``backend_node`` silent 11 s in the clock loop.

The thread:

- answers ``get_parameters``, ``list_parameters``, ``describe_parameters`` and
  ``get_parameter_types`` as they come (its own executor over a view of the node that shows it
  only those services, moved to a callback group of their own; they read the node's parameters
  and never enter the stage).
  ``set_parameters`` and the stage's own services stay in the executor's thread;
- publishes the node's ``/diagnostics`` status (``node.diagnostics_when_busy(now_ns)``: the same
  status, built from the counters as they stand) while the executor's thread is inside one callback
  for more than :data:`BUSY_AFTER_S` of wall clock (the spin loop calls :meth:`Responsive.beat`
  after each callback) and has not published one for as long. A node that is not busy publishes
  from its timer, on its clock, as before (under sim time, none before ``/clock``). Reading the
  counters while the stage updates them can fail (a dict changing size as it is read): that round
  is skipped and tried again :data:`POLL_S` later.
"""
from __future__ import annotations

import threading
import time
from typing import Any

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

#: Services the thread answers (by the end of their names): they only read the node's parameters.
READ_ONLY = ("/get_parameters", "/list_parameters", "/describe_parameters", "/get_parameter_types")
#: The thread publishes the node's /diagnostics once its executor's thread has not for this long (s).
BUSY_AFTER_S = 2.0
#: How long the thread waits for a service request before it looks at the diagnostics again (s).
POLL_S = 0.05


class ServicesView:
    """What an rclpy executor takes as a node, showing it only ``node``'s services (:attr:`services`;
    a subclass may show fewer): no subscriptions, timers, clients, guards or waitables."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.executor: Any = None                       # set by Executor.add_node
        self.subscriptions: tuple = ()
        self.timers: tuple = ()
        self.clients: tuple = ()
        self.guards: tuple = ()
        self.waitables: tuple = ()

    @property
    def context(self) -> Any:
        return self.node.context

    @property
    def services(self) -> Any:
        return self.node.services


class _ReadOnlyServices(ServicesView):
    """A view of a node for an executor: its read-only parameter services and nothing else."""

    def __init__(self, node: Node) -> None:
        super().__init__(node)
        self._services = None
        # a callback group of their own: in the node's default one, shared with every subscription
        # and timer, the request waits until the long callback holding that group has ended
        group = MutuallyExclusiveCallbackGroup()
        for srv in self.services:
            srv.callback_group = group
            group.add_entity(srv)

    @property
    def services(self) -> Any:
        if self._services is None:
            self._services = [s for s in self.node.services if s.srv_name.endswith(READ_ONLY)]
        return self._services


class Responsive:
    """The thread (see the module doc); :meth:`stop` ends it."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self._stop = threading.Event()
        self._executor = SingleThreadedExecutor(context=node.context)
        self._executor.add_node(_ReadOnlyServices(node))   # type: ignore[arg-type]
        self.published_busy = 0                         # /diagnostics statuses this thread published
        self._beat = time.monotonic()                   # the executor's thread last between two callbacks
        self._thread = threading.Thread(target=self._run, name="responsive", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        busy_status = getattr(self.node, "diagnostics_when_busy", None)
        while not self._stop.is_set() and self.node.context.ok():
            try:
                self._executor.spin_once(timeout_sec=POLL_S)
            except Exception:  # noqa: BLE001 - the context is shutting down, or a request went to the other executor
                if self._stop.is_set() or not self.node.context.ok():
                    return
            if busy_status is None:
                continue
            now = time.monotonic()
            last = float(getattr(self.node, "diag_published_at", 0.0) or 0.0)
            if last and now - last > BUSY_AFTER_S and now - self._beat > BUSY_AFTER_S:
                try:
                    if busy_status(self.node.get_clock().now().nanoseconds):
                        self.published_busy += 1
                except Exception:  # noqa: BLE001 - counters changing under us: try again later
                    continue

    def beat(self) -> None:
        """The executor's thread is between two callbacks (called by the spin loop)."""
        self._beat = time.monotonic()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._executor.shutdown(timeout_sec=0.0)
