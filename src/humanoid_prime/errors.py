"""Errors meant for people: each says what was wrong, where, and what to do."""

from __future__ import annotations

from pathlib import Path


class PrimeError(Exception):
    """Base of every error the command line reports as one line (no traceback)."""


class ConfigError(PrimeError):
    """A configuration file is malformed or inconsistent."""

    def __init__(self, file: str | Path, key: str, problem: str, fix: str = "") -> None:
        self.file = str(file)
        self.key = key
        self.problem = problem
        self.fix = fix
        where = f"{self.file}: {key}" if key else self.file
        text = f"{where}: {problem}"
        if fix:
            text += f" ({fix})"
        super().__init__(text)


class ControllerError(PrimeError):
    """A controller cannot produce a safe command (stale or invalid input); the manager falls back."""


class LifecycleError(PrimeError):
    """A lifecycle step was asked for in the wrong state (a hardware component, the controller manager)."""
