"""The work ``indoor-loc bench backend`` times: the PUTMC front end (reading the text files, the
stepometer and headings) and one graph configuration over all walks, importing only what that work
needs (the PUTMC reader, the stepometer, the graph; no ROS, plotting, evaluation or bench code).

Run as a module, it is one configuration from scratch in a fresh process, as the authors' C++ is
timed (one process per configuration: loading, stepometer, WKNN, 15 LM iterations), and prints one
JSON line: the work's CPU and wall time, the process's CPU time in all (interpreter start-up and
imports included) and its peak resident memory::

    python -m indoor_loc.bench.backend_run DATA_DIR "separate, no step-length est." [--jobs N]

``--jobs N``: the walks' front ends in N forked workers while this process builds the graph
(:func:`from_scratch`; the same poses, the CPU time of all the processes). :func:`scratch` runs it
from the bench.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Sequence

if TYPE_CHECKING:       # the heavy imports wait until the work starts (see main)
    import numpy as np

    from indoor_loc.backend.graph import GraphParams, MultiUserGraph
    from indoor_loc.backend.putmc_events import WalkEvents
    from indoor_loc.wifi.types import RadioMap

#: the front end's parts, as :func:`load` times them
READING = "reading the text files (24 walks, survey, routes)"
STEPS = "stepometer + headings"
#: the importer's configuration (joint + step length, measured noise, Huber): ``PUTMC_GRAPH_PARAMS``
DEFAULT = "default (importer): joint + SLE, measured noise, Huber"
#: the configurations :func:`configs` gives, in its order
CONFIG_NAMES = ("separate, no step-length est.", "separate, step-length est.", "joint, no step-length est.",
                "joint, step-length est.", DEFAULT)


def configs() -> dict[str, GraphParams]:
    """The paper's four configurations (users separate/joint x step length off/on) and the default,
    each optimised once at the end (no live window)."""
    from indoor_loc.backend.graph import GraphParams
    from indoor_loc.backend.putmc_events import PUTMC_GRAPH_PARAMS
    return dict(zip(CONFIG_NAMES, (
        GraphParams(joint=False, estimate_step_length=False, window_poses=0),
        GraphParams(joint=False, estimate_step_length=True, window_poses=0),
        GraphParams(joint=True, estimate_step_length=False, window_poses=0),
        GraphParams(joint=True, estimate_step_length=True, window_poses=0),
        GraphParams(window_poses=0, **PUTMC_GRAPH_PARAMS))))


@dataclass
class Putmc:
    """The front end's output for the graph and the scoring, per walk number, and its times (s)."""
    walks: list[int]
    events: dict[int, WalkEvents]
    truth: dict[int, tuple[np.ndarray, np.ndarray]]      # scan stamps, true scan xy
    segments: dict[int, np.ndarray]
    survey: RadioMap
    load_s: float
    load_cpu_s: float = 0.0
    #: wall and CPU time (s) of the front end's parts: READING, STEPS
    parts: dict[str, tuple[float, float]] = field(default_factory=dict)


class _Clock:
    """Wall and CPU time (``time.process_time``: this process, all threads) summed per part."""

    def __init__(self) -> None:
        self.parts: dict[str, tuple[float, float]] = {}

    @contextmanager
    def part(self, name: str) -> Iterator[None]:
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            w, c = self.parts.get(name, (0.0, 0.0))
            self.parts[name] = (w + time.perf_counter() - t0, c + time.process_time() - c0)

    def add(self, parts: dict[str, tuple[float, float]]) -> None:
        """Another clock's times, added part by part."""
        for name, (w, c) in parts.items():
            w0, c0 = self.parts.get(name, (0.0, 0.0))
            self.parts[name] = (w0 + w, c0 + c)


def load(data: Path, walks: Sequence[int] | None = None, jobs: int = 1) -> Putmc:
    """Every walk's hops and scans (the front end), timed (wall and CPU time, in total and per part:
    reading the text files; the stepometer and headings). ``walks``: only these walk numbers
    (default: all). ``jobs`` > 1: the walks are shared out among that many forked worker processes
    while this one reads the survey — not less work, so the CPU times are those of all the processes
    (this one's and the workers', each part summed over them) and only the wall time can drop."""
    t0, c0, k0 = time.perf_counter(), time.process_time(), _children_cpu_s()
    with _walks(data, walks, jobs) as w:
        for _ in w.events():
            pass
    cpu = time.process_time() - c0 + _children_cpu_s() - k0
    return w.putmc(time.perf_counter() - t0, cpu)


