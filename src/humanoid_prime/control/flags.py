"""Safety flags: problems observed now, keyed by source, cheap for the control loop to poll."""

from __future__ import annotations


class SafetyFlags:
    """Problems observed now, keyed by source; ``flags_version`` grows on every change (cheap to poll)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.flags: dict[str, str] = {}
        self.flags_version = 0

    def set_flag(self, key: str, text: str) -> None:
        if self.flags.get(key) != text:
            self.flags[key] = text
            self.flags_version += 1

    def clear_flag(self, key: str) -> None:
        if key in self.flags:
            del self.flags[key]
            self.flags_version += 1
