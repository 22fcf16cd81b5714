"""``indoor-loc demo`` (``make demo``): the package's main job, live over DDS, on the shipped sample building.

With no arguments:

1. simulate a few walkers with phones in the sample building (``indoor-loc sim``) -> OUT/sim/
   (bag, radio map, building graph, truth, params.yaml; a few seconds, the same seed gives the same run);
2. bring up the nodes as processes over DDS (``indoor-loc up`` machinery), one ``--multi-user``
   process per stage serving every walker under the walker's namespace (docs/scaling.md;
   ``--per-user``: one process per stage and walker): ``imu_node`` (stepometer + AEKF heading ->
   pdr/odom, imu/data), ``wifi_fix_node`` (WKNN -> wifi/fix), ``pdr_kf_node`` (PDR + WiFi Kalman
   filter -> pdr_kf/pose, pdr_kf/path), the particle filter and the multi-user back-end when this
   build has them (a robot's estimators on its wheel odometry: ``user_params``), the recorder (every output
   topic -> OUT/live.mcap) and the player (the simulated bag, with /clock, all nodes on sim time);
3. when the bag has been played, wait for the multi-user nodes to finish the walkers (they leave
   once their inputs' publishers are gone), then (or on Ctrl-C) stop the nodes in dependency order:
   the player, then the estimators from sources to sinks (each one's final outputs reach the nodes
   after it), the recorder last; score each estimator per walker against the ground truth; draw
   OUT/demo.png.

``--dataset putmc`` runs the real-data demo instead (PUTMC import, offline replay through the same
stages, scores beside the published reference). ``--foxglove`` adds the live view
(``indoor-loc view``: Foxglove WebSocket on ws://localhost:8765).
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import os
import re
import signal
import sys
import threading
import time
from pathlib import Path

import yaml

from indoor_loc.errors import ConfigError

# (label, relative topic) of the estimators scored per walker (those present in the recording)
ESTIMATORS = [("WiFi only, WKNN", "wifi/fix"),
              ("PDR + WiFi KF, filtered", "pdr_kf/pose"),
              ("PDR + WiFi KF, RTS-smoothed", "pdr_kf/path"),
              ("particle filter (TLL), filtered", "pf/pose"),
              ("particle filter (TLL), smoothed", "pf/path"),
              ("multi-user back-end", "backend/{user}/path")]
#: Inputs played from the simulated bag: not recorded again (the sim bag has them).
INPUT_TOPICS_RE = r"(/imu/data_raw|/imu/mag|/wifi/scan|^/robot\d+/odom|^/robot\d+/imu|^/clock|^/rosout|^/parameter_events)$"
PER_WALKER_NODES = [("imu", "imu_node"), ("wifi", "wifi_fix_node"), ("pdr_kf", "pdr_kf_node")]
#: Node modules that later builds add; the demo starts them when present.
OPTIONAL_PER_WALKER = [("pf", "tll_pf_node")]
OPTIONAL_SHARED = [("backend", "backend_node")]
#: The demo's multi-user nodes: a user whose inputs have had no publisher this long has left (s)
USER_TIMEOUT_S = 3.0
#: Once the bag is played, the demo waits at most this long (s) for the multi-user nodes to finish their users
USERS_FINISH_WAIT_S = 90.0
#: A multi-user node's log line saying it has finished a user (``indoor_loc.nodes.multi_user_node``)
_FINISHED = re.compile(r"^\[(\w+)\] \[INFO\] .*: user '([^']+)' finished: ")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output directory (default out/demo)")
    parser.add_argument("--walkers", type=int, default=3, help="simulated walkers (default 3)")
    parser.add_argument("--robots", type=int, default=0, help="simulated differential-drive robots among them, their "
                                                              "estimators on their own wheel odometry (default 0)")
    parser.add_argument("--duration", type=float, default=60.0, help="simulated run length, s (default 60)")
    parser.add_argument("--seed", type=int, default=7, help="simulation seed (default 7)")
    parser.add_argument("--floors", type=int, choices=(2, 3), default=2,
                        help="3: the three-floor office with stairs and a lift; default 2: the two-floor sample "
                             "building (its stairs). Walkers change floors, phones have a barometer (docs/floors.md)")
    parser.add_argument("--rate", type=float, default=1.0, help="playback rate (default 1.0 = real time)")
    parser.add_argument("--foxglove", type=int, nargs="?", const=8765, default=None, metavar="PORT",
                        help="also serve the live view over the Foxglove WebSocket protocol (default port 8765)")
    parser.add_argument("--per-user", action="store_true",
                        help="run every stage as one process per walker (default: one --multi-user process per "
                             "stage serving every walker; docs/scaling.md)")
    parser.add_argument("--verbose", action="store_true", help="print every node's log lines (always in OUT/nodes.log)")
    parser.add_argument("--dataset", choices=("sim", "putmc"), default="sim",
                        help="'sim' (default): the shipped sample building, live over DDS; 'putmc': the real "
                             "PUTMC dataset from --data, replayed offline")
    g = parser.add_argument_group("--dataset putmc")
    g.add_argument("--data", type=Path, default=Path("../shared/datasets"),
                   help="datasets directory, holding putmc/ (default ../shared/datasets)")
    g.add_argument("--walks", default="all", help="PUTMC walks to use: 'all' or e.g. 1,7,12")
    g.add_argument("--plot-walk", type=int, default=6, help="walk drawn on the floor plan (default 6)")
    g.add_argument("--reimport", action="store_true", help="import again even if OUT/import exists")


def main(args: argparse.Namespace) -> int:
    if args.dataset == "putmc":
        from indoor_loc.demo_putmc import main as putmc_main
        return putmc_main(args)
    return run_sim_demo(args)


# ------------------------------------------------------------------------------------ simulation
def _simulate(out: Path, args: argparse.Namespace) -> dict[str, Path]:
    from indoor_loc.commands.sim import generate
    from indoor_loc.sim.baro import BaroSimParams
    from indoor_loc.sim.building import make_tower_building
    from indoor_loc.sim.scenario import SimConfig

    try:
        floors3 = getattr(args, "floors", 2) == 3
        # walkers go to every floor (the default seed's all take the stairs within 60 s) with a
        # barometer in every phone: OUT/demo_floors.png shows their floor over time
        cfg = SimConfig(walkers=args.walkers, duration_s=args.duration, seed=args.seed,
                        robots=getattr(args, "robots", 0), change_floors=True, baro=BaroSimParams())
        cfg.validate()
    except ValueError as err:
        raise ConfigError(str(err)) from err
    sim_dir = out / "sim"
    print(f"== 1/4 simulate {cfg.walkers} walkers x {cfg.duration_s:g} s in the sample building -> {sim_dir}")
    paths = generate(sim_dir, cfg, building=make_tower_building() if floors3 else None)
    scenario = yaml.safe_load(paths["scenario"].read_text())
    robots = [r["name"] for r in scenario.get("robots", [])]
    names = [w["name"] for w in scenario["walkers"]] + robots
    return {"bag": paths["bag"], "params": paths["params"], "dir": sim_dir, "walkers": names, "robots": robots}


def _module_exists(name: str) -> bool:
    return importlib.util.find_spec(f"indoor_loc.nodes.{name}") is not None


def bringup_config(walkers: list[str], sim: dict, out: Path, *, rate: float, foxglove: int | None,
                   dds_env: dict[str, str] | None = None, per_user: bool = False) -> dict:
    """The bring-up mapping (same schema as ``indoor-loc up``) of the live demo. ``dds_env``: the
    ``ROS_DOMAIN_ID`` / ``ROS_AUTOMATIC_DISCOVERY_RANGE`` chosen by :mod:`indoor_loc.dds_isolation`.
    ``per_user``: one process per stage and walker (else one ``--multi-user`` process per stage serves
    every walker: :func:`stage_nodes`)."""
    env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST"),
           **(dds_env or {}), "RCUTILS_COLORIZED_OUTPUT": "0"}
    # a replay: reliable sensor inputs, so the player's stream is never dropped in DDS (docs/nodes.md)
    replay = {"sensor_reliability": "reliable"}
    params = str(sim["params"])
    nodes: list[dict] = [{"name": "recorder", "module": "indoor_loc.nodes.recorder_node",
                          "args": ["-a", "-o", str(out / "live.mcap"), "--overwrite", "--poll", "0.5",
                                   "--exclude", INPUT_TOPICS_RE],
                          # wall clock: its graph polling must run before the player's /clock starts
                          # (log time = wall-clock reception; every message keeps its bag-time stamp)
                          "use_sim_time": False}]
    nodes += stage_nodes(walkers, list(sim.get("robots", ())), params, replay, per_user)
    # the name of the node holding a stage's subscriptions (a multi-user node's users' are on <name>_io)
    sub = (lambda mod: mod) if per_user else (lambda mod: f"{mod}_io")
    scan_consumers = [sub("wifi_fix_node")]
    for label, mod in OPTIONAL_SHARED:
        if _module_exists(mod):
            nodes.append({"name": label, "module": f"indoor_loc.nodes.{mod}", "params_files": [params],
                          "params": dict(replay)})
            scan_consumers.append(f"/{mod}")
    plans = Path(sim["dir"]) / "floor_plans"
    if plans.is_dir():       # the building as nav_msgs/OccupancyGrid on /map (latched), for RViz and Foxglove
        nodes.append({"name": "map", "module": "indoor_loc.nodes.map_node", "args": ["--plans", str(plans)],
                      "use_sim_time": False})
    if foxglove is not None:
        nodes.append({"name": "view", "module": "indoor_loc.nodes.view_node",
                      "args": ["--port", str(foxglove), "--building", str(sim["dir"] / "building.geojson")],
                      "use_sim_time": True})
    # the player starts with the nodes and waits until the nodes that consume its topics have matched
    # (by name: the view and the recorder subscribe to everything, a count would be met without
    # imu_node): the demo's sixteen processes (per user) starting on a 2-core machine took 20 s where one
    # CPU in three was free and over 60 s at a load average of 20, so the bound is 180 s (a loss is then
    # counted and printed with the scores)
    consumers = [f"imu/data_raw={sub('imu_node')}", f"imu/mag={sub('imu_node')}", "wifi/scan=" + ",".join(scan_consumers),
                 # ground truth and the building graph: the recorder is their consumer (for the scores)
                 "ground_truth=/recorder", "ground_truth/route=/recorder", "/map/graph=/recorder"]
    robot_args: list[str] = []
    if sim.get("robots"):
        # a robot's wheel odometry feeds its estimators (and the back-end); its gyro (imu) has no consumer
        # in the demo, so the player does not wait for one
        consumers.append("odom=" + ",".join([sub("pdr_kf_node"), sub("tll_pf")] + scan_consumers[1:]))
        robot_args = ["--min-subscribers", "imu=0"]
    nodes.append({"name": "player", "module": "indoor_loc.nodes.player_node",
                  "args": [str(sim["bag"]), "--clock", "50", "--rate", str(rate), "--wait-for-subscribers", "180",
                           "--consumers", *consumers, *robot_args, "--delay", "1.0"],
                  "use_sim_time": False})
    return {"env": env, "use_sim_time": True, "stop_timeout_s": 10.0, "nodes": nodes}


def stage_nodes(walkers: list[str], robots: list[str], params: str, replay: dict, per_user: bool) -> list[dict]:
    """The stage nodes of the demo's users. Default: one ``--multi-user`` process per stage
    (``imu``, ``wifi``, ``pdr_kf``, ``pf``) serving its ``users`` (docs/scaling.md): the walkers, and for
    ``wifi_fix_node``, ``pdr_kf_node`` and ``tll_pf`` the robots as well: a robot's estimators take its
    wheel odometry (``motion_source: odom``) where the walkers' take ``pdr/odom``, by the node's
    ``user_params`` (docs/scaling.md). ``per_user``: every stage one process per user (the layout of a
    robot or a few phones; a robot's from its params.yaml entry)."""
    from indoor_loc.sim.robot_write import ROBOT_NODE_PARAMS
    stages = PER_WALKER_NODES + [n for n in OPTIONAL_PER_WALKER if _module_exists(n[1])]
    nodes: list[dict] = []
    if not per_user:
        phones = [w for w in walkers if w not in robots]
        for label, mod in stages:
            users = [w for w in walkers if label != "imu" or w in phones]
            # the robots' own parameters (their per-user nodes' params.yaml entries) as user_params
            own = {f"user_params.{r}.{k}": v for r in robots if label in ("pdr_kf", "pf")
                   for k, v in ROBOT_NODE_PARAMS.items()}
            if users:
                nodes.append({"name": label, "module": f"indoor_loc.nodes.{mod}", "args": ["--multi-user"],
                              "params_files": [params],
                              "params": {**replay, "users": users, "user_timeout_s": USER_TIMEOUT_S, **own}})
    for w in walkers:
        for label, mod in stages:
            if label == "imu" and w in robots:
                continue                # a robot's own odometry is its motion input: no stepometer
            if per_user:
                nodes.append({"name": f"{label}_{w}", "module": f"indoor_loc.nodes.{mod}", "namespace": f"/{w}",
                              "params_files": [params], "params": dict(replay)})
    return nodes


def users_to_finish(cfg_map: dict) -> frozenset[tuple[str, str]]:
    """(node label, user) of every user of the bring-up's multi-user nodes: the demo waits for them
    to be finished (:func:`_supervise`)."""
    return frozenset((n["name"], u) for n in cfg_map["nodes"] if "--multi-user" in n.get("args", ())
                     for u in n["params"]["users"])


class _Console:
    """Bring-up output: every line to OUT/nodes.log; to the terminal only the supervisor's lines,
    warnings and errors (or everything with --verbose). Notes the users a multi-user node has
    finished (``finished``: (node label, user))."""

    def __init__(self, log_path: Path, verbose: bool) -> None:
        self._log = open(log_path, "w", encoding="utf-8")
        self.verbose = verbose
        self._lock = threading.Lock()
        self.finished: set[tuple[str, str]] = set()

    def write(self, text: str) -> int:
        with self._lock:
            self._log.write(text)
            for line in text.splitlines():
                done = _FINISHED.match(line)
                if done:
                    self.finished.add((done[1], done[2]))
                if self.verbose or line.startswith("[up]") or "ERROR" in line or "Traceback" in line \
                        or "WARN" in line:
                    sys.stdout.write("   " + line + "\n")
        return len(text)

    def flush(self) -> None:
        self._log.flush()
        sys.stdout.flush()

    def close(self) -> None:
        self._log.close()


def _supervise(bup, duration_s: float, rate: float, stop_event: threading.Event, state: dict,
               console: _Console | None = None, users: frozenset[tuple[str, str]] = frozenset()) -> None:
    """Progress while the player runs; when it has finished, let the multi-user nodes' ``users``
    leave (their inputs' publishers gone for ``user_timeout_s``, from the front ends to the
    estimators: each finishes its users, the particle filter smoothing their paths, without the stop's
    deadline; at most :data:`USERS_FINISH_WAIT_S`), then stop the nodes in dependency order (the
    bring-up's ``stop_order`` waves: the estimators from sources to sinks, so each one's final outputs
    reach the nodes after it, the recorder last)."""
    player = next(c for c in bup.children if c.spec.name == "player")
    t_start = time.monotonic()
    next_report = t_start + 10.0
    while not stop_event.is_set():
        if player.proc is None and player.starts > 0:
            break
        if time.monotonic() >= next_report:
            elapsed = time.monotonic() - t_start
            print(f"   ... {elapsed:.0f} s since start-up (the bag plays for {duration_s / rate:.0f} s once every "
                  f"node has subscribed)", flush=True)
            next_report += 10.0
        time.sleep(0.1)
    if stop_event.is_set() or bup._stop_requested is not None:
        return                          # interrupted (Ctrl-C) or a node died: the bring-up stops everything
    state["played"] = player.last_rc == 0
    time.sleep(1.5)          # let the last messages drain through the nodes
    if console is not None and users:
        print(f"   ... the bag has been played: waiting for the multi-user nodes to finish their users (each "
              f"leaves {USER_TIMEOUT_S:g} s after its inputs' publishers)", flush=True)
        until = time.monotonic() + USERS_FINISH_WAIT_S
        while not users <= console.finished and time.monotonic() < until and not stop_event.is_set() \
                and bup._stop_requested is None:
            time.sleep(0.2)
        if stop_event.is_set() or bup._stop_requested is not None:
            return
    bup.request_stop(signal.SIGINT)


def run_sim_demo(args: argparse.Namespace) -> int:
    from indoor_loc.supervisor import Bringup, parse_config

    if not args.rate > 0:
        raise ConfigError(f"--rate: expected > 0, got {args.rate}")
    t0 = time.perf_counter()
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    sim = _simulate(out, args)
    walkers = sim["walkers"]
    live = out / "live.mcap"
    for stale in (live, live.with_suffix(".mcap.partial")):
        if stale.exists():
            stale.unlink()
    from indoor_loc.dds_isolation import isolated_env
    dds_env, dds_said = isolated_env(os.environ)
    cfg_map = bringup_config(walkers, sim, out, rate=args.rate, foxglove=args.foxglove, dds_env=dds_env,
                             per_user=getattr(args, "per_user", False))
    (out / "bringup.yaml").write_text(
        f"# The demo's bring-up; `indoor-loc up {out / 'bringup.yaml'}` runs the same processes. The player\n"
        "# is not `required`: when the bag ends the nodes keep running until Ctrl-C (`indoor-loc demo` itself\n"
        "# stops them when the bag ends). Both stop them in waves of stop_order, by module: the player, then\n"
        "# imu_node, wifi_fix_node, pdr_kf_node and tll_pf, backend_node, the recorder last, so every node's\n"
        "# last outputs reach the nodes after it and are recorded.\n"
        + yaml.safe_dump(cfg_map, sort_keys=False))
    config = parse_config(cfg_map, out)
    names = [n["name"] for n in cfg_map["nodes"]]
    missing = [m for _, m in OPTIONAL_PER_WALKER + OPTIONAL_SHARED if not _module_exists(m)]
    print(f"== 2/4 live over DDS: {len(names)} processes ({', '.join(names)})\n   {dds_said}")
    if missing:
        print(f"   not in this build, so not started: {', '.join(missing)}")
    if args.foxglove is not None:
        from indoor_loc.foxglove_layout import write_layout
        layout = write_layout(out / "foxglove_layout.json", walkers)
        print(f"   live view: open Foxglove or Lichtblick -> Open connection -> Foxglove WebSocket -> "
              f"ws://localhost:{args.foxglove} (layout for these walkers: {layout})")
    console = _Console(out / "nodes.log", args.verbose)
    bup = Bringup(config, out=console, hint_ctrl_c=False)      # the demo stops the nodes itself
    stop_event = threading.Event()
    state = {"played": False}
    watcher = threading.Thread(target=_supervise, args=(bup, args.duration, args.rate, stop_event, state, console,
                                                        users_to_finish(cfg_map)), daemon=True)
    watcher.start()
    try:
        status = bup.run()
    finally:
        stop_event.set()
        watcher.join(timeout=5.0)
        console.close()
    if not state["played"] or not live.exists():
        print(f"indoor-loc demo: stopped before the bag was played; node logs in {out / 'nodes.log'}",
              file=sys.stderr)
        return 130 if status == 0 else status
    print(f"== 3/4 score each estimator per walker against the ground truth ({live})")
    rows, trajs = score_run(live, sim["dir"], walkers)
    print(format_scores(rows))
    from indoor_loc.demo_inputs import count_inputs, format_inputs
    print(format_inputs(count_inputs(live, sim["bag"], walkers)))
    print("== 4/4 plot")
    png = plot_run(out / "demo.png", sim["dir"], trajs, rows)
    print(f"   {png}")
    from indoor_loc.floors_plot import plot_floors      # walkers changing floors: floor over time (--floors 3)
    floors_png = plot_floors(out / "demo_floors.png", live, sim["dir"], walkers)
    if floors_png is not None:
        print(f"   {floors_png}")
    print(f"files: recording {live}; simulated input {sim['bag']}; radio map {sim['dir'] / 'radiomap'}; "
          f"building {sim['dir'] / 'building.geojson'}; node logs {out / 'nodes.log'}; "
          f"bring-up {out / 'bringup.yaml'}")
    print(f"done in {time.perf_counter() - t0:.0f} s" + ("" if status == 0 else
                                                        " (some node exited with an error: see nodes.log)"))
    return status


def layout_path() -> Path:
    from importlib import resources
    return Path(str(resources.files("indoor_loc") / "data" / "foxglove_layout.json"))


# ------------------------------------------------------------------------------------ scoring
@dataclasses.dataclass(frozen=True)
class ScoreRow:
    walker: str
    estimator: str
    topic: str
    n: int
    mean_m: float
    p95_m: float
    max_m: float
    route_m: float
    coverage: float


def score_run(bag: Path, sim_dir: Path, walkers: list[str]):
    """Per walker and estimator, ``indoor-loc eval``'s scores (one implementation:
    :func:`indoor_loc.commands.eval.evaluate`): the error of the estimate interpolated at the 5 Hz
    truth samples, held before its first and after its last pose (m), the share of those samples
    inside the estimate's span, and the distance to the walked route."""
    from indoor_loc.bag import bag_topics
    from indoor_loc.commands.eval import evaluate, trajectories_from_bags, truth_from_import

    truths = truth_from_import(sim_dir)
    topics = bag_topics([bag])
    rows, trajs = [], {}
    for label, rel in ESTIMATORS:
        per_user = {}
        if "{user}" in rel:
            for w in walkers:
                t = rel.format(user=w)
                if any(name.endswith("/" + t) for name in topics):
                    found = list(trajectories_from_bags([bag], t).values())
                    if found:
                        per_user[w] = found[-1]
        elif any(name.endswith("/" + rel) for name in topics):
            per_user = trajectories_from_bags([bag], rel)
        for w in walkers:
            tr = per_user.get(w)
            truth = truths.get(w)
            if tr is None or truth is None or len(tr) == 0:
                continue
            trajs[(w, rel)] = tr
            s = evaluate({w: tr}, {w: truth})[0][0]
            if s.scan_m.n == 0:
                continue
            rows.append(ScoreRow(w, label, rel, len(tr), s.scan_m.mean, s.scan_m.p95, s.scan_m.max, s.route_m.mean,
                                 1.0 - s.n_scans_outside / s.scan_m.n))
    return rows, trajs


def format_scores(rows: list[ScoreRow]) -> str:
    head = (f"{'walker':8s} {'estimator':30s} {'poses':>6s} | {'error at truth samples (m)':>26s} | "
            f"{'to route':>8s} {'covers':>6s}")
    sub = f"{'':8s} {'':30s} {'':>6s} | {'mean':>8s} {'p95':>8s} {'max':>8s} | {'mean m':>8s} {'':>6s}"
    lines = [head, sub, "-" * len(head)]
    for r in rows:
        lines.append(f"{r.walker:8s} {r.estimator:30s} {r.n:6d} | {r.mean_m:8.2f} {r.p95_m:8.2f} {r.max_m:8.2f} | "
                     f"{r.route_m:8.2f} {100 * r.coverage:5.0f}%")
    if not rows:
        lines.append("(no estimates were recorded: see nodes.log)")
    lines.append("error at truth samples: the estimate interpolated at the 5 Hz ground-truth stamps, held before its "
                 "first and after its last pose; covers: share of those stamps inside the estimate's span; to route: "
                 "poses within 10 m of the route (the same scores as `indoor-loc eval --truth OUT/sim`)")
    return "\n".join(lines)


def plot_run(png: Path, sim_dir: Path, trajs: dict, rows: list[ScoreRow]) -> Path:
    """One panel per walker: walls, graph, true path, the estimates."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from indoor_loc.commands.eval import truth_from_import
    from indoor_loc.sim.building import load_building

    b = load_building(sim_dir / "building.geojson")
    truths = truth_from_import(sim_dir)
    walkers = sorted({w for w, _ in trajs} | set(truths))
    x0, x1, y0, y1 = b.extent(1.0)
    fig, axes = plt.subplots(len(walkers), 1, figsize=(11, 5.2 * len(walkers)), dpi=100, squeeze=False)
    style = {"wifi/fix": dict(ls="", marker="o", ms=4, color="tab:orange", alpha=0.8),
             "pdr_kf/pose": dict(lw=0.8, color="tab:purple", alpha=0.6),
             "pdr_kf/path": dict(lw=1.8, color="tab:blue"),
             "pf/pose": dict(lw=0.8, color="tab:red", alpha=0.6),
             "pf/path": dict(lw=1.5, color="tab:red"),
             "backend/{user}/path": dict(lw=1.5, color="tab:green")}
    err = {(r.walker, r.topic): r.mean_m for r in rows}
    try:
        for ax, w in zip(axes[:, 0], walkers):
            for (a, c), f in zip(b.walls, b.wall_floor):
                ax.plot([a[0], c[0]], [a[1], c[1]], color="0.35" if f == 0 else "0.75", lw=1.6 if f == 0 else 0.8,
                        ls="-" if f == 0 else "--", zorder=0)
            for i, j in b.link_nodes:
                ax.plot(b.node_xyz[[i, j], 0], b.node_xyz[[i, j], 1], color="0.85", lw=0.6, zorder=0)
            truth = truths.get(w)
            if truth is not None:
                ax.plot(truth.scan_xy[:, 0], truth.scan_xy[:, 1], color="black", lw=2.2, alpha=0.55,
                        label="ground truth", zorder=1)
            for _, rel in ESTIMATORS:
                tr = trajs.get((w, rel))
                if tr is None:
                    continue
                e = err.get((w, rel))
                ax.plot(tr.xy[:, 0], tr.xy[:, 1], zorder=2, **style[rel],
                        label=f"{rel.format(user=w)} ({e:.2f} m)" if e is not None else rel.format(user=w))
            ax.set_xlim(x0, x1)
            ax.set_ylim(y0, y1)
            ax.set_aspect("equal")
            ax.set_title(f"/{w}: estimates vs ground truth (mean error at truth samples); "
                         f"walls: floor 0 solid, floor 1 dashed")
            ax.set_xlabel("x [m] (map, ENU)")
            ax.set_ylabel("y [m]")
            ax.legend(loc="upper left", fontsize=8, framealpha=0.85)
        fig.tight_layout()
        png.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(png)
    finally:
        plt.close(fig)
    return png


if __name__ == "__main__":      # python -m indoor_loc.demo (the same as indoor-loc demo)
    from indoor_loc.cli import main as _cli
    sys.exit(_cli(["demo", *sys.argv[1:]]))
