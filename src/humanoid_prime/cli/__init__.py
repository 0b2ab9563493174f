"""The ``prime`` command. Each subcommand's module (``_commands.COMMANDS``) defines ``register(subparsers)``,
which adds it (and any other command of that module); a subcommand sets ``func(args) -> int``. Errors meant for people
(PrimeError, and argparse's own) print one line to stderr and exit non-zero; anything else is a bug,
reported as one line too (exit 70), with the traceback only under PRIME_DEBUG=1."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from typing import NoReturn

from humanoid_prime import __version__
from humanoid_prime.cli._commands import COMMANDS
from humanoid_prime.errors import PrimeError
from humanoid_prime.interrupts import Interrupts


class _Parser(argparse.ArgumentParser):
    """A bad argument is reported as one line (no usage block); subcommand parsers inherit this."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def build_parser(command: str | None) -> argparse.ArgumentParser:
    """The ``prime`` parser: every subcommand listed, and ``command``'s own parser built by its module (only that
    module is imported; None: no command's, which is enough for ``prime --help``)."""
    parser = _Parser(prog="prime", description="Bring up, calibrate and operate Prime.")
    parser.add_argument("--version", action="version", version=f"prime {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    if command is not None:  # its module may register other commands too (view and replay)
        importlib.import_module(f"{__name__}.{COMMANDS[command][0]}").register(subparsers)
    for name, (_, summary) in sorted(COMMANDS.items()):
        if name not in subparsers.choices:
            subparsers.add_parser(name, help=summary, add_help=False)
    return parser


def _command(argv: list[str]) -> str | None:
    """The subcommand ``argv`` names (its first word that is no option), if it is one."""
    word = next((arg for arg in argv if not arg.startswith("-")), None)
    return word if word in COMMANDS else None


def main(argv: list[str] | None = None, *, interrupts: Interrupts | None = None) -> int:
    """The command line, run: its exit status. ``interrupts``: the entry's Ctrl-C watch, started before the command
    line loaded (None: main watches while it runs)."""
    name, own = "prime", interrupts is None
    try:
        if interrupts is None:
            interrupts = Interrupts()
        argv = sys.argv[1:] if argv is None else argv
        command = _command(argv)
        name = f"prime {command}" if command else name  # an interrupt while it loads names it too
        parser = build_parser(command)
        args = parser.parse_args(argv)
        if getattr(args, "func", None) is None:
            parser.print_help()
            return 2
        name = f"prime {args.command}"
        # The command reads the robot's configuration: one rule for all of them (`prime config init` makes it).
        if hasattr(args, "robot") and not getattr(args, "makes_config", False):
            from humanoid_prime.cli._common import resolve_config

            resolve_config(args)
        from humanoid_prime.cli._common import check_outputs

        check_outputs(parser, args)  # no output may be an input: checked before anything starts
        if hasattr(args, "web_port"):  # --web and --port, one idea on every command that serves the view
            from humanoid_prime.cli._common import resolve_web

            resolve_web(args)
        return int(args.func(args) or 0)
    except PrimeError as exc:
        print(f"{name}: {_one_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{name}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader (e.g. `| head`) went away; silence the flush at exit as well.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:  # the system refused (a device gone, a permission): say what, where it was known
        if interrupts is not None and interrupts.seen:
            print(f"{name}: interrupted", file=sys.stderr)
            return 130
        where = f" ({exc.filename})" if exc.filename else ""
        print(f"{name}: {exc.strerror or exc}{where}", file=sys.stderr)
        return 1
    except Exception as exc:  # a bug of ours still ends in one line; PRIME_DEBUG=1 shows the traceback
        if interrupts is not None and interrupts.seen:  # e.g. an import broken off by Ctrl-C ("initialization failed")
            print(f"{name}: interrupted", file=sys.stderr)
            return 130
        if os.environ.get("PRIME_DEBUG"):
            raise
        print(f"{name}: internal error, {type(exc).__name__}: {_one_line(exc)} (PRIME_DEBUG=1 shows where; "
              "please report it)", file=sys.stderr)
        return 70
    finally:
        if own and interrupts is not None:
            interrupts.close()


def _one_line(exc: BaseException) -> str:
    """An error's text on one line: a library's message (xacro, MuJoCo) may span several."""
    return " ".join(line.strip() for line in str(exc).splitlines() if line.strip())


if __name__ == "__main__":
    sys.exit(main())
