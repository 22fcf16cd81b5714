"""Scan the machine's own wireless interface by running ``iw`` or ``nmcli`` (no ROS).

:class:`InterfaceScanner` runs one scan command with a timeout in a subprocess and parses its
output; :meth:`InterfaceScanner.scan` never raises — failures come back in the
:class:`ScanAttempt` as a :class:`ScanCommandError` with a stable ``reason`` and a hint:

- ``not_found``: the program is not installed (``apt install iw`` / ``network-manager``);
- ``permission``: ``iw dev IF scan`` triggers a scan, which needs ``CAP_NET_ADMIN``; the scanner
  then falls back (``dump_fallback``) to ``iw dev IF scan dump`` — the kernel's cached results of
  the last scan anyone ran (NetworkManager/wpa_supplicant scan periodically), readable without
  privileges; stale entries carry their ``last seen`` age. Otherwise run as root, grant the
  capability (``sudo setcap cap_net_admin+ep $(command -v iw)``) or use ``source: nmcli``;
- ``no_device``, ``down``, ``busy`` (a scan is already running; the next period retries),
  ``timeout`` (the command was killed; any complete entries it printed are still used),
  ``failed`` (any other non-zero exit), ``parse`` (output that is not the expected format).

The command runs in a new session so that a timeout kills it with every child it started, and
with ``LC_ALL=C.UTF-8`` so its messages are untranslated (the parsers accept localised output
anyway).
"""
from __future__ import annotations

import os
import shlex
import signal
import subprocess
import time
from dataclasses import dataclass
from typing import Callable

from indoor_loc.errors import ParseError, ScanCommandError
from indoor_loc.wifi.parsers import NMCLI_FIELDS, ParseResult, parse_iw, parse_nmcli

TOOLS = ("iw", "nmcli")


@dataclass(frozen=True)
class ScanAttempt:
    """One run of the scan command: ``result`` when it produced a scan, else ``error``.

    ``stamp_ns``: when the command returned (the scan time); ``command``: the argv that ran;
    ``duration_s``: its wall time; ``fallback``: True when ``iw ... scan dump`` was used.
    """
    stamp_ns: int
    tool: str
    command: tuple[str, ...]
    duration_s: float
    result: ParseResult | None = None
    error: ScanCommandError | None = None
    fallback: bool = False


def default_command(tool: str, interface: str) -> list[str]:
    """The command the package runs for ``tool`` on ``interface``."""
    if tool == "iw":
        return ["iw", "dev", interface, "scan"]
    if tool == "nmcli":
        return ["nmcli", "-t", "-f", ",".join(NMCLI_FIELDS), "dev", "wifi", "list", "ifname", interface,
                "--rescan", "auto"]
    raise ScanCommandError("bad_tool", f"unknown scan tool {tool!r}", f"expected one of {TOOLS}")


def build_command(tool: str, interface: str, override: str = "") -> list[str]:
    """``override`` (a shell-like string, ``{interface}`` replaced) or :func:`default_command`."""
    if override.strip():
        try:
            return shlex.split(override.replace("{interface}", interface))
        except ValueError as err:
            raise ScanCommandError("bad_command", f"cannot split command {override!r}: {err}") from err
    return default_command(tool, interface)


def _classify(argv: list[str], returncode: int, stderr: str) -> ScanCommandError:
    msg = stderr.strip().splitlines()[-1] if stderr.strip() else f"exit status {returncode}"
    low = stderr.lower()
    head = f"`{' '.join(argv)}` failed: {msg}"
    if "operation not permitted" in low or "permission denied" in low or "not authorized" in low \
            or "insufficient privileges" in low:
        return ScanCommandError("permission", head,
                                "triggering a scan needs CAP_NET_ADMIN: use `iw dev IF scan dump` (cached "
                                "results, no privileges), run as root, `sudo setcap cap_net_admin+ep "
                                "$(command -v iw)`, or source nmcli")
    if "no such device" in low or ("not found" in low and "device" in low):
        return ScanCommandError("no_device", head, "is it the wireless interface? see `iw dev`")
    if "network is down" in low:
        return ScanCommandError("down", head, "bring the interface up: `sudo ip link set IF up`")
    if "resource busy" in low:
        return ScanCommandError("busy", head, "another scan is running; the next period retries")
    return ScanCommandError("failed", head)


