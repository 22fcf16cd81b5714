"""A Foxglove / Lichtblick layout for the actual users: the 3D view of the building (``/map``
occupancy grid, ``/view/building``, ``/map/graph``) and, per user, ground truth, WiFi fixes, the
KF pose and smoothed path, the particle filter and the back-end's path, one colour per user; a plot
of the first user's x estimates, the diagnostics and the first user's PDR odometry beside it. The 3D
panel's *2D pose estimate* tool publishes on the first user's ``initialpose`` (change it in the
panel's settings to re-initialise another user's ``tll_pf``).

``indoor_loc/data/foxglove_layout.json`` is ``layout_for(["alice", "bob", "carol"])``; the demo
writes ``OUT/foxglove_layout.json`` for its walkers; ``indoor-loc view --write-layout FILE --users
a,b`` for any others.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

#: one colour per user, in order (matplotlib's tab10 without orange, which the WiFi fixes use)
COLOURS = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"]
FIX_COLOUR = "#ff7f0e"
BACKEND_COLOUR = "#9467bd"


def user_topics(user: str, colour: str) -> dict[str, dict[str, Any]]:
    return {
        f"/{user}/ground_truth": {"visible": True, "lineWidth": 0.12, "gradient": ["#000000aa", "#000000aa"],
                                  "type": "line"},
        f"/{user}/ground_truth/route": {"visible": False},
        f"/{user}/pdr_kf/path": {"visible": True, "lineWidth": 0.1, "gradient": [colour, colour], "type": "line"},
        f"/{user}/pdr_kf/pose": {"visible": True, "type": "arrow", "color": colour + "cc", "showCovariance": True,
                                 "covarianceColor": colour + "33"},
        f"/{user}/wifi/fix": {"visible": True, "type": "arrow", "color": FIX_COLOUR + "cc", "showCovariance": True,
                              "covarianceColor": FIX_COLOUR + "33"},
        f"/{user}/pf/pose": {"visible": True, "type": "arrow", "color": colour, "showCovariance": True,
                             "covarianceColor": colour + "40"},
        f"/{user}/pf/particles": {"visible": True, "type": "arrow", "arrowScale": [0.3, 0.05, 0.05],
                                  "color": colour + "66"},
        f"/backend/{user}/path": {"visible": True, "lineWidth": 0.08, "gradient": [BACKEND_COLOUR, BACKEND_COLOUR],
                                  "type": "line"},
    }


def layout_for(users: list[str]) -> dict[str, Any]:
    """The layout document (Foxglove's *Import layout* JSON) for these user names (at least one)."""
    if not users:
        raise ValueError("layout_for: expected at least one user")
    first = users[0]
    topics: dict[str, dict[str, Any]] = {"/map": {"visible": True, "colorMode": "map", "alpha": 0.5},
                                         "/map/graph": {"visible": True}, "/view/building": {"visible": True}}
    for i, u in enumerate(users):
        topics.update(user_topics(u, COLOURS[i % len(COLOURS)]))
    topics.update({f"/{u}/map/graph": {"visible": False} for u in users})
    three_d = {
        "cameraState": {"distance": 55, "perspective": False, "phi": 0.01, "thetaOffset": 0, "targetOffset": [20, 10, 0],
                        "target": [0, 0, 0], "targetOrientation": [0, 0, 0, 1], "fovy": 45, "near": 0.5, "far": 5000},
        "followMode": "follow-none", "followTf": "map",
        "scene": {"backgroundColor": "#ffffff", "labelScaleFactor": 1, "enableStats": False},
        "transforms": {}, "topics": topics,
        "layers": {"grid": {"visible": True, "layerId": "foxglove.Grid", "frameId": "map", "size": 60, "divisions": 60,
                            "lineWidth": 0.5, "color": "#24825a55", "position": [20, 10, -0.01], "rotation": [0, 0, 0],
                            "order": 1}},
        "publish": {"type": "pose_estimate", "poseTopic": "/move_base_simple/goal", "pointTopic": "/clicked_point",
                    "poseEstimateTopic": f"/{first}/initialpose",
                    "poseEstimateXDeviation": 0.5, "poseEstimateYDeviation": 0.5,
                    "poseEstimateThetaDeviation": 0.26179939},
        "imageMode": {}}
    plot = {"title": f"x of each estimate ({first}): WiFi, KF, particle filter",
            "paths": [{"value": f"/{first}/{rel}.pose.pose.position.x", "enabled": True, "timestampMethod": "headerStamp"}
                      for rel in ("wifi/fix", "pdr_kf/pose", "pf/pose")],
            "showXAxisLabels": True, "showYAxisLabels": True, "showLegend": True, "legendDisplay": "floating",
            "isSynced": True, "xAxisVal": "timestamp", "sidebarDimension": 240}
    return {"configById": {
        "3D!indoorloc": three_d, "Plot!errors": plot,
        "DiagnosticSummary!diag": {"minLevel": 0, "pinnedIds": [], "hardwareIdFilter": "", "topicToRender": "/diagnostics"},
        "RawMessages!pdr": {"topicPath": f"/{first}/pdr/odom", "diffEnabled": False, "diffMethod": "custom",
                            "diffTopicPath": "", "showFullMessageForDiff": False, "expansion": "auto"}},
        "globalVariables": {}, "userNodes": {}, "playbackConfig": {"speed": 1},
        "layout": {"first": "3D!indoorloc", "second": {"first": "Plot!errors", "second": {
            "first": "DiagnosticSummary!diag", "second": "RawMessages!pdr", "direction": "row"},
            "direction": "column", "splitPercentage": 45}, "direction": "row", "splitPercentage": 62}}


def write_layout(path: str | Path, users: list[str]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(layout_for(users), indent=2) + "\n")
    return path