class _Walks:
    """What :func:`_walks` yields: the survey, each walk's events as they come (:meth:`events`), and
    the dataset in :class:`Putmc` form once they all came (:meth:`putmc`)."""

    def __init__(self, ds: Any, numbers: list[int], survey: RadioMap, front: _FrontEnd, clock: _Clock) -> None:
        self.ds, self.numbers, self.survey, self.front, self.clock = ds, numbers, survey, front, clock
        self.ev: dict[int, WalkEvents] = {}
        self.truth: dict[int, tuple] = {}
        self.seg: dict[int, Any] = {}

    def events(self) -> Iterator[WalkEvents]:
        """Each walk's events, in walk order, as they come (its truth, segments and parts' times kept)."""
        for n, e, tr, parts in self.front.results():
            self.ev[n], self.truth[n], self.seg[n] = e, tr, self.ds.routes[n].segments
            self.clock.add(parts)
            yield e

    def putmc(self, load_s: float, cpu_s: float) -> Putmc:
        return Putmc(self.numbers, self.ev, self.truth, self.seg, self.survey, load_s, cpu_s, self.clock.parts)


@contextmanager
def _walks(data: Path, walks: Sequence[int] | None, jobs: int) -> Iterator[_Walks]:
    """The PUTMC dataset opened and its survey read (timed as reading), with the front ends of walks
    ``walks`` (default: all) computed by :class:`_FrontEnd` meanwhile; on exit its workers are waited for."""
    from indoor_loc.datasets.putmc import Putmc as Dataset

    clock = _Clock()
    with clock.part(READING):
        ds = Dataset(Path(data) / "putmc")
    numbers = [n for n in ds.walk_numbers if walks is None or n in walks]
    with _FrontEnd(ds, numbers, jobs) as front:
        with clock.part(READING):
            survey = ds.survey_map()                    # (while the workers, if any, take the walks)
        yield _Walks(ds, numbers, survey, front, clock)


#: the dataset :func:`_front_end` reads from: set by :class:`_FrontEnd` (and inherited by its forked workers)
_DATASET: Any = None


class _FrontEnd:
    """The front end of walks ``numbers`` of dataset ``ds``, walk by walk in walk order
    (:meth:`results`): computed one after another in this process as they are asked for (``jobs`` 1),
    or by ``jobs`` worker processes forked on entry, which work ahead while this process does
    something else (the graph of the walks already received). On exit the workers have exited and
    been waited for, so their CPU time is in ``RUSAGE_CHILDREN``."""

    def __init__(self, ds: Any, numbers: Sequence[int], jobs: int = 1) -> None:
        self.ds, self.numbers, self.jobs = ds, list(numbers), max(1, min(int(jobs), len(numbers)))
        self.pool: Any = None

    def __enter__(self) -> _FrontEnd:
        global _DATASET
        _DATASET = self.ds
        if self.jobs > 1:
            import gc
            import multiprocessing

            # the objects this process has now are left out of the collector's passes (the workers'
            # too): a pass writes to every object it visits, and each page so written is copied
            gc.freeze()
            try:
                # Ctrl-C reaches the whole process group: the workers ignore it and this process ends
                # them (a worker interrupted while holding the task queue's lock would hang terminate())
                self.pool = multiprocessing.get_context("fork").Pool(self.jobs, initializer=_ignore_sigint)
                # ordered, one walk per task: walk n's events arrive as soon as walks 1…n are done
                self._it: Iterator = self.pool.imap(_front_end, self.numbers)
            except BaseException:
                self.__exit__(BaseException)
                raise
        else:
            self._it = map(_front_end, self.numbers)
        return self

    def results(self) -> Iterator[tuple[int, WalkEvents, tuple, dict]]:
        """(walk number, its events, its truth (scan stamps, true scan xy), the parts' times)."""
        for n, (e, tr, parts) in zip(self.numbers, self._it):
            yield n, e, tr, parts

    def __exit__(self, exc_type: Any, *_: Any) -> None:
        global _DATASET
        if self.jobs > 1:
            if self.pool is not None:
                if exc_type is not None:
                    self.pool.terminate()
                self.pool.close()
                self.pool.join()
                self.pool = None
            import gc
            gc.unfreeze()
        _DATASET = None


