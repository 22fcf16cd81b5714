"""Process supervisor (no ROS in it): start a set of nodes from a bring-up YAML, like a launch file;
``indoor-loc up CONFIG.yaml`` is its command line (:mod:`indoor_loc.commands.up`).

Each node runs as a child process::

    <program> [args...] --ros-args -r __ns:=NS [-r FROM:=TO ...] [-p use_sim_time:=true]
              [--params-file F ...] [-p NAME:=VALUE ...] [ros_args...]

with its output (stdout and stderr) prefixed by ``[name]``. SIGINT/SIGTERM stop the children in
waves of ascending ``stop_order`` (the player, then the estimators from sources to sinks, the
recorder last; each wave once the one before has exited), each child with SIGINT first — SIGTERM to
a child that has printed nothing yet, so one still starting ends without a traceback; SIGTERM after
``stop_timeout_s``, SIGKILL after as long again; a second signal stops every wave at once. The
bring-up ends when every child has exited, or when one dies (exits non-zero, or exits at all with
``required: true``) and has no ``respawn``: then the others are stopped too. Exit status: 0 when
every child ended cleanly, 1 otherwise. ``config/bringup_example.yaml`` documents every key.
"""
from __future__ import annotations

import importlib.util
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, TextIO

import yaml

from indoor_loc.errors import ConfigError
from indoor_loc.params import load_params_file

PREFIX = "up"
_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")
_NS_RE = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)*$")
_ENV_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_TOP_KEYS = {"env", "use_sim_time", "params_files", "stop_timeout_s", "nodes"}
_NODE_KEYS = {"name", "executable", "module", "script", "namespace", "args", "params_files", "params",
              "remap", "ros_args", "env", "use_sim_time", "respawn", "respawn_delay_s", "required", "stop_order"}
#: Default ``stop_order`` of the package's executables (given as ``executable:`` or as their
#: ``module:``): data sources stop first, then the front ends, then the estimators from sources to
#: sinks (their end-of-input outputs, e.g. pdr_kf's final smoothed path, still reach the nodes after
#: them), the recorder and the live view last so they hold all of it. Other nodes: 1.
STOP_ORDER = {"player": 0, "wifi_scan_node": 1, "imu_node": 1, "wifi_fix_node": 2, "pdr_kf_node": 3,
              "tll_pf": 3, "backend_node": 4, "recorder": 9, "view": 9, "indoor_loc_view": 9, "indoor_loc_map": 9}
#: Exit statuses of a child that was asked to stop and did so (0, or killed by the signal sent).
_CLEAN_STOP = {0, -signal.SIGINT, -signal.SIGTERM, 128 + signal.SIGINT, 128 + signal.SIGTERM}
#: A child stopped within this many seconds of its start may not have installed its signal
#: handlers yet (Python then exits 1 with a KeyboardInterrupt traceback): not counted as a failure.
STARTUP_GRACE_S = 2.0
# Runs a console-script target "module:function" with argv[0] = the executable's name.
_STUB = ("import importlib, sys; mod, fn = sys.argv[1].split(':'); sys.argv = sys.argv[2:]; "
         "sys.exit(getattr(importlib.import_module(mod), fn)())")


@dataclass(frozen=True)
class NodeSpec:
    """One child process of the bring-up (see ``config/bringup_example.yaml``)."""
    name: str
    program: tuple[str, ...]          # the command before the node's own args
    namespace: str = ""
    args: tuple[str, ...] = ()
    params_files: tuple[Path, ...] = ()
    params: dict[str, Any] = field(default_factory=dict)
    remap: dict[str, str] = field(default_factory=dict)
    ros_args: tuple[str, ...] = ()
    env: dict[str, str] = field(default_factory=dict)
    use_sim_time: bool | None = None
    respawn: bool = False
    respawn_delay_s: float = 1.0
    required: bool = False
    stop_order: int = 1               # stopping goes by ascending stop_order, one wave at a time

    def command(self) -> list[str]:
        ros = ["--ros-args"]
        if self.namespace:
            ros += ["-r", f"__ns:={self.namespace}"]
        for src, dst in self.remap.items():
            ros += ["-r", f"{src}:={dst}"]
        if self.use_sim_time is not None:
            ros += ["-p", f"use_sim_time:={'true' if self.use_sim_time else 'false'}"]
        for f in self.params_files:
            ros += ["--params-file", str(f)]
        for key, value in self.params.items():
            ros += ["-p", f"{key}:={param_text(value)}"]
        return [*self.program, *self.args, *ros, *self.ros_args]

    def display(self) -> str:
        """The command line as a person would type it (a console script by its name)."""
        cmd = self.command()
        if cmd[1:2] == ["-c"]:              # (python, -c, stub, target, name, ...)
            cmd = cmd[4:]
        return shlex.join(cmd)


