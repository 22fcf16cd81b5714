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

BLE (``ble.enabled``): the node also takes ``ble/scan`` (schema ``ble_scan.v1``) and adds the beacons heard in
the last ``ble.window_s`` before each WiFi scan to it as entries ``ble:<beacon id>`` (:mod:`indoor_loc.wifi.ble`),
so a radio map holding those keys (the importers build them from the survey the same way) locates the scan on
WiFi and BLE together; diagnostics give ``ble.*``. A jump back in time forgets the readings.

Floor plans: ``floor_plans`` names the directory of per-floor plans ``indoor-loc import ms-indoor``
writes (``OUT_DIR/floors``); with ``powed.field_weight`` > 0 the powed method's extrapolating radio map
then extends only over each floor's walkable area (:mod:`indoor_loc.wifi.walkable`). A missing or
unreadable plan is a configuration error at start-up naming the path.

Map mismatch (``map_check``, :mod:`indoor_loc.wifi.map_check`): when most of the last scans were declined,
or they match the map far worse than the map's own scans match each other (leave-one-out), the scans do not
fit the map (another place, or access points moved): said once as a notice (the node's WARN), and while it
lasts a standing ``warning`` (WARN in ``/diagnostics``) with ``map_fit.*`` values. A map whose fingerprints
disagree with their positions (its own scans' best matches as far away as any other scan) is said at start-up
and stays a standing ``warning``.

An unreadable radio map is a configuration error at start-up. With ``radiomap: ""`` the stage
starts, drops every scan with reason ``no_map`` and says so under ``error`` in its diagnostics.
A scan the method declines (too few shared APs, outlier conflict...) publishes nothing and is
counted under ``declined.<reason>``; invalid scans are counted by the adapters' reasons.

Fitting the positioner to a large map takes seconds (the pooled four-floor ms_site2 map: about
7 s with the powed k-NN grid, 25–27 s with the importer's parameters, which add the path-loss
field bounded by the floor plans). Offline (``indoor-loc run``) and by default the stage fits it at
construction. The live node constructs it with ``fit_now=False`` and fits in a worker thread
(:meth:`WifiFixStage.begin_fit` / :meth:`fit_positioner` / :meth:`end_fit`): meanwhile each scan is
validated as usual and kept in a queue of at most ``pending_max`` scans (the oldest beyond it is
dropped and counted as ``rejected.fit_queue_full``); when the fit ends the queued scans are located
in arrival order, so the fixes are exactly those of the synchronous stage. A failed fit is a standing
``error`` (ERROR in ``/diagnostics``) with its cause; the queued scans are then counted as
``rejected.fit_failed``. While a new map (:meth:`set_radio_map`, or ``begin_fit`` live) is being
fitted, the previous one keeps answering.

Saved fits (``fit_cache``, on by default; :mod:`indoor_loc.wifi.fit_store`): the fit of the map named by
``radiomap`` is saved in ``fit_cache_dir`` (default ``<radiomap>/fit_cache``) and loaded at the next start
on the same map files, floor plans, parameters and code (the pooled map: 0.8 s instead of the fit); a
stale or unreadable file is logged, fitted again and replaced; diagnostics give ``fit.cache`` (the file loaded
or saved). ``indoor-loc radiomap fit`` saves it ahead
of time. A map given otherwise (:meth:`set_radio_map`) is fitted. After a fit the positioner drops the
data only the fit used; the fixes are the same either way.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import sys
from collections import Counter, deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from indoor_loc.params import field, group, require, validate_groups
from indoor_loc.contract import Qos
from indoor_loc.errors import InvalidMessageError
from msg_adapters.pose import fix_to_msg
from msg_adapters.ble_scan import ble_from_msg
from msg_adapters.wifi_scan import scan_from_msg
from indoor_loc.pipeline.stage import Output, Port, Stage
from indoor_loc.pipeline.time_policy import TimeParams
from indoor_loc.wifi.ble import BleParams, BleWindow
from indoor_loc.wifi.coverage import CoverageParams
from indoor_loc.wifi.fit_store import FitStore, Log, fit_positioner, plan_files
from indoor_loc.wifi.map_check import MapCheck, MapCheckParams, MapCheckState
from indoor_loc.wifi.methods import METHODS, make_chain
from indoor_loc.wifi.pathloss import PathLossParams
from indoor_loc.wifi.powed_knn import PowedKnn
from indoor_loc.wifi.powed_knn_params import PowedKnnParams
from indoor_loc.wifi.radio_field import Walkable
from indoor_loc.wifi.radiomap import load_radiomap
from indoor_loc.wifi.types import Positioner, RadioMap, WifiScan
from indoor_loc.wifi.walkable import load_floor_plans
from indoor_loc.wifi.wknn import WknnParams

NODE_NAME = "wifi_fix_node"
#: Scans kept while the radio map is being fitted with no earlier map to answer them (live start-up):
#: 1000 scans = 17 min of one phone scanning every second. Beyond it the oldest is dropped and counted.
PENDING_MAX = 1000


@dataclass(frozen=True)
class WifiFixParams:
    """Parameters of ``wifi_fix_node`` (see config/wifi_fix_node.yaml)."""
    radiomap: str = field("", "radio map directory (indoor-loc radiomap build / import); '' = none: "
                                "scans are dropped (reason no_map) and diagnostics report the error")
    method: str = field("wknn", "positioning method: 'wknn', 'powed', 'pathloss' or 'coverage'")
    fallback: str = field("", "method for the scans the first declines ('' = none, e.g. 'powed')")
    frame_id: str = field("map", "frame_id of the published fixes (the radio map's frame)")
    fit_cache: bool = field(True, "save the fitted radio map (powed k-NN) and load it at the next start on the same "
                                  "map files, floor plans, parameters and code instead of fitting again "
                                  "(indoor_loc.wifi.fit_store; `indoor-loc radiomap fit` does it ahead of time)")
    fit_cache_dir: str = field("", "directory of the saved fits; '' = <radiomap>/fit_cache")
    floor_plans: str = field("", "floor plans bounding the powed method's extrapolating radio map (powed.field_weight "
                                 "> 0): the directory `indoor-loc import ms-indoor` writes (OUT_DIR/floors, one "
                                 "<floor>/map.yaml + geojson_map.json each, matched to the map's floors by z_m); "
                                 "'' = none")
    wknn: WknnParams = group(WknnParams, "WKNN (indoor_loc/wifi/wknn.py; wknn.k, wknn.shared_threshold, ...)")
    pathloss: PathLossParams = group(PathLossParams, "path-loss model (indoor_loc/wifi/pathloss.py; pathloss.*)")
    coverage: CoverageParams = group(CoverageParams, "coverage areas (indoor_loc/wifi/coverage.py; coverage.*)")
    powed: PowedKnnParams = group(PowedKnnParams, "powed k-NN (indoor_loc/wifi/powed_knn.py; powed.k, "
                                                  "powed.age_tau_ms, ...)")
    time: TimeParams = group(TimeParams, "which stamps are taken, clock jumps (indoor_loc/pipeline/time_policy.py)")
    ble: BleParams = group(BleParams, "BLE beacons as a second RF source (indoor_loc/wifi/ble.py; ble.enabled, "
                                      "ble.window_s): ble/scan readings join the WiFi scans as 'ble:<id>' entries")
    map_check: MapCheckParams = group(MapCheckParams, "whether the scans still fit the radio map: a WARN when most "
                                                      "are declined or they match it far worse than its own scans "
                                                      "(indoor_loc/wifi/map_check.py; map_check.*)")

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

    def make_positioner(self, walkable: Walkable | None = None):
        """The configured positioner (with its fallback), unfitted; ``walkable`` (from ``floor_plans``)
        bounds the powed method's extrapolating grid."""
        pos = make_chain(self.method, self.method_params(), self.fallback,
                         getattr(self, self.fallback) if self.fallback else None)
        for part in (pos, getattr(pos, "primary", None), getattr(pos, "fallback", None)):
            if isinstance(part, PowedKnn):
                part.walkable = walkable
        return pos


class WifiFixStage(Stage):
    """WiFi positioning: wifi/scan -> wifi/fix (PoseWithCovarianceStamped, covariance in m^2)."""
    NODE_NAME = NODE_NAME
    PARAMS = WifiFixParams

    def __init__(self, params: WifiFixParams, *, namespace: str = "",
                 radio_map: RadioMap | None = None, fit_now: bool = True, pending_max: int = PENDING_MAX) -> None:
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
        #: the map being fitted (``begin_fit`` .. ``end_fit``/``fit_failed``) and its job number
        self.fitting: RadioMap | None = None
        self.fit_job = 0
        self.fit_error = ""
        #: scans received while no positioner could answer them: (scan, node-clock receive ns)
        self.pending: deque[tuple[WifiScan, int]] = deque()
        self.pending_max = max(1, int(pending_max))
        self.located_late = 0           # queued scans located once the fit ended
        #: where people can be per floor, from ``floor_plans`` (ConfigError at start-up naming the path)
        self.walkable: Walkable | None = None
        self._configured_map: RadioMap | None = None
        #: log(level, text) of the fit store (the live node: its logger; None: stderr)
        self.fit_log: Log | None = None
        self.floor_plans: dict[float, str] = {}
        #: floor plans not parsed at start-up: every fit they bound is saved (read when a fit is needed)
        self._plans_deferred = False
        store = FitStore(params.radiomap, params.floor_plans, params.fit_cache_dir) \
            if params.fit_cache and params.radiomap and self.radio_map is None else None
        if store is not None:              # the map's arrays as saved from the same files (no CSV to parse)
            self.radio_map = store.load_map(self._log)
        if self.radio_map is None and params.radiomap:
            self.radio_map = load_radiomap(Path(params.radiomap).expanduser())   # MapError -> start-up fails
        if params.radiomap and self.radio_map is not None and radio_map is None:
            self._configured_map = self.radio_map       # its fit may be saved beside it (fit_cache)
        self._store = store
        if params.floor_plans:
            if store is not None and self.radio_map is not None and store.is_current(self.params.make_positioner()):
                self._plans_deferred = True             # unchanged since a fit they bounded: parsed that time
                self.floor_plans = {float(i): str(f) for i, f in enumerate(plan_files(Path(params.floor_plans).expanduser()))
                                    if f.name == "geojson_map.json"}
            else:
                self.walkable, self.floor_plans = load_floor_plans(params.floor_plans)   # ConfigError naming it
        if self.radio_map is not None:
            if fit_now:
                self.positioner = self.fit_positioner(self.radio_map)
            else:               # radio_map is the configured map; it answers once end_fit installs it
                self.begin_fit(self.radio_map)
        #: whether the scans fit the radio map (map_check.*), built for the map in use
        self.map_check: MapCheck | None = None
        if self.radio_map is not None and params.map_check.enabled:
            self._new_map_check(self.radio_map)
        self.on("wifi/scan", self._on_scan)
        #: BLE readings of the last ble.window_s (ble.enabled), joined to each WiFi scan
        self.ble_window = BleWindow(params.ble.window_s)
        self.ble_merged = 0             # WiFi scans that got at least one beacon
        if params.ble.enabled:
            self.on("ble/scan", self._on_ble)

    def for_user(self, namespace: str) -> WifiFixStage:
        """A stage for another user sharing this one's radio map, floor plans, fitted positioner and the
        map check's reference (read-only); the user's own: its counters and the map check's window."""
        other = type(self)(dataclasses.replace(self.params, radiomap="", floor_plans=""), namespace=namespace)
        other.params = self.params
        other.radio_map, other.positioner, other.walkable = self.radio_map, self.positioner, self.walkable
        other.floor_plans, other.fit_error, other._configured_map = self.floor_plans, self.fit_error, self._configured_map
        if self.map_check is not None:
            other.map_check = copy.copy(self.map_check)
            other.map_check.state = MapCheckState.empty(self.params.map_check.window)
        return other

    def inputs(self) -> list[Port]:
        ports = [Port("wifi/scan", "diagnostic_msgs/msg/DiagnosticArray", Qos.RELIABLE, required=True)]
        if self.params.ble.enabled:     # beacons may be absent where the user is: an occasional input
            ports.append(Port("ble/scan", "diagnostic_msgs/msg/DiagnosticArray", Qos.RELIABLE, stream=False))
        return ports

    def reset_user(self, user: str) -> list[Output]:
        self.ble_window.clear()         # readings of the old pass must not join the new pass's scans
        return []

    def _on_ble(self, msg, recv_ns: int) -> list[Output]:
        self.ble_window.add(ble_from_msg(msg))          # InvalidMessageError -> counted by reason
        return []

    def outputs(self) -> list[Port]:
        return [Port("wifi/fix", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE)]

    def set_radio_map(self, rm: RadioMap) -> None:
        """Replace the map (e.g. grown by the back-end) and refit the positioner, here and now."""
        job = self.begin_fit(rm)
        self.end_fit(job, self.fit_positioner(rm))

    # -- fitting in steps (the live node runs fit_positioner in a worker thread) ----------------
    def fit_positioner(self, rm: RadioMap, log: Log | None = None, *, refit: bool = False,
                       store: FitStore | None = None) -> Positioner:
        """A new positioner fitted to ``rm``. Touches no state of the stage, so it may run in
        another thread while the stage handles scans. The configured map (parameter ``radiomap``)
        is loaded from its saved fit when one matches (``fit_cache``; :mod:`indoor_loc.wifi.fit_store`),
        else fitted (``refit``: always) and saved (in ``store``, default :meth:`fit_store`); ``log(level, text)``
        gets what the store did (default: :attr:`fit_log`, else stderr)."""
        store = self.fit_store(rm) if store is None else store
        walkable = self.walkable
        if self._plans_deferred and store is None:      # (with a store, the store reads them if a fit needs them)
            walkable = load_floor_plans(self.params.floor_plans)[0]
        return fit_positioner(self.params.make_positioner(walkable), rm, store, log or self.fit_log or self._log,
                              refit=refit)

    def fit_store(self, rm: RadioMap | None = None) -> FitStore | None:
        """Where fits of ``rm`` (default: the configured map) are saved: None unless ``fit_cache`` is on and
        ``rm`` is the map read from parameter ``radiomap`` (a map given otherwise has no files to key it)."""
        p = self.params
        rm = self._configured_map if rm is None else rm
        if not (p.fit_cache and p.radiomap and rm is not None and rm is self._configured_map):
            return None
        return self._store or FitStore(p.radiomap, p.floor_plans, p.fit_cache_dir)

    def _log(self, level: str, text: str) -> None:
        """What the fit store did: to :attr:`fit_log` (the live node's logger), else stderr."""
        if self.fit_log is not None:
            self.fit_log(level, text)
            return
        print(f"[{self.NODE_NAME}{' in ' + self.namespace if self.namespace else ''}] {level}: {text}",
              file=sys.stderr)

    def begin_fit(self, rm: RadioMap) -> int:
        """``rm`` is being fitted: until :meth:`end_fit`, scans are located with the current
        positioner, or queued when there is none. Returns the job number ``end_fit`` and
        :meth:`fit_failed` take (a later ``begin_fit`` supersedes an unfinished one)."""
        self.fit_job += 1
        self.fitting = rm
        return self.fit_job

    def end_fit(self, job: int, positioner: Positioner) -> list[Output]:
        """Install the positioner fitted for job ``job`` (ignored if a later job superseded it) and
        locate the queued scans in arrival order; returns their fixes (counted as published)."""
        if job != self.fit_job or self.fitting is None:
            return []
        self.radio_map, self.positioner, self.fitting, self.fit_error = self.fitting, positioner, None, ""
        out: list[Output] = []
        while self.pending:
            scan, recv_ns = self.pending.popleft()
            self.diag.now_ns = recv_ns
            self.located_late += 1
            out += self._guarded("queued scan", lambda scan=scan: self._locate(scan))
        return out

    def fit_failed(self, job: int, err: BaseException) -> None:
        """The fit of job ``job`` raised ``err``: a standing error (ERROR in diagnostics) with the
        cause; the previous positioner, if any, keeps answering, else the queued scans are dropped
        and counted (``fit_failed``)."""
        if job != self.fit_job or self.fitting is None:
            return
        n_scans = self.fitting.n_scans
        self.fitting = None
        self.fit_error = f"fitting the radio map ({n_scans} scans) failed: {type(err).__name__}: {err}"
        if self.positioner is not None:
            self.fit_error += f"; the previous map ({self.radio_map.n_scans if self.radio_map else 0} scans) is still used"
        while self.pending:
            scan, recv_ns = self.pending.popleft()
            self.diag.now_ns = recv_ns
            self._reject("fit_failed", f"wifi/scan stamped {scan.stamp_ns} ns: {self.fit_error}")

    def waiting_for_fit(self) -> bool:
        """True while scans are held for a fit in progress (no earlier positioner answers them)."""
        return self.fitting is not None and self.positioner is None

    def finish(self) -> list[Output]:
        # input ends while the map is still being fitted: the queued scans were never located
        while self.pending:
            scan, recv_ns = self.pending.popleft()
            self.diag.now_ns = recv_ns
            self._reject("fit_unfinished", f"wifi/scan stamped {scan.stamp_ns} ns: input ended before the "
                                           f"radio map was fitted; not located")
        return []

    def _on_scan(self, msg, recv_ns: int) -> list[Output]:
        scan = scan_from_msg(msg)          # InvalidMessageError -> counted by reason
        if self.params.ble.enabled:
            n = len(scan)
            scan = self.ble_window.merge(scan)
            self.ble_merged += len(scan) > n
        if self.positioner is None and self.fitting is None:
            if self.fit_error:
                raise InvalidMessageError("fit_failed", self.fit_error)
            raise InvalidMessageError("no_map", "no radio map configured (parameter radiomap is ''; set it, e.g. "
                                       "-p radiomap:=DIR, a directory from `indoor-loc radiomap build` or an importer)")
        if self.positioner is None:        # the map is being fitted: located when it is ready
            if len(self.pending) >= self.pending_max:
                old, _ = self.pending.popleft()
                self._reject("fit_queue_full", f"wifi/scan stamped {old.stamp_ns} ns dropped: more than "
                                               f"{self.pending_max} scans arrived while the radio map was fitted")
            self.pending.append((scan, recv_ns))
            return []
        return self._locate(scan)

    def _locate(self, scan: WifiScan) -> list[Output]:
        assert self.positioner is not None
        fix = self.positioner.locate(scan)
        if not fix.ok:
            self.declined[fix.reason or "declined"] += 1
            self._check_map_fit(scan, declined=True)
            return []
        if not (np.all(np.isfinite(fix.xy)) and np.all(np.isfinite(fix.cov))):
            self.declined["non_finite"] += 1
            self._check_map_fit(scan, declined=True)
            return []
        self._check_map_fit(scan, declined=False)
        self.fixes += 1
        if "fallback_from" in fix.info:
            self.fallbacks[fix.info["fallback_from"] or "declined"] += 1
        if self.radio_map is not None and self.radio_map.floors:
            self.last_floor = fix.info.get("floor") or f"z={fix.z:g}"
            self.floors[self.last_floor] += 1
        self.last_sigma_m = math.sqrt(max(float(np.max(np.linalg.eigvalsh(fix.cov))), 0.0))
        return [("wifi/fix", fix_to_msg(fix, frame_id=self.params.frame_id))]

    def _check_map_fit(self, scan: WifiScan, declined: bool) -> None:
        """Feed the map check (a new map in use gets a new one); say once when the scans stop fitting."""
        if not self.params.map_check.enabled or self.radio_map is None:
            return
        mc = self.map_check
        if mc is None or mc.radio_map is not self.radio_map:
            mc = self._new_map_check(self.radio_map)
        text = mc.update(scan, declined)
        if text:
            self.notice(text)

    def _new_map_check(self, rm: RadioMap) -> MapCheck:
        """The map check of ``rm`` (said once if the map disagrees with itself)."""
        self.map_check = MapCheck(rm, self.params.map_check)
        if self.map_check.map_suspect:
            self.notice(self.map_check.describe_map())
        return self.map_check

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
        if self.fit_error:
            out["error"] = self.fit_error
        elif self.radio_map is None and self.fitting is None:
            out["error"] = ("no radio map configured (parameter radiomap is ''): scans are dropped; set it, e.g. "
                            "-p radiomap:=DIR (`indoor-loc radiomap build` or an importer writes one)")
        if self.floor_plans:
            out["floor_plans"] = str(len(self.floor_plans))
        if self._store is not None and (self._store.loaded or self._store.saved):   # what the fit store did last
            out["fit.cache"] = f"loaded {self._store.loaded[-1]}" if self._store.loaded else \
                f"saved {self._store.saved[-1]}"
        if self.radio_map is not None:
            out["map.scans"] = str(self.radio_map.n_scans)
            out["map.aps"] = str(self.radio_map.n_aps)
        if self.fitting is not None:
            out["fit.state"] = "fitting"
            out["fit.map_scans"] = str(self.fitting.n_scans)
            out["fit.queued"] = str(len(self.pending))
        elif self.located_late:
            out["fit.located_late"] = str(self.located_late)
        if self.params.ble.enabled:
            out["ble.beacons_in_window"] = str(len(self.ble_window.readings))
            out["ble.scans_with_beacons"] = str(self.ble_merged)
        if self.fixes:
            out["last_fix_sigma_m"] = f"{self.last_sigma_m:.2f}"
        if self.map_check is not None and self.map_check.radio_map is self.radio_map:
            out.update(self.map_check.summary())
            warnings = [self.map_check.describe_map()]       # standing WARNs: a suspect map, scans not fitting it
            if self.map_check.state.mismatch:
                warnings.append(self.map_check.describe())
            if any(warnings):
                out["warning"] = "; ".join(w for w in warnings if w)
        return out