def _ignore_sigint() -> None:
    """A worker's initializer: SIGINT is for the process that forked it (:class:`_FrontEnd`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _front_end(n: int) -> tuple[WalkEvents, tuple, dict]:
    """Walk ``n``'s events and truth, and the parts' times."""
    from indoor_loc.backend.putmc_events import walk_events

    ds = _DATASET
    clock = _Clock()
    with clock.part(READING):
        w = ds.walk(n)
    with clock.part(STEPS):
        e = walk_events(w)
    return e, (w.scan_t, w.scan_xy), clock.parts


def _children_cpu_s() -> float:
    """CPU time of this process's terminated and waited-for children (the forked workers)."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def _feed(g: MultiUserGraph, events: WalkEvents) -> None:
    """One walk's hops and scans into the graph, in stamp order; then its user is finished."""
    name = events.name
    for _, kind, payload in events.events():
        if kind == 0:
            g.add_hop(name, *payload)        # type: ignore[misc]
        else:
            g.add_scan(name, payload)        # type: ignore[arg-type]
    g.finish_user(name)


def run_graph(data: Putmc, params: GraphParams, survey: RadioMap | None = None) -> tuple[MultiUserGraph, float]:
    """Walks 1…24 one after another, then one optimisation; returns the graph and the wall time."""
    from indoor_loc.backend.graph import MultiUserGraph

    t0 = time.perf_counter()
    g = MultiUserGraph(params, data.survey if survey is None else survey)
    for n in data.walks:
        _feed(g, data.events[n])
    g.optimize()
    return g, time.perf_counter() - t0


@dataclass
class Scratch:
    """One configuration from scratch (:func:`from_scratch`): the front end's output (with its parts'
    times), the optimised graph, and the work's wall and CPU time (s) — CPU of this process and of its
    workers, if any."""
    data: Putmc
    graph: MultiUserGraph
    wall_s: float
    cpu_s: float
    jobs: int


def from_scratch(data: Path, params: GraphParams, walks: Sequence[int] | None = None, jobs: int = 1) -> Scratch:
    """The work the reference times for one configuration: the front end of every walk (reading,
    stepometer, headings), the graph (walks 1…24 one after another, WKNN) and one optimisation.

    ``jobs`` > 1: the walks' front ends are computed by that many forked worker processes, ahead of
    this one, which meanwhile reads the survey and puts each walk into the graph as soon as its
    events arrive (in walk order: the graph, and so every pose and score, is the same as with
    ``jobs`` 1, which computes a walk's front end and then puts it in the graph, one walk after
    another). The optimisation is one process's work either way. Not less work: the CPU time is
    this process's and the workers' (waited for, ``RUSAGE_CHILDREN``), so only the wall time can drop.
    The front end's times per part (``data.parts``) are summed over the processes; ``data.load_s``
    is the wall time until the last walk's events arrived."""
    from indoor_loc.backend.graph import MultiUserGraph

    t0, c0, k0 = time.perf_counter(), time.process_time(), _children_cpu_s()
    with _walks(data, walks, jobs) as w:
        g = MultiUserGraph(params, w.survey)
        for e in w.events():
            _feed(g, e)
        load_s = time.perf_counter() - t0
    g.optimize()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0 + _children_cpu_s() - k0
    front_cpu = sum(c for _, c in w.clock.parts.values())
    return Scratch(w.putmc(load_s, front_cpu), g, wall, cpu, w.front.jobs)


def run_graph_timed(data: Putmc, params: GraphParams,
                    survey: RadioMap | None = None) -> tuple[MultiUserGraph, float, float]:
    """:func:`run_graph`, also returning its CPU time (this process; all threads)."""
    c0 = time.process_time()
    g, wall = run_graph(data, params, survey)
    return g, wall, time.process_time() - c0