@dataclass(frozen=True)
class BringupConfig:
    nodes: tuple[NodeSpec, ...]
    env: dict[str, str] = field(default_factory=dict)
    stop_timeout_s: float = 10.0
    source: Path | None = None


def param_text(value: Any) -> str:
    """A parameter value as rcl reads ``-p name:=VALUE`` (YAML flow style: '0.5' stays a string)."""
    text = yaml.safe_dump(value, default_flow_style=True, width=1 << 20).strip()
    return text[:-4].strip() if text.endswith("\n...") else text.removesuffix("...").strip()


def package_executables() -> dict[str, str]:
    """``{console script name: "module:function"}`` of this package's node executables."""
    out = {}
    for ep in entry_points(group="console_scripts"):
        if ep.value.startswith("indoor_loc.") and ep.name != "indoor-loc":
            out[ep.name] = ep.value
    installed = set(out.values())
    nodes_dir = Path(__file__).resolve().parent / "nodes"
    for p in nodes_dir.glob("*_node.py"):           # also nodes not (yet) installed as scripts
        name = p.stem
        if f"indoor_loc.nodes.{name}:main" in installed:
            continue
        out.setdefault(name.removesuffix("_node") if name in ("player_node", "recorder_node") else name,
                       f"indoor_loc.nodes.{name}:main")
    return out


# ------------------------------------------------------------------------------------- config
def _where(i: int | None, key: str) -> str:
    return f"bringup.{key}" if i is None else f"bringup.nodes[{i}].{key}"


def _expect(cond: bool, where: str, expected: str, got: Any) -> None:
    if not cond:
        raise ConfigError(f"{where}: expected {expected}, got {got!r}")


def _str_list(value: Any, where: str) -> tuple[str, ...]:
    if value is None:
        return ()
    if isinstance(value, str):
        value = [value]
    _expect(isinstance(value, list) and all(isinstance(v, (str, int, float)) and not isinstance(v, bool)
                                            for v in value), where, "a list of strings", value)
    return tuple(str(v) for v in value)


def _env(value: Any, where: str) -> dict[str, str]:
    if value is None:
        return {}
    _expect(isinstance(value, dict), where, "a mapping NAME: value", value)
    out = {}
    for k, v in value.items():
        _expect(isinstance(k, str) and bool(_ENV_RE.match(k)), f"{where}", "environment variable names", k)
        _expect(isinstance(v, (str, int, float, bool)), f"{where}.{k}", "a string or number", v)
        out[k] = ("true" if v else "false") if isinstance(v, bool) else str(v)
    if "ROS_DOMAIN_ID" in out:
        d = out["ROS_DOMAIN_ID"]
        _expect(d.isdigit() and 0 <= int(d) <= 232, f"{where}.ROS_DOMAIN_ID", "an integer in [0, 232]", d)
    return out


def _files(value: Any, where: str, base: Path) -> tuple[Path, ...]:
    out = []
    for f in _str_list(value, where):
        p = Path(os.path.expandvars(os.path.expanduser(f)))
        p = p if p.is_absolute() else (base / p)
        if not p.is_file():
            raise ConfigError(f"{where}: params file {p} does not exist")
        load_params_file(p)      # ConfigError for a file rcl would refuse
        out.append(p.resolve())
    return tuple(out)


def _bool(value: Any, where: str, default: bool | None) -> bool | None:
    if value is None:
        return default
    _expect(isinstance(value, bool), where, "true or false", value)
    return value


def _program(i: int, node: dict, base: Path, exes: dict[str, str]) -> tuple[str, ...]:
    given = [k for k in ("executable", "module", "script") if node.get(k) is not None]
    _expect(len(given) == 1, _where(i, "executable"), "exactly one of executable / module / script", given)
    kind = given[0]
    value = node[kind]
    _expect(isinstance(value, str) and value != "", _where(i, kind), "a non-empty string", value)
    if kind == "executable":
        if value not in exes:
            raise ConfigError(f"{_where(i, 'executable')}: unknown executable {value!r}; expected one of "
                              f"{sorted(exes)} (or use module: / script:)")
        script = Path(sys.executable).parent / value     # installed beside this interpreter (pip/venv)
        if script.is_file() and os.access(script, os.X_OK):
            return (str(script),)
        return (sys.executable, "-c", _STUB, exes[value], value)
    if kind == "module":
        if importlib.util.find_spec(value.split(".")[0]) is None:
            raise ConfigError(f"{_where(i, 'module')}: cannot import {value!r}")
        return (sys.executable, "-m", value)
    path = Path(os.path.expanduser(value))
    path = path if path.is_absolute() else base / path
    if not path.is_file():
        raise ConfigError(f"{_where(i, 'script')}: {path} does not exist")
    return (sys.executable, str(path.resolve()))


