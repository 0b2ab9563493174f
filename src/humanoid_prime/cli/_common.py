"""Options and output helpers shared by the subcommands."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any


def add_config_options(parser: argparse.ArgumentParser, *, calibration: bool = False,
                       controllers: bool = False) -> None:
    parser.add_argument("--hardware", metavar="FILE", help="hardware file (default: bundled prime_hardware.yaml)")
    if calibration:
        parser.add_argument("--calibration", metavar="FILE",
                            help="calibration file (default: bundled prime_calibration.yaml)")
    if controllers:
        parser.add_argument("--controllers", metavar="FILE",
                            help="controllers file (default: bundled prime_controllers.yaml)")


def add_json_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print machine-readable JSON")


def print_json(data: Any) -> None:
    json.dump(data, sys.stdout, indent=2)
    sys.stdout.write("\n")
