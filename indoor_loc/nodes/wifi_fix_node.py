"""``ros2 run indoor_loc wifi_fix_node``: WiFi positioning, wifi/scan -> wifi/fix (see
pipeline/wifi_fix_stage.py). Each method's parameters are a group named after the method
(``wknn.k``, ``pathloss.sigma_db``, ``coverage.mimo`` ...), declared, merged and documented by
``--help`` like every stage's parameter groups.

Start-up does not wait for the radio map's fit (seconds on a large multi-floor map): the node is up
at once and fits in a worker thread, or loads the fit saved by an earlier start or by ``indoor-loc
radiomap fit`` (parameter ``fit_cache``; a stale or unreadable one is logged and fitted again).
Until the fit ends, ``/diagnostics`` says "fitting the radio map (N scans)" at WARN with the time so
far and the scans queued (``fit.*`` values), parameter and other requests are answered, and each
scan received is kept (see the stage's ``pending_max``) and located, in order, as soon as the fit
ends. A failed fit is an ERROR in ``/diagnostics`` with its cause, and the node keeps running.
:meth:`WifiFixNode.set_radio_map` replaces the map the same way (the previous one answers
meanwhile)."""
from __future__ import annotations

import threading
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from indoor_loc.nodes.process import run_stage_node
from indoor_loc.nodes.stage_node import StageNode
from indoor_loc.pipeline.wifi_fix_stage import WifiFixParams, WifiFixStage
from indoor_loc.wifi.types import Positioner, RadioMap


class _LiveWifiFixStage(WifiFixStage):
    """The stage as the live node builds it: the radio map is loaded (an unreadable one still stops
    start-up) but fitted later, in a worker thread."""

    def __init__(self, params: WifiFixParams, *, namespace: str = "") -> None:
        super().__init__(params, namespace=namespace, fit_now=False)


class WifiFixNode(StageNode):
    """The node class, for composing it in a process of one's own (``WifiFixNode(context=...)``)."""

    def __init__(self, **node_kwargs: Any) -> None:
        self._fit_lock = threading.Lock()
        #: (job, positioner or None, error or None, wall s, CPU s of the worker)
        self._fit_results: list[tuple[int, Positioner | None, BaseException | None, float, float]] = []
        self._fit_started: dict[int, float] = {}      # job -> time.monotonic() at its start
        super().__init__(_LiveWifiFixStage, **node_kwargs)
        self.stage: WifiFixStage
        logger = self.get_logger()
        # what the fit store did (loaded, saved, refused a stale or unreadable fit) goes to the node's log
        self.stage.fit_log = lambda level, text: (logger.warning if level == "warning" else logger.info)(text)
        self._fit_done = self.create_guard_condition(self._on_fit_done)
        if self.stage.fitting is not None:
            self._start_fit(self.stage.fit_job, self.stage.fitting)

    def set_radio_map(self, rm: RadioMap) -> None:
        """Replace the radio map without blocking the executor: it is fitted in a worker thread and
        installed when ready (the current map answers meanwhile; a later call supersedes this one)."""
        self._start_fit(self.stage.begin_fit(rm), rm)

    def _start_fit(self, job: int, rm: RadioMap) -> None:
        self._fit_started[job] = time.monotonic()
        self.get_logger().info(f"fitting the radio map ({rm.n_scans} scans, {rm.n_aps} APs) in the background")
        fit = self.stage.fit_positioner      # touches no stage state: safe beside the executor

        def work() -> None:
            t0, c0 = time.monotonic(), time.thread_time()
            try:
                result: tuple[Positioner | None, BaseException | None] = (fit(rm), None)
            except Exception as err:  # noqa: BLE001 - reported as an ERROR by the executor thread
                result = (None, err)
            with self._fit_lock:
                self._fit_results.append((job, *result, time.monotonic() - t0, time.thread_time() - c0))
            try:
                self._fit_done.trigger()
            except Exception:  # noqa: BLE001 - the node was destroyed meanwhile (stopping)
                pass

        threading.Thread(target=work, name=f"wifi_fix_fit_{job}", daemon=True).start()

    def _on_fit_done(self) -> None:
        """In the executor: install what the worker fitted, publish the queued scans' fixes."""
        with self._fit_lock:
            results, self._fit_results = self._fit_results, []
        for job, positioner, err, took_s, cpu_s in results:
            self._fit_started.pop(job, None)
            if positioner is not None:
                queued = len(self.stage.pending)
                outs = self.stage.end_fit(job, positioner)
                if self.stage.fitting is None and self.stage.positioner is positioner:
                    self.get_logger().info(f"radio map fitted in {took_s:.1f} s ({cpu_s:.1f} s CPU); located the {queued} scan(s) "
                                           f"received meanwhile ({len(outs)} fixes)")
                self._publish(outs)
            elif err is not None:
                self.stage.fit_failed(job, err)
                if self.stage.fit_error:
                    self.get_logger().error(self.stage.fit_error)
        self._log_rejections()
        self._diag_pub.publish(self.diagnostics_msg(self.get_clock().now().nanoseconds))

    def shutdown(self) -> None:
        queued = len(self.stage.pending)
        if queued:      # stopped before the fit ended: the stage counts them (fit_unfinished); say so
            self.get_logger().warning(f"stopping before the radio map was fitted: {queued} queued scan(s) "
                                      f"not located")
        super().shutdown()

    def diagnostics_msg(self, now_ns: int) -> DiagnosticArray:
        arr = super().diagnostics_msg(now_ns)
        rm = self.stage.fitting
        if rm is None or not arr.status:
            return arr
        st = arr.status[0]
        started = self._fit_started.get(self.stage.fit_job)
        elapsed = time.monotonic() - started if started is not None else 0.0
        st.values.append(KeyValue(key="fit.elapsed_s", value=f"{elapsed:.1f}"))
        if self.stage.waiting_for_fit():
            what = (f"fitting the radio map ({rm.n_scans} scans, {elapsed:.0f} s so far); "
                    f"{len(self.stage.pending)} scan(s) queued")
            if st.level < DiagnosticStatus.WARN:
                st.level = DiagnosticStatus.WARN
                st.message = what
            else:
                st.message = f"{what}; {st.message}"
        return arr


def main(args: list[str] | None = None) -> int:
    return run_stage_node(WifiFixStage, args, node_factory=WifiFixNode)


if __name__ == "__main__":
    raise SystemExit(main())