def _stop_order(i: int, node: dict, exes: dict[str, str]) -> int:
    value = node.get("stop_order")
    if value is None:
        names = [str(node.get("executable"))]
        if node.get("module") is not None:      # a package node run as python -m: its executables' names
            names = [exe for exe, target in exes.items() if target.split(":")[0] == node["module"]]
        # (a node module found beside the package but not installed is named after its file: tll_pf_node)
        return next((STOP_ORDER[n] for name in names for n in (name, name.removesuffix("_node")) if n in STOP_ORDER), 1)
    _expect(isinstance(value, int) and not isinstance(value, bool), _where(i, "stop_order"), "an integer", value)
    return int(value)


def parse_config(data: Any, base: Path, source: Path | None = None) -> BringupConfig:
    """Validate a bring-up mapping (see ``config/bringup_example.yaml``); relative paths are taken
    from ``base`` (the config file's directory). Raises ConfigError naming the bad key."""
    _expect(isinstance(data, dict), "bringup", "a mapping with a 'nodes' list", type(data).__name__)
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise ConfigError(f"bringup: unknown key(s) {unknown}; expected some of {sorted(_TOP_KEYS)}")
    env = _env(data.get("env"), "bringup.env")
    sim = _bool(data.get("use_sim_time"), "bringup.use_sim_time", None)
    common_files = _files(data.get("params_files"), "bringup.params_files", base)
    stop = data.get("stop_timeout_s", 10.0)
    _expect(isinstance(stop, (int, float)) and not isinstance(stop, bool) and stop > 0,
            "bringup.stop_timeout_s", "a number > 0 (s)", stop)
    nodes_in = data.get("nodes")
    _expect(isinstance(nodes_in, list) and len(nodes_in) > 0, "bringup.nodes", "a non-empty list of nodes", nodes_in)
    exes = package_executables()
    nodes: list[NodeSpec] = []
    names: set[str] = set()
    for i, n in enumerate(nodes_in):
        _expect(isinstance(n, dict), f"bringup.nodes[{i}]", "a mapping", n)
        unknown = sorted(set(n) - _NODE_KEYS)
        if unknown:
            raise ConfigError(f"bringup.nodes[{i}]: unknown key(s) {unknown}; expected some of {sorted(_NODE_KEYS)}")
        name = n.get("name")
        _expect(isinstance(name, str) and bool(_NAME_RE.match(name)), _where(i, "name"),
                "a label of letters, digits, '_', '.', '-'", name)
        if name in names:
            raise ConfigError(f"{_where(i, 'name')}: duplicate node name {name!r}")
        names.add(name)
        ns = n.get("namespace", "")
        _expect(isinstance(ns, str) and (ns == "" or (ns.startswith("/") and bool(_NS_RE.match(ns.rstrip("/"))))),
                _where(i, "namespace"),
                "'' or an absolute namespace like /alice", ns)
        params = n.get("params") or {}
        _expect(isinstance(params, dict), _where(i, "params"), "a mapping NAME: value", params)
        for k, v in params.items():
            _expect(isinstance(k, str) and bool(re.match(r"^[A-Za-z_][A-Za-z0-9_.]*$", k)), _where(i, "params"),
                    "parameter names", k)
            _expect(v is not None and not isinstance(v, dict), _where(i, f"params.{k}"),
                    "a scalar or a list", v)
        remap = n.get("remap") or {}
        _expect(isinstance(remap, dict) and all(isinstance(k, str) and isinstance(v, str) and k and v
                                                for k, v in remap.items()),
                _where(i, "remap"), "a mapping FROM: TO of topic names", remap)
        delay = n.get("respawn_delay_s", 1.0)
        _expect(isinstance(delay, (int, float)) and not isinstance(delay, bool) and delay >= 0,
                _where(i, "respawn_delay_s"), "a number >= 0 (s)", delay)
        nodes.append(NodeSpec(
            name=name, program=_program(i, n, base, exes), namespace=ns.rstrip("/"),
            args=_str_list(n.get("args"), _where(i, "args")),
            params_files=common_files + _files(n.get("params_files"), _where(i, "params_files"), base),
            params=dict(params), remap=dict(remap), ros_args=_str_list(n.get("ros_args"), _where(i, "ros_args")),
            env=_env(n.get("env"), _where(i, "env")),
            use_sim_time=_bool(n.get("use_sim_time"), _where(i, "use_sim_time"), sim),
            respawn=bool(_bool(n.get("respawn"), _where(i, "respawn"), False)),
            respawn_delay_s=float(delay),
            required=bool(_bool(n.get("required"), _where(i, "required"), False)),
            stop_order=_stop_order(i, n, exes)))
    return BringupConfig(nodes=tuple(nodes), env=env, stop_timeout_s=float(stop), source=source)


