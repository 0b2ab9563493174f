"""What Prime's frames beside SOEM's rest on, checked: the pysoem version, the split of frame indices, and SOEM
made to read its socket before Prime's replies could fill it."""

from __future__ import annotations

from humanoid_prime.drivers.ethercat.soem_contract import TESTED_PYSOEM, QueueKeeper, check_indices, check_version


def test_the_tested_pysoem_passes_and_another_is_refused_in_one_line_naming_both():
    assert check_version(TESTED_PYSOEM) is None
    problem = check_version("1.1.14")
    assert problem is not None and "\n" not in problem
    assert "pysoem 1.1.14 is installed" in problem and f"pip install pysoem=={TESTED_PYSOEM}" in problem


def test_soem_frames_numbered_below_ec_maxbuf_keep_the_split_and_any_other_breaks_it():
    assert check_indices(range(16)) is None
    assert check_indices([]) is None
    problem = check_indices([3, 0x10, 0x41])
    assert problem is not None and "0x10, 0x41 inside the range Prime keeps for its own frames" in problem


def test_soem_is_made_to_read_its_socket_at_the_limit_and_a_cycle_read_counts_what_came_before_its_frame():
    drains = []
    keeper = QueueKeeper(lambda: drains.append(1), limit=5)
    for _ in range(3):
        keeper.sent()
    keeper.sending()  # a cycle frame goes out behind those three replies
    keeper.sent()  # and one more after it, still in SOEM's socket once the cycle is read
    keeper.read()
    for _ in range(3):
        keeper.sent()
    assert drains == []
    keeper.sent()  # the fifth since SOEM's socket was read up to the cycle's frame
    assert drains == [1] and keeper.drains == 1
