"""One exception hierarchy for the package (messages built first, chained with ``from err``)."""
from __future__ import annotations


class IndoorLocError(Exception):
    """Base class of every error the package raises on purpose."""


class ConfigError(IndoorLocError, ValueError):
    """Invalid parameters or configuration (unknown key, out-of-range value)."""


class InvalidInputError(IndoorLocError, ValueError):
    """Input to a core function that breaks its documented contract (array shape, a non-finite
    value, time going backwards). ``reason`` is a short stable slug a stage counts in diagnostics
    (e.g. ``"shape"``, ``"nan"``, ``"non_monotonic_stamp"``); ``detail`` says what was expected and got."""

    def __init__(self, reason: str, detail: str = "") -> None:
        self.reason = reason
        self.detail = detail
        super().__init__(f"{reason}: {detail}" if detail else reason)


class InvalidMessageError(InvalidInputError):
    """A message that violates the message contract (raised by ``msg_adapters``). ``reason`` is a
    short stable slug counted in diagnostics (e.g. ``"nan"``, ``"schema_version"``, ``"rssi_range"``)."""


class EvalError(InvalidInputError):
    """Inputs to a metric with the wrong shape, non-finite values or nothing to score."""

    def __init__(self, detail: str, reason: str = "eval_input") -> None:
        super().__init__(reason, detail)

    def __str__(self) -> str:
        return self.detail


class ScanCommandError(IndoorLocError):
    """A WiFi scan command (``iw``, ``nmcli``) that could not run or failed. ``reason`` is a short
    stable slug counted in diagnostics; ``hint`` says what to do about it."""

    def __init__(self, reason: str, message: str, hint: str = "") -> None:
        self.reason = reason
        self.message = message
        self.hint = hint
        super().__init__(f"{message}; {hint}" if hint else message)


class MapError(IndoorLocError):
    """A radio map or building graph that cannot be read or used."""


class BagError(IndoorLocError):
    """An MCAP bag that cannot be read or written."""


class DatasetError(IndoorLocError):
    """A dataset directory that does not look like what the importer expects."""


class ParseError(IndoorLocError, ValueError):
    """Text (command output, JSON) that cannot be parsed into a scan."""


class ToolchainError(IndoorLocError):
    """A build step (tf2_msgs, indoor_loc/tools/build_tf2_msgs.py) lacks its compiler, headers or generators."""
