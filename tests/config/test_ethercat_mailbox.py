"""buses.ethercat.mailbox: who works the eRob's mailboxes (prime: Prime's CoE layer; soem: SOEM alone, the way
back), read from the hardware file, prime when the key is absent, and anything else refused by name."""

from __future__ import annotations

import copy

import pytest
import yaml

from humanoid_prime.config.hardware import load_hardware
from humanoid_prime.errors import ConfigError
from humanoid_prime.files import bundled

HARDWARE = yaml.safe_load(bundled("prime_hardware.yaml").read_text())


def hardware_file(tmp_path, mailbox):
    data = copy.deepcopy(HARDWARE)
    if mailbox is None:
        del data["buses"]["ethercat"]["mailbox"]
    else:
        data["buses"]["ethercat"]["mailbox"] = mailbox
    path = tmp_path / "prime_hardware.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.mark.parametrize("written, read", [("prime", "prime"), ("soem", "soem"), (None, "prime")])
def test_the_mailbox_key_names_who_works_the_mailboxes(tmp_path, written, read):
    assert load_hardware(hardware_file(tmp_path, written)).ethercat.mailbox == read


@pytest.mark.parametrize("written", ["SOEM", "igh", 1])
def test_any_other_mailbox_is_refused_by_key(tmp_path, written):
    path = hardware_file(tmp_path, written)
    with pytest.raises(ConfigError) as info:
        load_hardware(path)
    assert info.value.key == "buses.ethercat.mailbox" and str(path) in str(info.value)
