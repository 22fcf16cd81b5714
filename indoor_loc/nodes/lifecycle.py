"""Managed (lifecycle) mode of the estimators: ``tll_pf --managed --ros-args ...`` (also ``pdr_kf_node``,
``backend_node``), driven as nav2's lifecycle manager drives nav2_amcl.

The node is then an ``rclpy.lifecycle.LifecycleNode`` with the standard services
(``~/change_state``, ``~/get_state``, ``~/get_available_transitions``, ...) and ``~/transition_event``:

- **unconfigured** (at start) and **inactive**: input messages are received (their liveness stays
  watched) but not processed, and nothing is published but ``/diagnostics``; they are counted,
  ``lifecycle.dropped_inactive`` in ``/diagnostics``; ``~/set_pose`` answers ``success: false``.
- **configure**: the parameters were read and the stage (graph, radio map) built at start-up, as in
  plain mode, so a bad parameter still fails the start (exit 2); configure makes the stage anew when
  a cleanup dropped it.
- **activate**: inputs are processed and every output published (``pf/pose``, ``/tf``, ...).
- **deactivate**: back to inactive; the filter keeps its state (an activate continues from it).
- **cleanup**: the stage's state is dropped (the filter forgets where it was); the next configure
  makes it afresh.
- **shutdown**: as a stop in plain mode.

Plain mode (no ``--managed``) stays the default: the node is active from the start.
"""
from __future__ import annotations

from typing import Any, Callable

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

MANAGED_FLAG = "--managed"


def wants_managed(args: list[str] | None) -> bool:
    """``--managed`` among a node's own arguments (before ``--ros-args``)."""
    import sys
    argv = list(sys.argv if args is None else args)
    own = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    return MANAGED_FLAG in own


class ManagedMixin:
    """Lifecycle states for a StageNode (see the module doc); mixed in by :func:`managed`."""

    _active = False
    _cleaned = False
    dropped_inactive = 0

    # -- the gate ---------------------------------------------------------------------------------
    def _on_message(self, inp: Any, data: Any, info: Any, *, probe: bool = False) -> None:
        node: Any = self
        if self._active:
            super()._on_message(inp, data, info, probe=probe)       # type: ignore[misc]
            return
        if node._book(inp, info, probe=probe) is not None:          # liveness and sequence kept
            self.dropped_inactive += 1

    def _publish(self, outs: list) -> None:
        if self._active:
            super()._publish(outs)                                  # type: ignore[misc]

    def set_pose_refused(self) -> str | None:
        return None if self._active else "the node is not active (lifecycle)"

    def diagnostics_msg(self, now_ns: int) -> Any:
        arr = super().diagnostics_msg(now_ns)                       # type: ignore[misc]
        from diagnostic_msgs.msg import KeyValue
        state = "active" if self._active else ("unconfigured" if self._cleaned or not self._configured else "inactive")
        for st in arr.status:
            st.values.append(KeyValue(key="lifecycle.state", value=state))
            st.values.append(KeyValue(key="lifecycle.dropped_inactive", value=str(self.dropped_inactive)))
        return arr

    # -- transitions --------------------------------------------------------------------------------
    _configured = False

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        node: Any = self
        if self._cleaned:
            try:
                node.stage = node._stage_cls(node.stage.params, namespace=node.get_namespace())
            except Exception as err:  # noqa: BLE001 - a failed configure is the manager's to handle
                node.get_logger().error(f"configure failed: {err}")
                return TransitionCallbackReturn.FAILURE
            node._last_rejected = 0
            self._cleaned = False
        self._configured = True
        node.get_logger().info("configured")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._active = True
        self._log("activated: processing inputs, publishing outputs")
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._active = False
        self._log("deactivated: inputs dropped, no outputs")
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._active = False
        self._cleaned = True
        self._configured = False
        self._log("cleaned up: the estimator's state is dropped")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._active = False
        return TransitionCallbackReturn.SUCCESS

    def _log(self, text: str) -> None:
        node: Any = self
        node.get_logger().info(text)


def managed(cls: type) -> type:
    """``cls`` (a StageNode subclass) as a lifecycle node (see the module doc)."""
    return type(f"Managed{cls.__name__}", (ManagedMixin, cls, LifecycleNode), {"__doc__": __doc__})


def node_factory(cls: type, args: list[str] | None) -> Callable[[], Any]:
    """The factory ``run_stage_node`` takes: ``cls``, or its managed form with ``--managed``."""
    return managed(cls) if wants_managed(args) else cls
