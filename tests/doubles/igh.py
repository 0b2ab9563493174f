"""A stand-in for the IgH ``ethercat`` command-line tool, installed on PATH by the tests.

It keeps its slaves and object values in a JSON file next to it, prints what the real tool prints for
``slaves -v``, ``upload`` and ``download``, and fails the way the real tool fails (message on stderr,
exit status 1). Every invocation is logged so tests can check the exact command lines.
"""

from __future__ import annotations

import json
import os
import stat
import sys
from pathlib import Path

SCRIPT = r'''#!{python}
import json, sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
state = json.loads((HERE / "state.json").read_text())
with open(HERE / "calls.log", "a") as log:
    log.write(" ".join(sys.argv[1:]) + "\n")
args = sys.argv[1:]
opts = {{}}
rest = []
i = 0
while i < len(args):
    a = args[i]
    if a in ("-m", "--master", "--type", "-t"):
        opts[a.lstrip("-")[0]] = args[i + 1]
        i += 2
    elif a.startswith("-p"):
        opts["p"] = a[2:]
        i += 1
    elif a == "-v":
        opts["v"] = True
        i += 1
    else:
        rest.append(a)
        i += 1

def fail(text):
    sys.stderr.write(text + "\n")
    sys.exit(1)

if state.get("no_master"):
    fail("Failed to open master device /dev/EtherCAT0: No such file or directory")
widths = {{"uint8": 2, "int8": 2, "uint16": 4, "int16": 4, "uint32": 8, "int32": 8}}
command = rest[0]
if command == "slaves":
    for s in state["slaves"]:
        print(f"=== Master 0, Slave {{s['position']}} ===")
        print(f"State: {{s['state']}}")
        print("Flag: +")
        print("Identity:")
        print(f"  Vendor Id:       0x{{s['vendor']:08x}}")
        print(f"  Product code:    0x{{s['product']:08x}}")
        print("  Revision number: 0x00000001")
        print("General:")
        print(f"  Device name: {{s['name']}}")
    sys.exit(0)
position = int(opts["p"])
if position >= len(state["slaves"]):
    fail(f"Slave selection: No slave with position {{position}}!")
index, sub = int(rest[1], 0), int(rest[2], 0)
key = f"{{position}}:{{index:04X}}:{{sub:02X}}"
objects = state["objects"]
if command == "upload":
    if key not in objects:
        fail("SDO transfer aborted with code 0x06020000: This object does not exist in the object directory.")
    entry = objects[key]
    type_name = opts.get("t") or entry["type"]
    value = entry["value"]
    shown = value & ((1 << (4 * widths[type_name])) - 1)
    print(f"0x{{shown:0{{widths[type_name]}}x}} {{value}}")
elif command == "download":
    if key not in objects:
        fail("SDO transfer aborted with code 0x06020000: This object does not exist in the object directory.")
    objects[key]["value"] = int(rest[3], 0)
    (HERE / "state.json").write_text(json.dumps(state))
else:
    fail(f"Unknown command '{{command}}'!")
'''


class FakeIgh:
    """A fake ``ethercat`` tool in ``folder``: ``slaves`` and ``objects`` are editable and saved on ``save()``."""

    def __init__(self, folder: Path, monkeypatch) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        tool = folder / "ethercat"
        tool.write_text(SCRIPT.format(python=sys.executable))
        tool.chmod(tool.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
        monkeypatch.setenv("PATH", f"{folder}{os.pathsep}{os.environ.get('PATH', '')}")
        self.state: dict = {
            "slaves": [{"position": k, "state": "OP", "vendor": 0x5A65726F, "product": 0x00029252, "name": "eRob"}
                       for k in range(10)],
            "objects": {},
        }
        for k in range(10):
            self.set(k, 0x6041, 0, 5687, "uint16")
            self.set(k, 0x603F, 0, 0, "uint16")
            self.set(k, 0x6076, 0, 23000, "uint32")
        self.save()

    def set(self, position: int, index: int, sub: int, value: int, type_name: str) -> None:
        self.state["objects"][f"{position}:{index:04X}:{sub:02X}"] = {"value": value, "type": type_name}

    def value(self, position: int, index: int, sub: int) -> int:
        state = json.loads((self.folder / "state.json").read_text())
        return state["objects"][f"{position}:{index:04X}:{sub:02X}"]["value"]

    def save(self) -> None:
        (self.folder / "state.json").write_text(json.dumps(self.state))

    @property
    def calls(self) -> list[str]:
        log = self.folder / "calls.log"
        return log.read_text().splitlines() if log.exists() else []
