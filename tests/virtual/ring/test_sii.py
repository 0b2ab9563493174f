"""The SII EEPROM image: the words and categories SOEM reads during ec_config_init."""

from __future__ import annotations

import struct

import pytest

from humanoid_prime.drivers.erob.constants import PRODUCT_CODE, VENDOR_ID
from humanoid_prime.drivers.erob.objects import POWER_UP_RXPDO, POWER_UP_TXPDO
from humanoid_prime.drivers.ethercat.wire import COE_DETAIL_COMPLETE_ACCESS, COE_DETAIL_SDO, MAILBOX_PROTOCOL_COE
from humanoid_prime.virtual.ring import sii
from humanoid_prime.virtual.ring.firmware import sii_content
from humanoid_prime.virtual.ring.options import RingOptions


@pytest.fixture(scope="module")
def image() -> bytes:
    return sii.build_image(sii_content(RingOptions(), serial=0x1234))


def word32(image: bytes, word: int) -> int:
    return struct.unpack_from("<I", image, 2 * word)[0]


def test_identity_words_carry_the_erob_vendor_and_product(image):
    assert word32(image, 0x08) == VENDOR_ID == 0x5A65726F
    assert word32(image, 0x0A) == PRODUCT_CODE == 0x00029252
    assert word32(image, 0x0E) == 0x1234


def test_mailbox_words_give_offsets_and_sizes_and_coe(image):
    assert struct.unpack_from("<HHHHH", image, 2 * 0x18) == (0x1000, 128, 0x1080, 128, MAILBOX_PROTOCOL_COE)


def test_header_checksum_is_crc8_of_words_0_to_6(image):
    assert image[14] == sii.crc8(image[:14])


def test_crc8_uses_polynomial_0x07_and_initial_value_0xff():
    # one zero byte: 0xFF shifted through eight steps of x^8 + x^2 + x + 1, worked by hand
    assert sii.crc8(b"\x00") == 0xF3


def test_string_one_is_the_slave_name(image):
    strings = sii.find_category(image, sii.CATEGORY_STRINGS)
    assert strings[0] == 3
    assert strings[2:2 + strings[1]] == b"eRob CiA402 (emulated)"


def test_general_category_does_not_advertise_complete_access(image):
    general = sii.find_category(image, sii.CATEGORY_GENERAL)
    coe_details = general[5]
    assert coe_details & COE_DETAIL_SDO
    assert not coe_details & COE_DETAIL_COMPLETE_ACCESS
    assert not general[11] & 0x02  # LRW allowed


def test_sync_manager_category_lists_mailboxes_and_process_data(image):
    data = sii.find_category(image, sii.CATEGORY_SYNC_MANAGER)
    sms = [struct.unpack_from("<HHBBBB", data, 8 * i) for i in range(len(data) // 8)]
    assert sms == [
        (0x1000, 128, 0x26, 0, 1, sii.SM_TYPE_MAILBOX_OUT),
        (0x1080, 128, 0x22, 0, 1, sii.SM_TYPE_MAILBOX_IN),
        (0x1100, 10, 0x64, 0, 1, sii.SM_TYPE_OUTPUTS),  # ZeroErr's power-up mapping: 607A, 60FE, 6040
        (0x1180, 10, 0x20, 0, 1, sii.SM_TYPE_INPUTS),  # 6064, 60FD, 6041
    ]


def test_pdo_categories_hold_the_power_up_mapping(image):
    for kind, pdo_index, entries, sm in ((sii.CATEGORY_RXPDO, 0x1600, POWER_UP_RXPDO, 2),
                                         (sii.CATEGORY_TXPDO, 0x1A00, POWER_UP_TXPDO, 3)):
        data = sii.find_category(image, kind)
        index, count, sync_manager = struct.unpack_from("<HBB", data)
        assert (index, count, sync_manager) == (pdo_index, len(entries), sm)
        listed = [struct.unpack_from("<HBBBB", data, 8 + 8 * i) for i in range(count)]
        assert [(e[0], e[1], e[4]) for e in listed] == [(e.index, e.sub_index, e.bits) for e in entries]


def test_category_walk_ends_at_0xffff(image):
    assert sii.find_category(image, 0x1234) is None