def _process_cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _peak_rss_mb() -> float:
    """This process's peak resident memory, MB: ``VmHWM`` of ``/proc/self/status`` (since the exec;
    ``getrusage``'s ``ru_maxrss`` starts from the parent's at the fork), else ``ru_maxrss``."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0      # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0     # Linux: KiB


def measure(data: Path, config: str, walks: Sequence[int] | None = None, jobs: int = 1) -> dict[str, Any]:
    """This process (fresh): import what the work needs, then the front end (``jobs``: see
    :func:`load`) and the graph of ``config`` once. CPU times are this process's and its workers'
    (``time.process_time`` / ``getrusage``)."""
    cpu_start, rss_start = _process_cpu_s(), _peak_rss_mb()       # interpreter start-up
    c0 = time.process_time()
    import numpy  # noqa: F401  (imported first so that its share is reported)
    cpu_numpy = time.process_time() - c0
    import indoor_loc.backend.graph  # noqa: F401
    import indoor_loc.backend.putmc_events  # noqa: F401
    import indoor_loc.datasets.putmc  # noqa: F401
    import indoor_loc.eval.metrics  # noqa: F401  (the reader's route check: imported once, before any fork)
    params = configs()[config]
    cpu_imports = time.process_time() - c0
    rss_imports = _peak_rss_mb()
    s = from_scratch(data, params, walks, jobs)
    return {"config": config, "jobs": s.jobs, "walks": len(s.data.walks), "poses": int(s.graph.poses.n),
            "cpu_start_s": cpu_start, "cpu_numpy_s": cpu_numpy, "cpu_imports_s": cpu_imports,
            "cpu_front_s": s.data.load_cpu_s, "wall_front_s": s.data.load_s, "cpu_work_s": s.cpu_s,
            "wall_work_s": s.wall_s, "cpu_process_s": _process_cpu_s() + _children_cpu_s(),
            "rss_start_mb": rss_start, "rss_imports_mb": rss_imports, "rss_peak_mb": _peak_rss_mb(),
            "rss_workers_peak_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0,
            "modules": sorted(m for m in sys.modules if m.split(".")[0] in {"scipy", "indoor_loc", "yaml"}
                              and m.count(".") <= 1)}


def scratch(data: Path, config: str, runs: int = 1, walks: Sequence[int] | None = None, jobs: int = 1,
            timeout_s: float = 300.0, pycache: str | Path | None = None) -> list[dict[str, Any]]:
    """:func:`measure` in ``runs`` fresh processes (``python -m indoor_loc.bench.backend_run``), one
    after another; their JSON results, each with ``wall_process_s``: the process's wall time from its
    start to its exit, timed here. ``pycache``: the processes read and write byte code there
    (``PYTHONPYCACHEPREFIX``, even where ``PYTHONDONTWRITEBYTECODE`` is set), so that a run after the
    first finds the modules compiled; default: the environment's setting."""
    cmd = [sys.executable, "-m", "indoor_loc.bench.backend_run", str(data), config, "--jobs", str(jobs)]
    if walks is not None:
        cmd += ["--walks", ",".join(str(n) for n in walks)]
    root = str(Path(__file__).resolve().parents[2])        # this package, first on the child's path
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p))
    if pycache is not None:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        env["PYTHONPYCACHEPREFIX"] = str(pycache)
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=False, env=env)
        wall = time.perf_counter() - t0
        if res.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed ({res.returncode}): {res.stderr.strip()[-2000:]}")
        out.append(dict(json.loads(res.stdout.strip().splitlines()[-1]), wall_process_s=wall))
    return out


def _walk_numbers(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not comma-separated walk numbers: {text!r}") from None


def _positive(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"not a whole number >= 1: {text!r}")
    return int(text)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m indoor_loc.bench.backend_run",
                                 description="One back-end configuration from scratch in this process; prints "
                                             "its times (s) and memory (MB) as one JSON line.")
    ap.add_argument("data", type=Path, help="datasets directory (holding putmc/)")
    ap.add_argument("config", help=f"configuration, one of: {'; '.join(CONFIG_NAMES)}")
    ap.add_argument("--walks", type=_walk_numbers, help="comma-separated walk numbers (default: all)")
    ap.add_argument("--jobs", type=_positive, default=1,
                    help="processes computing the walks' front ends while this one builds the graph (default 1)")
    args = ap.parse_args(argv)
    if args.config not in CONFIG_NAMES:
        ap.error(f"unknown configuration {args.config!r}; one of {list(CONFIG_NAMES)}")
    print(json.dumps(measure(args.data, args.config, args.walks, args.jobs)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
