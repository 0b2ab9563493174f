"""Prime in a viser scene: the MuJoCo model's visual geoms (the description's shapes and colours), one frame
per body, posed by MuJoCo's forward kinematics from the 14 joint positions."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from humanoid_prime.config.model import load_model
from humanoid_prime.config.robot import Robot

ROOT = "/prime"


class RobotScene:
    def __init__(self, server, robot: Robot, model_path: str | Path | None = None) -> None:
        self.server = server
        self.model = model = load_model(robot, model_path)
        self.data = mujoco.MjData(model)
        self._qpos = np.array([model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)]
                               for name in robot.names])
        self._frames: dict[int, object] = {}
        scene = server.scene
        scene.add_grid(f"{ROOT}/floor", width=2.0, height=2.0, cell_size=0.1, section_size=0.5)
        for body in range(1, model.nbody):
            geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body]
            if not geoms:
                continue
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body)
            self._frames[body] = scene.add_frame(f"{ROOT}/{name}", show_axes=False)
            for g in geoms:
                self._add_geom(f"{ROOT}/{name}/geom{g}", g)
        for g in range(model.ngeom):  # the world's own geoms (the pedestal), not the floor plane
            if model.geom_bodyid[g] == 0 and model.geom_type[g] != mujoco.mjtGeom.mjGEOM_PLANE:
                self._add_geom(f"{ROOT}/world_geom{g}", g)
        self.pose(np.zeros(robot.n))

    def _add_geom(self, name: str, g: int) -> None:
        model, scene = self.model, self.server.scene
        kind = model.geom_type[g]
        size = model.geom_size[g]
        colour = tuple(int(round(255 * c)) for c in model.geom_rgba[g][:3])
        placed = {"position": tuple(model.geom_pos[g]), "wxyz": tuple(model.geom_quat[g])}
        if kind == mujoco.mjtGeom.mjGEOM_BOX:
            scene.add_box(name, color=colour, dimensions=tuple(2 * size), **placed)
        elif kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
            scene.add_cylinder(name, radius=float(size[0]), height=float(2 * size[1]), color=colour, **placed)
        elif kind == mujoco.mjtGeom.mjGEOM_CAPSULE:  # a cylinder with a sphere at each end
            scene.add_frame(name, show_axes=False, **placed)
            scene.add_cylinder(f"{name}/body", radius=float(size[0]), height=float(2 * size[1]), color=colour)
            for end, z in (("top", size[1]), ("bottom", -size[1])):
                scene.add_icosphere(f"{name}/{end}", radius=float(size[0]), color=colour, position=(0.0, 0.0, z))
        elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
            scene.add_icosphere(name, radius=float(size[0]), color=colour, **placed)

    def pose(self, positions: np.ndarray) -> None:
        """Put the joints at ``positions`` (rad, canonical order); a NaN joint (not measured) stays at 0."""
        model, data = self.model, self.data
        data.qpos[self._qpos] = np.nan_to_num(positions, nan=0.0)
        mujoco.mj_kinematics(model, data)
        with self.server.atomic():
            for body, frame in self._frames.items():
                frame.position = tuple(data.xpos[body])
                frame.wxyz = tuple(data.xquat[body])