def load_config(path: str | Path) -> BringupConfig:
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"cannot read bring-up file {path}: {err}") from err
    return parse_config(data, path.resolve().parent, path)


# ------------------------------------------------------------------------------------ running
class _Child:
    def __init__(self, spec: NodeSpec) -> None:
        self.spec = spec
        self.proc: subprocess.Popen | None = None
        self.reader: threading.Thread | None = None
        self.starts = 0
        self.started_at = 0.0
        self.signalled = False
        self.spoke = False          # printed a line since its start (our nodes: signal handlers are in place)
        self.restart_at: float | None = None
        self.last_rc: int | None = None


class Bringup:
    """Runs the children of a :class:`BringupConfig` (``run()`` blocks until they are all done)."""

    def __init__(self, config: BringupConfig, *, out: TextIO | None = None, hint_ctrl_c: bool = True) -> None:
        self.config = config
        self.out = out or sys.stdout
        self.hint_ctrl_c = hint_ctrl_c     # say that Ctrl-C stops the rest when a node ends (not when a caller will)
        self.children = [_Child(s) for s in config.nodes]
        self._lock = threading.Lock()
        self._stop_requested: int | None = None     # signal number once asked to stop
        self._failed = False

    def log(self, name: str, line: str) -> None:
        with self._lock:
            self.out.write(f"[{name}] {line}\n")
            self.out.flush()

    def _env(self, spec: NodeSpec) -> dict[str, str]:
        env = dict(os.environ)
        env.update(self.config.env)
        env.update(spec.env)
        env["PYTHONUNBUFFERED"] = "1"
        return env

    def _start(self, child: _Child) -> None:
        cmd = child.spec.command()
        try:
            child.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                          stdin=subprocess.DEVNULL, env=self._env(child.spec), text=True,
                                          bufsize=1, errors="replace", process_group=0)
        except OSError as err:       # not executable, vanished...: like a node that died at once
            self.log(PREFIX, f"cannot start {child.spec.name}: {err}")
            child.restart_at = None
            self._failed = True
            self.request_stop(signal.SIGINT)
            return
        child.starts += 1
        child.started_at = time.monotonic()
        child.restart_at = None
        child.signalled = False
        self.log(PREFIX, f"started {child.spec.name} (pid {child.proc.pid}): {child.spec.display()}")
        child.spoke = False
        child.reader = threading.Thread(target=self._pump, args=(child, child.proc), daemon=True)
        child.reader.start()

    def _pump(self, child: _Child, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            child.spoke = True
            self.log(child.spec.name, line.rstrip("\n"))

    def request_stop(self, signum: int = signal.SIGINT) -> None:
        """Ask every child to stop (safe from a signal handler: the loop sends the signals).
        Asked again while stopping (a second Ctrl-C): escalate to SIGTERM/SIGKILL at once."""
        if self._stop_requested is not None:
            self._stop_deadline = time.monotonic()
            self._hurry = True                     # every wave at once
            self._hurry_said = self._term_sent = False
            return
        self._wave: int | None = None
        self._hurry = False
        self._stop_requested = signum
        self._stop_at = time.monotonic()
        self._stop_deadline = self._stop_at + self.config.stop_timeout_s
        self._term_sent = False
        self._kill_sent = False

    def _escalate(self) -> None:
        """Stop in waves of ascending ``stop_order``: SIGINT the lowest wave still running, and the
        next only once it has exited (so the end-of-input outputs of producers and estimators reach
        the nodes after them, the recorder last); SIGTERM / SIGKILL escalate per wave."""
        now = time.monotonic()
        running = [c for c in self.children if c.proc is not None and c.proc.poll() is None]
        for c in self.children:
            c.restart_at = None
        if not running:
            return
        wave = min(c.spec.stop_order for c in running)
        alive = [c for c in running if c.spec.stop_order == wave or self._hurry]
        if self._hurry and not self._hurry_said:
            self._hurry_said = True
            self.log(PREFIX, f"asked again: stopping {', '.join(c.spec.name for c in alive)} at once (SIGTERM)")
        if wave != self._wave:                     # a new wave: its own timeouts
            self._wave = wave
            self.log(PREFIX, f"stopping {', '.join(c.spec.name for c in alive)}"
                             + ("" if self._hurry else f" (stop_order {wave})"))
            self._stop_deadline = now + self.config.stop_timeout_s
            self._term_sent = self._kill_sent = False
        for c in alive:
            if not c.signalled:
                c.signalled = True
                # A child that has printed nothing yet is still starting (importing, before its
                # handlers exist): SIGINT would end it with a KeyboardInterrupt traceback, SIGTERM
                # ends it quietly. Our nodes handle both alike once running.
                c.proc.send_signal(signal.SIGINT if c.spoke else signal.SIGTERM)
        if not self._term_sent and now > self._stop_deadline:
            self._term_sent = True
            self._stop_deadline = now + self.config.stop_timeout_s
            for c in alive:
                if not self._hurry:
                    self.log(PREFIX, f"{c.spec.name} still running {self.config.stop_timeout_s:g} s after SIGINT: SIGTERM")
                c.proc.terminate()
        elif self._term_sent and not self._kill_sent and now > self._stop_deadline:
            self._kill_sent = True
            for c in alive:
                self.log(PREFIX, f"{c.spec.name} ignored SIGTERM: SIGKILL")
                c.proc.kill()

    def _reap(self, child: _Child) -> None:
        assert child.proc is not None
        rc = child.proc.returncode
        if child.reader is not None:
            child.reader.join(timeout=2.0)
        child.last_rc = rc
        child.proc = None
        spec = child.spec
        if self._stop_requested is not None:
            starting = self._stop_at - child.started_at < STARTUP_GRACE_S
            clean = rc in _CLEAN_STOP or (starting and rc > 0)
            self.log(PREFIX, f"{spec.name} stopped (exit status {rc}"
                             f"{', interrupted while starting' if starting and rc not in _CLEAN_STOP else ''})")
            self._failed |= not clean
            return
        self.log(PREFIX, f"{spec.name} exited with status {rc}")
        if spec.respawn:
            child.restart_at = time.monotonic() + spec.respawn_delay_s
            self.log(PREFIX, f"respawning {spec.name} in {spec.respawn_delay_s:g} s")
        elif rc != 0 or spec.required:
            self._failed |= rc != 0
            why = "died" if rc != 0 else "is required and exited"
            self.log(PREFIX, f"{spec.name} {why}: stopping the others")
            self.request_stop(signal.SIGINT)
        elif self.hint_ctrl_c and any(c.proc is not None and c.proc.poll() is None for c in self.children):
            self.log(PREFIX, f"the other nodes keep running: Ctrl-C stops them ({spec.name} is not `required`)")

    def run(self, poll_s: float = 0.05) -> int:
        """Start every child, supervise until all are done; 0 when all ended cleanly, else 1."""
        handlers = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                handlers[sig] = signal.signal(sig, lambda s, f: self.request_stop(s))
        try:
            for c in self.children:
                if self._stop_requested is None:
                    self._start(c)
            while True:
                for c in self.children:
                    if c.proc is not None and c.proc.poll() is not None:
                        self._reap(c)
                    elif (c.proc is None and c.restart_at is not None and self._stop_requested is None
                          and time.monotonic() >= c.restart_at):
                        self._start(c)
                if self._stop_requested is not None:
                    self._escalate()
                if all(c.proc is None and c.restart_at is None for c in self.children):
                    break
                time.sleep(poll_s)
        finally:
            for sig, h in handlers.items():
                signal.signal(sig, h)
            for c in self.children:      # never leave a child behind (e.g. on an internal error)
                if c.proc is not None and c.proc.poll() is None:
                    c.proc.kill()
                    c.proc.wait()
        status = 1 if self._failed else 0
        took = "" if self._stop_requested is None else f" in {time.monotonic() - self._stop_at:.1f} s"
        self.log(PREFIX, f"all nodes stopped{took}" + ("" if status == 0 else " (some exited with an error)"))
        return status
