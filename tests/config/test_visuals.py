"""The description draws the robot: every moving link and the torso have visual geometry, the URDF passes an
independent parser (check_urdf, Debian's liburdfdom-tools), and the URDF and the MuJoCo model colour each link
by the actuator family that drives it."""

from __future__ import annotations

import shutil
import subprocess
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest

from humanoid_prime.config.description import render_urdf
from humanoid_prime.config.model import load_model

FAMILY_RGBA = {"erob": (0.31, 0.43, 0.58, 1.0), "sito": (0.85, 0.51, 0.17, 1.0)}


@pytest.fixture(scope="module")
def urdf(robot) -> str:
    return render_urdf(robot.hardware)


def test_check_urdf_accepts_the_description(urdf, tmp_path):
    if shutil.which("check_urdf") is None:
        pytest.fail("check_urdf is missing: `make test` installs Debian's liburdfdom-tools")
    path = tmp_path / "prime.urdf"
    path.write_text(urdf)
    done = subprocess.run(["check_urdf", str(path)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "robot name is: prime_dummy" in done.stdout and "root Link: base_link has 1 child(ren)" in done.stdout


def test_every_moving_link_is_drawn_in_its_familys_colour(robot, urdf):
    root = ET.fromstring(urdf)
    colours = {m.get("name"): tuple(float(v) for v in m.find("color").get("rgba").split())
               for m in root.iter("material") if m.find("color") is not None}
    child_of = {j.get("name"): j.find("child").get("link") for j in root.findall("joint")}
    links = {link.get("name"): link for link in root.findall("link")}
    for joint in robot.joints:
        visual = links[child_of[joint.name]].find("visual")
        assert visual is not None, joint.name
        assert colours[visual.find("material").get("name")] == FAMILY_RGBA[joint.family], joint.name
    assert links["torso_link"].find("visual") is not None


def test_the_mujoco_model_colours_links_like_the_urdf(robot):
    model = load_model(robot)
    for joint in robot.joints:
        body = model.jnt_bodyid[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, joint.name)]
        geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body]
        assert geoms, joint.name
        for g in geoms:
            np.testing.assert_allclose(model.geom_rgba[g], FAMILY_RGBA[joint.family], err_msg=joint.name)
