"""What the bad-input cases are made from: every (sub)command's parser, walked, and the files of a case's folder."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path

from humanoid_prime.cli import build_parser
from humanoid_prime.cli._commands import COMMANDS  # private to cli/: the suite walks every command of its table
from humanoid_prime.files import bundled

# A valid value for each positional argument, by command path and metavar (the cases replace one at a time).
POSITIONALS = {
    ("limp", "RING_POS"): "4", ("limp", "DAMPING"): "2",
    ("ec", "sdo", "read", "RING"): "3", ("ec", "sdo", "read", "INDEX:SUB"): "0x2382:01",
    ("ec", "sdo", "write", "RING"): "3", ("ec", "sdo", "write", "INDEX:SUB"): "0x2382:01",
    ("ec", "sdo", "write", "VALUE"): "5",
    ("switch", "mode"): "DAMPING", ("decode", "N"): "0",
    ("plot", "FILE.mcap"): "{tmp}/run.mcap", ("replay", "FILE.mcap"): "{tmp}/run.mcap",
    ("calibration", "flip", "JOINT"): "left_elbow_pitch",
}
PATH_TYPES = ("output_file", "output_dir", "mcap_file")


Parsers = Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]
# private to argparse, which has no public way to list a parser's arguments or tell subcommands apart: read here only
SUBPARSERS = argparse._SubParsersAction


def actions(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """Every argument of ``parser``, its subcommands' action included (argparse's own list, read only)."""
    return list(parser._actions)  # private to argparse: see SUBPARSERS


def walk(parser: argparse.ArgumentParser, path: tuple[str, ...]) -> Parsers:
    """Every parser under ``parser`` with the words that reach it."""
    yield path, parser
    for action in actions(parser):
        if isinstance(action, SUBPARSERS):
            for name, sub in action.choices.items():
                if name not in COMMANDS or not path:  # the command's own parser, or its subcommands
                    yield from walk(sub, (*path, name))


def parsers() -> list[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    """Every runnable (sub)command's parser: ``(("can", "monitor"), parser)``, ..."""
    found = []
    for command in sorted(COMMANDS):
        top = build_parser(command)
        sub = next(a for a in actions(top) if isinstance(a, SUBPARSERS)).choices[command]
        for path, parser in walk(sub, (command,)):
            if parser.get_default("func") is not None and not any(
                    isinstance(a, SUBPARSERS) and a.required for a in actions(parser)):
                found.append((path, parser))
    return found


def positionals(path: tuple[str, ...], parser: argparse.ArgumentParser) -> list[argparse.Action]:
    return [a for a in actions(parser) if not a.option_strings and not isinstance(a, SUBPARSERS)
            and a.nargs not in ("*", argparse.REMAINDER)]


def positional_values(path: tuple[str, ...], parser: argparse.ArgumentParser) -> list[str]:
    """A valid value for each required positional of ``path`` (optional ones left out)."""
    return [POSITIONALS.get((*path, a.metavar or a.dest)) or POSITIONALS[(path[0], a.metavar or a.dest)]
            for a in positionals(path, parser) if a.nargs != "?"]


def name(action: argparse.Action) -> str:
    """How argparse names ``action`` in its errors."""
    return argparse._get_action_name(action) or action.dest  # private to argparse: the name its errors use


def typed(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The visible arguments that convert their value (numbers, ids, words), not paths."""
    return [a for a in actions(parser) if a.type is not None and a.help != argparse.SUPPRESS
            and getattr(a.type, "__name__", "") not in PATH_TYPES and not isinstance(a, SUBPARSERS)]


SENTINELS = {  # what every case's folder holds before the command runs; none of it may change
    "keep.txt": b"a file a path names by mistake\n",
    "summary.json": b'{"sentinel": true}\n',
    "plot.png": b"\x89PNG sentinel",
}


def fill(folder: Path) -> None:
    for file, data in SENTINELS.items():
        (folder / file).write_bytes(data)
    (folder / "cal.yaml").write_bytes(bundled("prime_calibration.yaml").read_bytes())
