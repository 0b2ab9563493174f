"""The resource layer: one flat 14-joint list in canonical order, whoever owns the joints."""

import numpy as np
import pytest

from doubles.control import Plant
from humanoid_prime.control.resources import ResourceManager
from humanoid_prime.errors import PrimeError


def split_like_hardware(robot):
    """Two components as on Prime: the 10 eRob on one, the 4 Sito on the other."""
    erob = tuple(j.name for j in robot.joints if j.family == "erob")
    sito = tuple(j.name for j in robot.joints if j.family == "sito")
    return Plant("ethercat", erob), Plant("sito", sito)


def test_components_get_the_canonical_indices_of_their_joints(robot):
    ethercat, sito = split_like_hardware(robot)
    ResourceManager(robot, [ethercat, sito])
    assert ethercat.indices.tolist() == [0, 1, 2, 3, 6, 7, 8, 9, 10, 13]
    assert sito.indices.tolist() == [4, 5, 11, 12]


def test_read_assembles_one_flat_state_in_canonical_order(robot):
    ethercat, sito = split_like_hardware(robot)
    resources = ResourceManager(robot, [ethercat, sito])
    ethercat.position[:] = [robot.index(name) for name in ethercat.joints]
    sito.position[:] = [robot.index(name) for name in sito.joints]
    resources.read(1.5)
    assert resources.state.position.tolist() == list(range(14))
    assert resources.state.stamp == 1.5


def test_write_hands_each_component_its_own_joints(robot):
    ethercat, sito = split_like_hardware(robot)
    resources = ResourceManager(robot, [ethercat, sito])
    resources.command.position[:] = np.arange(14)
    resources.write(0.0)
    assert sito.last[0].tolist() == [4, 5, 11, 12]
    assert ethercat.last[0].tolist() == [0, 1, 2, 3, 6, 7, 8, 9, 10, 13]


def test_a_joint_owned_twice_is_refused(robot):
    with pytest.raises(PrimeError, match="'left_wrist_roll' is owned by both 'all' and 'wrists'"):
        ResourceManager(robot, [Plant("all", robot.names), Plant("wrists", ("left_wrist_roll",))])


def test_a_joint_owned_by_nobody_is_refused(robot):
    with pytest.raises(PrimeError, match="no hardware component owns right_wrist_yaw"):
        ResourceManager(robot, [Plant("most", robot.names[:-1])])


def test_an_unknown_joint_is_refused(robot):
    with pytest.raises(PrimeError, match="lists unknown joint 'waist_yaw'"):
        ResourceManager(robot, [Plant("all", (*robot.names, "waist_yaw"))])


def test_lifecycle_walks_the_components_in_order(robot):
    events: list[str] = []
    first, second = Plant("ethercat", robot.names[:7], events), Plant("sito", robot.names[7:], events)
    resources = ResourceManager(robot, [first, second])
    resources.configure()
    resources.activate()
    resources.shutdown()
    assert events == ["ethercat.configure", "sito.configure", "ethercat.activate", "sito.activate",
                      "ethercat.deactivate", "ethercat.shutdown", "sito.deactivate", "sito.shutdown"]


def test_shutdown_attempts_every_component_even_if_one_fails(robot):
    class Failing(Plant):
        def on_shutdown(self) -> None:
            raise OSError("bus gone")

    events: list[str] = []
    failing, fine = Failing("ethercat", robot.names[:7], events), Plant("sito", robot.names[7:], events)
    resources = ResourceManager(robot, [failing, fine])
    resources.configure()
    resources.activate()
    with pytest.raises(PrimeError, match="ethercat: bus gone"):
        resources.shutdown()
    assert "sito.shutdown" in events
