"""WifiFixStage: ``wifi/scan`` -> ``wifi/fix`` against a radio map (WKNN, path loss or coverage area).

Parameters (``wifi_fix_node``): ``radiomap`` (a radio map directory, see
:mod:`indoor_loc.wifi.radiomap`; "" = none), ``method`` ("wknn" | "pathloss" | "coverage"),
``frame_id`` and each method's own parameters as a group named after the method — in a params
file a nested mapping, which ROS 2 flattens to dotted parameter names::

    wifi_fix_node:
      ros__parameters:
        radiomap: /data/putmc/radiomap
        method: wknn
        wknn: {k: 4, shared_threshold: 0.6}     # ROS parameters wknn.k, wknn.shared_threshold

``fallback`` names a second method for the scans the first declines (the importers configure WKNN
with ``fallback: powed``, so every scan sharing one AP with the map gets a fix); fallback fixes are
counted under ``fallback.<primary reason>``.

Floors: on a multi-floor radio map (format v2, per-scan ``z``) the ``powed`` method detects the
floor; ``wifi/fix`` then carries ``pose.position.z`` = the floor's height from the map manifest's
``floors: {name: z_m}`` and ``covariance[14]`` its variance; diagnostics give ``last_floor``.
On a single-floor map z is 0.

An unreadable radio map is a configuration error at start-up. With ``radiomap: ""`` the stage
starts, drops every scan with reason ``no_map`` and says so under ``error`` in its diagnostics.
A scan the method declines (too few shared APs, outlier conflict...) publishes nothing and is
counted under ``declined.<reason>``; invalid scans are counted by the adapters' reasons.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from indoor_loc.params import field, group, require, validate_groups
from indoor_loc.contract import Qos
from indoor_loc.errors import InvalidMessageError
from msg_adapters.pose import fix_to_msg
from msg_adapters.wifi_scan import scan_from_msg
from indoor_loc.pipeline.stage import Output, Port, Stage
from indoor_loc.wifi.coverage import CoverageParams
from indoor_loc.wifi.methods import METHODS, make_chain
from indoor_loc.wifi.pathloss import PathLossParams
from indoor_loc.wifi.powed_knn import PowedKnnParams
from indoor_loc.wifi.radiomap import load_radiomap
from indoor_loc.wifi.types import Positioner, RadioMap
from indoor_loc.wifi.wknn import WknnParams

NODE_NAME = "wifi_fix_node"


@dataclass(frozen=True)
class WifiFixParams:
    """Parameters of ``wifi_fix_node`` (see config/wifi_fix_node.yaml)."""
    radiomap: str = field("", "radio map directory (indoor-loc radiomap build / import); '' = none: "
                                "scans are dropped (reason no_map) and diagnostics report the error")
    method: str = field("wknn", "positioning method: 'wknn', 'powed', 'pathloss' or 'coverage'")
    fallback: str = field("", "method for the scans the first declines ('' = none, e.g. 'powed')")
    frame_id: str = field("map", "frame_id of the published fixes (the radio map's frame)")
    wknn: WknnParams = group(WknnParams, "WKNN (indoor_loc/wifi/wknn.py; wknn.k, wknn.shared_threshold, ...)")
    pathloss: PathLossParams = group(PathLossParams, "path-loss model (indoor_loc/wifi/pathloss.py; pathloss.*)")
    coverage: CoverageParams = group(CoverageParams, "coverage areas (indoor_loc/wifi/coverage.py; coverage.*)")
    powed: PowedKnnParams = group(PowedKnnParams, "powed k-NN (indoor_loc/wifi/powed_knn.py; powed.k, "
                                                  "powed.age_tau_ms, ...)")

    def validate(self) -> None:
        n = type(self).__name__
        require(self.method in METHODS, n, "method", f"one of {sorted(METHODS)}", self.method)
        require(self.fallback in ("", *METHODS) and self.fallback != self.method, n, "fallback",
                f"'' or another of {sorted(METHODS)}", self.fallback)
        require(bool(self.frame_id), n, "frame_id", "a non-empty frame name", self.frame_id)
        validate_groups(self)

    def method_params(self) -> WknnParams | PathLossParams | CoverageParams | PowedKnnParams:
        """The Params object of the selected method."""
        return getattr(self, self.method)

    def make_positioner(self):
        """The configured positioner (with its fallback), unfitted."""
        return make_chain(self.method, self.method_params(), self.fallback,
                          getattr(self, self.fallback) if self.fallback else None)


class WifiFixStage(Stage):
    """WiFi positioning: wifi/scan -> wifi/fix (PoseWithCovarianceStamped, covariance in m^2)."""
    NODE_NAME = NODE_NAME
    PARAMS = WifiFixParams

    def __init__(self, params: WifiFixParams, *, namespace: str = "",
                 radio_map: RadioMap | None = None) -> None:
        super().__init__(params, namespace=namespace)
        self.params: WifiFixParams = params
        self.declined: Counter = Counter()
        self.fallbacks: Counter = Counter()
        self.floors: Counter = Counter()
        self.last_floor = ""
        self.fixes = 0
        self.last_sigma_m = math.nan
        self.radio_map: RadioMap | None = radio_map
        self.positioner: Positioner | None = None
        if self.radio_map is None and params.radiomap:
            self.radio_map = load_radiomap(Path(params.radiomap).expanduser())   # MapError -> start-up fails
        if self.radio_map is not None:
            self.positioner = params.make_positioner().fit(self.radio_map)
        self._last_scan_ns: int | None = None     # stamp of the last scan accepted (older ones: stamp_backwards)
        self.on("wifi/scan", self._on_scan)

    def inputs(self) -> list[Port]:
        return [Port("wifi/scan", "diagnostic_msgs/msg/DiagnosticArray", Qos.RELIABLE)]

    def outputs(self) -> list[Port]:
        return [Port("wifi/fix", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE)]

    def set_radio_map(self, rm: RadioMap) -> None:
        """Replace the map (e.g. grown by the back-end) and refit the positioner."""
        self.radio_map = rm
        self.positioner = self.params.make_positioner().fit(rm)

    def _on_scan(self, msg, recv_ns: int) -> list[Output]:
        scan = scan_from_msg(msg)          # InvalidMessageError -> counted by reason
        if self.positioner is None:
            raise InvalidMessageError("no_map", "no radio map configured (parameter radiomap is '')")
        if self._last_scan_ns is not None and scan.stamp_ns < self._last_scan_ns:
            raise InvalidMessageError("stamp_backwards", f"scan stamp {scan.stamp_ns} ns is before the previous "
                                                         f"scan's {self._last_scan_ns} ns")
        self._last_scan_ns = scan.stamp_ns
        fix = self.positioner.locate(scan)
        if not fix.ok:
            self.declined[fix.reason or "declined"] += 1
            return []
        if not (np.all(np.isfinite(fix.xy)) and np.all(np.isfinite(fix.cov))):
            self.declined["non_finite"] += 1
            return []
        self.fixes += 1
        if "fallback_from" in fix.info:
            self.fallbacks[fix.info["fallback_from"] or "declined"] += 1
        if self.radio_map is not None and self.radio_map.floors:
            self.last_floor = fix.info.get("floor") or f"z={fix.z:g}"
            self.floors[self.last_floor] += 1
        self.last_sigma_m = math.sqrt(max(float(np.max(np.linalg.eigvalsh(fix.cov))), 0.0))
        return [("wifi/fix", fix_to_msg(fix, frame_id=self.params.frame_id))]

    def extra_diagnostics(self) -> dict[str, str]:
        out = {"method": self.params.method, "radiomap": self.params.radiomap or "(none)",
               "fixes": str(self.fixes), "declined.total": str(sum(self.declined.values()))}
        out.update({f"declined.{k}": str(v) for k, v in sorted(self.declined.items())})
        if self.params.fallback:
            out["fallback"] = self.params.fallback
            out.update({f"fallback.{k}": str(v) for k, v in sorted(self.fallbacks.items())})
        if self.last_floor:
            out["last_floor"] = self.last_floor
            out.update({f"floor.{k}": str(v) for k, v in sorted(self.floors.items())})
        if self.radio_map is None:
            out["error"] = "no radio map configured (parameter radiomap is ''): scans are dropped"
        else:
            out["map.scans"] = str(self.radio_map.n_scans)
            out["map.aps"] = str(self.radio_map.n_aps)
        if self.fixes:
            out["last_fix_sigma_m"] = f"{self.last_sigma_m:.2f}"
        return out
