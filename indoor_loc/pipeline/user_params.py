"""Per-user parameter overrides of a multi-user node (``user_params``): one process serving users
that need different parameters, e.g. robots on their wheel odometry beside walkers on PDR.

``user_params`` maps a user name, or a glob pattern of names (``robot*``, ``floor2_?``), to parameter
overrides of the stage, nested as in a params file::

    /**/tll_pf:
      ros__parameters:
        user_params:
          robot1: {motion_source: odom}               # one user
          "robot*": {motion_source: odom, odom: {min_distance_m: 0.1}}   # every robot

or on the command line ``-p user_params.robot1.motion_source:=odom``. A user's parameters are the
node's, then every matching pattern's overrides (the shorter pattern first, then by name: a longer,
more specific pattern wins on a parameter both set), then its exact name's. They are resolved once,
when the user is first followed, and hold until it leaves. Any stage parameter may be overridden,
including those that change the stage's input or output topics (``motion_source``: ``odom`` instead
of ``pdr/odom``): the user is subscribed to its own stage's inputs. The multi-user parameters
themselves (``users``, ``shard_*`` …) may not. Every entry is checked at start-up (an unknown
parameter or a bad value fails the start, exit 2, naming the entry).

Each distinct set of overrides gets its own template stage (:class:`~indoor_loc.pipeline.multi_user.
MultiUserStage`), which loads what a stage shares between its users once more (``tll_pf``: the graph
and its transition table); users with the same overrides share it.
"""
from __future__ import annotations

import fnmatch
from collections.abc import Mapping
from typing import Any

from indoor_loc.errors import ConfigError
from indoor_loc.params import flatten, params_from_dict, params_to_dict

#: The parameter of a multi-user node holding the overrides.
USER_PARAMS = "user_params"
#: What marks a ``user_params`` key as a glob pattern rather than a user name.
GLOB_CHARS = "*?["


def is_pattern(key: str) -> bool:
    return any(c in key for c in GLOB_CHARS)


def matching_entries(user: str, user_params: Mapping[str, Any]) -> list[str]:
    """The keys of ``user_params`` applying to ``user``, in the order they are applied: matching
    patterns (shorter first, then by name), then the user's exact name."""
    name = user.strip("/")
    patterns = sorted((k for k in user_params if is_pattern(k) and fnmatch.fnmatchcase(name, k)),
                      key=lambda k: (len(k), k))
    return patterns + ([name] if name in user_params and not is_pattern(name) else [])


def overrides_for(user: str, user_params: Mapping[str, Any]) -> dict[str, Any]:
    """The user's overrides, flat (``{"odom.min_distance_m": 0.1}``); ``{}``: the node's parameters."""
    out: dict[str, Any] = {}
    for key in matching_entries(user, user_params):
        out.update(flatten(user_params[key]))
    return out


def overrides_key(overrides: Mapping[str, Any]) -> str:
    """A canonical text of a set of overrides (users with the same key share a template)."""
    return repr(sorted((k, repr(v)) for k, v in overrides.items()))


def check_entries(params: Any, forbidden: frozenset[str]) -> None:
    """Each entry of ``params.user_params`` is a non-empty mapping of the stage's parameters, none of
    them in ``forbidden`` (the multi-user ones); ConfigError naming the entry otherwise. Whether the
    values are valid is checked by :func:`with_overrides` (the caller builds every entry's stage)."""
    entries = getattr(params, USER_PARAMS, None) or {}
    if not isinstance(entries, Mapping):
        raise ConfigError(f"{USER_PARAMS}: expected a mapping user-or-pattern -> parameters, got {entries!r}")
    for key, value in entries.items():
        if not isinstance(value, Mapping) or not value:
            raise ConfigError(f"{USER_PARAMS}.{key}: expected a mapping of parameter overrides (e.g. "
                              f"{USER_PARAMS}.{key}.motion_source: odom), got {value!r}")
        bad = sorted(k for k in flatten(value) if k.split(".", 1)[0] in forbidden)
        if bad:
            raise ConfigError(f"{USER_PARAMS}.{key}: {bad} are the multi-user node's own parameters, the same for "
                              f"every user; only the stage's parameters can be overridden per user")


def with_overrides(params: Any, overrides: Mapping[str, Any], where: str) -> Any:
    """``params`` with ``overrides`` (flat) applied, checked as a params file's values are
    (ConfigError naming ``where``)."""
    if not overrides:
        return params
    values = flatten(params_to_dict(params))
    # free-form mappings (user_params itself) are kept whole, not merged key by key
    values = {k: v for k, v in values.items() if not k.startswith(USER_PARAMS + ".")}
    values[USER_PARAMS] = {}
    values.update(overrides)
    try:
        return params_from_dict(type(params), values)
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from err


def describe(overrides: Mapping[str, Any]) -> str:
    """``motion_source=odom, odom.min_distance_m=0.1`` (a user's status shows its overrides)."""
    return ", ".join(f"{k}={v}" for k, v in sorted(overrides.items()))
