"""Safety flags: problems observed now, keyed by source, cheap for the control loop to poll."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from enum import IntEnum

_changes = itertools.count(1)  # next() on it is one C call, so two threads never draw the same number


class Level(IntEnum):
    """How bad a flag is, on the scale of ROS 2's diagnostic_msgs/DiagnosticStatus."""

    WARN = 1  # the stack copes by design (a clamped command, a stale remote stream, a stray frame)
    ERROR = 2  # a device or the control cannot do what was asked (a drive fault, a lost slave, gains not applied)


class SafetyFlags:
    """Problems observed now, keyed by source; ``flags_version`` grows on every change (cheap to poll).

    ``SafetyFlags.last_change`` is a number never used before, written after every change of any source's
    flags: a poller that saw it unchanged since its last look knows that no source has changed, without
    asking each one."""

    last_change = 0

    def __init__(self, name: str) -> None:
        self.name = name
        self.flags: dict[str, str] = {}
        self.levels: dict[str, Level] = {}
        self.flags_version = 0

    def set_flag(self, key: str, text: str, level: Level = Level.ERROR) -> None:
        if self.flags.get(key) != text or self.levels.get(key) is not level:
            self.flags[key] = text
            self.levels[key] = level
            self.flags_version += 1
            SafetyFlags.last_change = next(_changes)

    def clear_flag(self, key: str) -> None:
        if key in self.flags:
            del self.flags[key]
            self.levels.pop(key, None)
            self.flags_version += 1
            SafetyFlags.last_change = next(_changes)


class FlagSources:
    """The sources of one status, in order: ``changed`` merges their flags, each key prefixed by its source's name,
    when any source's flags have changed since the last look (cheap when none has: one comparison)."""

    def __init__(self, sources: Sequence[SafetyFlags]) -> None:
        self.sources = tuple(sources)
        self._version_seen = -1
        self._change_seen = -1

    @property
    def names(self) -> list[str]:
        return [source.name for source in self.sources]

    def add(self, source: SafetyFlags) -> None:
        """``source`` joins; the next look merges again."""
        self.sources = (*self.sources, source)
        self._version_seen = -1
        self._change_seen = -1

    def changed(self) -> tuple[dict[str, str], dict[str, Level]] | None:
        """Every source's flags and their levels, merged; None when nothing has changed since the last look."""
        change = SafetyFlags.last_change
        if change == self._change_seen:
            return None  # no source anywhere has changed its flags since the last look
        self._change_seen = change
        version = 0
        for source in self.sources:
            version += source.flags_version
        if version == self._version_seen:
            return None
        self._version_seen = version
        flags: dict[str, str] = {}
        levels: dict[str, Level] = {}
        for source in self.sources:
            for key, text in dict(source.flags).items():
                flags[f"{source.name}/{key}"] = text
                levels[f"{source.name}/{key}"] = source.levels.get(key, Level.ERROR)
        return flags, levels