def run_command(argv: list[str], *, timeout_s: float) -> tuple[str, bool]:
    """Run ``argv``; return (stdout text, timed_out). Raises ScanCommandError when it cannot start or
    exits non-zero. On timeout the whole process group is killed and what it printed is returned."""
    env = dict(os.environ, LC_ALL="C.UTF-8")
    try:
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                                env=env, start_new_session=True)
    except FileNotFoundError as err:
        raise ScanCommandError("not_found", f"{argv[0]}: command not found",
                               "install it (apt install iw / network-manager) or set the command") from err
    except PermissionError as err:
        raise ScanCommandError("permission", f"{argv[0]}: not executable: {err}") from err
    except OSError as err:
        raise ScanCommandError("failed", f"{argv[0]}: cannot start: {err}") from err
    timed_out = False
    try:
        out, err_b = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        timed_out = True
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        out, err_b = proc.communicate()
    text = out.decode("utf-8", errors="replace")
    if not timed_out and proc.returncode != 0:
        raise _classify(argv, proc.returncode, err_b.decode("utf-8", errors="replace"))
    return text, timed_out


class InterfaceScanner:
    """Runs and parses one tool's scan command; keeps the ``scan dump`` fallback once it was needed.

    ``command``: argv override (else :func:`default_command`). Not thread-safe: use it from one
    thread (the node's scan thread).
    """

    def __init__(self, tool: str, interface: str, *, command: list[str] | None = None, timeout_s: float = 10.0,
                 dump_fallback: bool = True, signal_mapping: str = "nm") -> None:
        if tool not in TOOLS:
            raise ScanCommandError("bad_tool", f"unknown scan tool {tool!r}", f"expected one of {TOOLS}")
        self.tool = tool
        self.interface = interface
        self.command = list(command) if command else default_command(tool, interface)
        self.timeout_s = float(timeout_s)
        self.dump_fallback = dump_fallback and tool == "iw"
        self.signal_mapping = signal_mapping
        self.using_dump = False
        self.fallback_reason = ""

    @property
    def dump_command(self) -> list[str]:
        """``iw dev IF scan dump``: the scan command with ``dump`` appended."""
        return self.command + ["dump"]

    def active_command(self) -> list[str]:
        return self.dump_command if self.using_dump else self.command

    def scan(self, clock_ns: Callable[[], int] = time.time_ns) -> ScanAttempt:
        """Run the command once (blocking, at most ``timeout_s``, twice that on the first fallback)."""
        t0 = time.perf_counter()
        argv = self.active_command()
        try:
            text, timed_out = run_command(argv, timeout_s=self.timeout_s)
        except ScanCommandError as err:
            if err.reason == "permission" and self.dump_fallback and not self.using_dump:
                self.using_dump = True
                self.fallback_reason = str(err)
                return self.scan(clock_ns)
            return ScanAttempt(clock_ns(), self.tool, tuple(argv), time.perf_counter() - t0, error=err,
                               fallback=self.using_dump)
        stamp = clock_ns()
        source = f"{self.tool}-dump" if self.using_dump else self.tool
        try:
            if self.tool == "iw":
                result = parse_iw(text, stamp_ns=stamp, source=source, signal_mapping=self.signal_mapping)
            else:
                result = parse_nmcli(text, stamp_ns=stamp, source=source, signal_mapping=self.signal_mapping)
        except ParseError as err:
            reason = "timeout" if timed_out else "parse"
            return ScanAttempt(stamp, self.tool, tuple(argv), time.perf_counter() - t0,
                               error=ScanCommandError(reason, str(err)), fallback=self.using_dump)
        if timed_out and len(result.scan) == 0:
            return ScanAttempt(stamp, self.tool, tuple(argv), time.perf_counter() - t0,
                               error=ScanCommandError("timeout", f"{' '.join(argv)}: no result within "
                                                                 f"{self.timeout_s:g} s"),
                               fallback=self.using_dump)
        if timed_out:
            result = ParseResult(result.scan, True, result.skipped,
                                 result.warnings + (f"killed after {self.timeout_s:g} s",))
        return ScanAttempt(stamp, self.tool, tuple(argv), time.perf_counter() - t0, result=result,
                           fallback=self.using_dump)
