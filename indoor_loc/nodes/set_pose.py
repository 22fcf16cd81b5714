"""``~/set_pose``: (re)start an estimator at a pose, with its covariance, as a service.

The type is ``nav_msgs/srv/SetMap`` (request ``map`` + ``initial_pose``, response ``success``): of the
service types the installed ROS 2 wheels ship (std_srvs, nav_msgs, lifecycle_msgs, rcl_interfaces)
it is the one that carries a ``geometry_msgs/PoseWithCovarianceStamped``; nav2's
``nav2_msgs/srv/SetInitialPose`` is not available. The ``map`` must be left empty (0 × 0): these
estimators localise on their own building graph / radio map, so a map in the request is refused
(``success: false``, counted ``map_not_supported``). ``initial_pose`` goes through exactly the path
an ``initialpose`` message takes (the stage's handler: validation, ``off_map``, the covariance
honoured), and the outputs it makes are published before the response. ``success`` is true when the
pose was taken.

Single-user estimators (``tll_pf``, ``pdr_kf_node``): ``/<ns>/<node>/set_pose``. The multi-user
``backend_node``: one service per user it follows, ``/<node>/<user>/set_pose``
(``/backend_node/alice/set_pose``), made when it starts following the user.
"""
from __future__ import annotations

from typing import Any

from nav_msgs.srv import SetMap

from indoor_loc.pipeline.stage import namespace_of_user

SERVICE = "set_pose"
INPUT = "initialpose"


class SetPoseMixin:
    """Mix in before :class:`~indoor_loc.nodes.stage_node.StageNode` (a stage that handles ``initialpose``)."""

    _set_pose_srvs: dict[str, Any]

    def _open_extra_outputs(self) -> None:
        super()._open_extra_outputs()                            # type: ignore[misc]
        node: Any = self
        self._set_pose_srvs = {}
        if node.stage.handles(INPUT) and not node.stage.MULTI_USER:
            self._set_pose_srvs[""] = node.create_service(SetMap, f"~/{SERVICE}",
                                                          lambda req, res: self._on_set_pose(req, res, None))

    def _follow(self, user: str) -> None:
        super()._follow(user)                                    # type: ignore[misc]
        node: Any = self
        if user and user not in self._set_pose_srvs and node.stage.handles(INPUT):
            name = f"~{namespace_of_user(user)}/{SERVICE}"
            self._set_pose_srvs[user] = node.create_service(SetMap, name,
                                                            lambda req, res: self._on_set_pose(req, res, user))

    def set_pose_refused(self) -> str | None:
        """Why set_pose is refused now (a lifecycle node not active), else None."""
        return None

    def _on_set_pose(self, request: SetMap.Request, response: SetMap.Response, user: str | None) -> SetMap.Response:
        node: Any = self
        stage = node.stage
        grid = request.map
        refused = self.set_pose_refused()
        if refused is not None:
            node.get_logger().warning(f"set_pose refused: {refused}")
            response.success = False
            return response
        if grid.info.width or grid.info.height or len(grid.data):
            stage._reject("map_not_supported", f"set_pose: a map ({grid.info.width} x {grid.info.height}) was given; "
                                               f"leave it empty, the node localises on its own graph / radio map")
            node._log_rejections()
            response.success = False
            return response
        before = sum(stage.diag.rejected.values())
        now = node.get_clock().now().nanoseconds
        stage.set_pose_call = True                 # answered, so no rate bound (position_trust.CommandRate)
        try:
            node._publish(stage.process(INPUT, request.initial_pose, now, user))
        except Exception as err:  # noqa: BLE001 - a node never dies on a request
            stage._reject("internal_error", f"set_pose: {type(err).__name__}: {err}")
        finally:
            stage.set_pose_call = False
        node._log_rejections()
        response.success = sum(stage.diag.rejected.values()) == before
        if response.success:
            p = request.initial_pose.pose.pose.position
            node.get_logger().info(f"set_pose{' ' + user if user else ''}: restarted at ({p.x:.2f}, {p.y:.2f})")
        return response
