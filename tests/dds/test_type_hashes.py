"""The control_msgs and controller_manager_msgs types Prime carries (``interfaces/``) hash as the official ones do,
so MoveIt and ``ros2 control`` built from the official packages match Prime's endpoints. The official values are
facts recorded with the upstream commits they were computed from (``ros/official_type_hashes.json``); Prime's are
what the PyPI rosidl toolchain computes building ``interfaces/`` into each client environment."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from .conftest import ROS_DISTROS

FACTS = json.loads((Path(__file__).parent / "ros" / "official_type_hashes.json").read_text())
PACKAGES = ("control_msgs", "controller_manager_msgs")


def built_hashes(install: Path) -> dict[str, str]:
    """Type name -> RIHS01 of every type of PACKAGES in ``install``'s type descriptions."""
    found = {}
    for package in PACKAGES:
        for path in sorted((install / "share" / package).rglob("*.json")):
            for entry in json.loads(path.read_text()).get("type_hashes", []):
                if entry["type_name"].split("/")[0] == package:
                    found[entry["type_name"]] = entry["hash_string"]
    return found


@pytest.mark.parametrize("distro", ROS_DISTROS)
def test_the_types_prime_serves_hash_as_the_official_ones(ros_clients, distro):
    install = Path(ros_clients[distro]["LD_LIBRARY_PATH"]).parent
    official = FACTS["hashes"][distro]
    assert "control_msgs/action/FollowJointTrajectory_Feedback" in official
    assert "controller_manager_msgs/srv/SwitchController_Request" in official
    assert built_hashes(install) == official


def test_jazzy_and_kilted_differ_only_in_the_trajectory_feedback():
    """Kilted's feedback has the index fields Jazzy's lacks: the two facts are not one value copied."""
    jazzy, kilted = FACTS["hashes"]["jazzy"], FACTS["hashes"]["kilted"]
    assert jazzy.keys() == kilted.keys()
    assert {name for name in jazzy if jazzy[name] != kilted[name]} == {
        "control_msgs/action/FollowJointTrajectory", "control_msgs/action/FollowJointTrajectory_Feedback",
        "control_msgs/action/FollowJointTrajectory_FeedbackMessage"}
