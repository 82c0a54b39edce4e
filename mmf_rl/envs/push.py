"""FetchPush-v4 with a simulated multimodal sensor suite.

`MultimodalPushEnv` subclasses gymnasium-robotics' `MujocoFetchPushEnv` and keeps its physics,
reward and goal sampling. It adds, at every step:

- ``image``: an RGB view rendered offscreen (EGL, else OSMesa) with the env's own renderer;
- ``force``: the wrench the gripper applies to the object, world frame, summed over the 20
  physics sub-steps of the env step (N and N·m per sub-step, so 20x the mean wrench; see
  `gripper_object_wrench`);
- ``proprio``: gripper position and velocity, finger positions and velocities, arm joints;
- ``object_pose``: object position and orientation quaternion (the forecasting target).

The GoalEnv keys (``observation``, ``achieved_goal``, ``desired_goal``) stay in the
observation dict, so code written for FetchPush keeps working.
"""

from __future__ import annotations

import ctypes.util
import functools
import os


def _select_gl_backend() -> None:
    """Pick EGL for offscreen rendering, OSMesa when no EGL library is installed.

    PyOpenGL fixes its platform at first import, so the choice has to be made before MuJoCo's
    GL modules load; a user's own ``MUJOCO_GL`` always wins.
    """
    if "MUJOCO_GL" not in os.environ:
        os.environ["MUJOCO_GL"] = "egl" if ctypes.util.find_library("EGL") else "osmesa"
    if os.environ["MUJOCO_GL"] in ("egl", "osmesa"):
        os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])


_select_gl_backend()


def _import_gymnasium_robotics_quietly() -> None:
    """Import gymnasium-robotics without the note on its Adroit envs' rewards that it prints to
    stderr on import (through farama_notifications): mmf-rl uses no Adroit env, and the note
    reached every process that imports the push env. Only gymnasium-robotics' own notifications
    are held back, and only during this import."""
    try:
        from farama_notifications import notifications
    except ImportError:  # without it gymnasium-robotics prints nothing either
        notifications = {}
    held = notifications.pop("gymnasium_robotics", None)
    try:
        import gymnasium_robotics  # noqa: F401
    finally:
        if held is not None:
            notifications["gymnasium_robotics"] = held


_import_gymnasium_robotics_quietly()

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402
from gymnasium.envs.mujoco.mujoco_rendering import MujocoRenderer  # noqa: E402
from gymnasium_robotics.envs import robot_env  # noqa: E402
from gymnasium_robotics.envs.fetch.push import MODEL_XML_PATH, MujocoFetchPushEnv  # noqa: E402

# Free cameras (MuJoCo `mjvCamera` fields); any camera named in the model XML works as well.
FREE_CAMERAS: dict[str, dict] = {
    # Facing the robot across the table: the whole table, the object, the goal marker and the arm.
    "front": {
        "distance": 1.0,
        "azimuth": 180.0,
        "elevation": -45.0,
        "lookat": np.array([1.3, 0.75, 0.42]),
    },
    # Straight down on the table: planar positions read off directly, the arm occludes more.
    "top": {
        "distance": 0.9,
        "azimuth": 180.0,
        "elevation": -89.0,
        "lookat": np.array([1.3, 0.75, 0.42]),
    },
}

GRIPPER_BODIES = ("robot0:gripper_link", "robot0:r_gripper_finger_link", "robot0:l_gripper_finger_link")
OBJECT_BODY = "object0"
GRIP_SITE = "robot0:grip"
OBJECT_JOINT = "object0:joint"
FINGER_JOINTS = ("robot0:r_gripper_finger_joint", "robot0:l_gripper_finger_joint")
ARM_JOINTS = (
    "robot0:shoulder_pan_joint",
    "robot0:shoulder_lift_joint",
    "robot0:upperarm_roll_joint",
    "robot0:elbow_flex_joint",
    "robot0:forearm_roll_joint",
    "robot0:wrist_flex_joint",
    "robot0:wrist_roll_joint",
)

# Per-dimension names, stored in the dataset's feature metadata.
FORCE_NAMES = ["fx", "fy", "fz", "tx", "ty", "tz"]
PROPRIO_NAMES = (
    ["grip_x", "grip_y", "grip_z", "grip_vx", "grip_vy", "grip_vz"]
    + ["finger_r_pos", "finger_l_pos", "finger_r_vel", "finger_l_vel"]
    + [name.removeprefix("robot0:").removesuffix("_joint") for name in ARM_JOINTS]
)
OBJECT_POSE_NAMES = ["x", "y", "z", "qw", "qx", "qy", "qz"]
GOAL_NAMES = ["goal_x", "goal_y", "goal_z"]
ACTION_NAMES = ["dx", "dy", "dz", "gripper"]


@functools.cache
def camera_names() -> list[str]:
    """Cameras `MultimodalPushEnv` accepts: the free ones, then those of the FetchPush model."""
    # Resolved the way gymnasium-robotics' RobotEnv resolves a relative model path.
    model = mujoco.MjModel.from_xml_path(
        os.path.join(os.path.dirname(robot_env.__file__), "assets", MODEL_XML_PATH)
    )
    return sorted(FREE_CAMERAS) + [model.camera(i).name for i in range(model.ncam)]


class MultimodalPushEnv(MujocoFetchPushEnv):
    """FetchPush-v4 whose observation adds ``image``, ``force``, ``proprio`` and ``object_pose``.

    Args:
        image_size (int, optional): side of the square RGB image, in pixels.
        camera (str, optional): a key of `FREE_CAMERAS` or the name of a camera in the model XML
            (e.g. ``"external_camera_0"``, ``"head_camera_rgb"``).
        reward_type (str, optional): ``"sparse"`` or ``"dense"``, as in FetchPush.

    Call `close()` when done: it frees the OpenGL context.

    Raises:
        ValueError: an ``image_size`` below 8, or a camera the model does not have.
    """

    def __init__(self, image_size: int = 64, camera: str = "front", reward_type: str = "sparse"):
        if image_size < 8:
            raise ValueError(f"image_size={image_size} is too small; use at least 8 pixels.")
        free_camera = FREE_CAMERAS.get(camera)
        super().__init__(
            reward_type=reward_type,
            render_mode="rgb_array",
            width=image_size,
            height=image_size,
            default_camera_config=free_camera,
        )
        if free_camera is None:
            # The env's renderer only knows free cameras; a fixed one needs its own renderer.
            self.close()
            camera_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
            if camera_id < 0:
                raise ValueError(f"unknown camera {camera!r}; choose one of {camera_names()}.")
            self.mujoco_renderer = MujocoRenderer(
                self.model, self.data, width=image_size, height=image_size, camera_id=camera_id
            )

        names = self._model_names
        self._gripper_body_ids = np.array([names.body_name2id[b] for b in GRIPPER_BODIES])
        self._object_body_id = names.body_name2id[OBJECT_BODY]
        self._wrench = np.zeros(6)
        self._contact_buffer = np.zeros(6)

        self.observation_space = spaces.Dict(
            {
                **self.observation_space.spaces,
                "image": spaces.Box(0, 255, (image_size, image_size, 3), np.uint8),
                "force": spaces.Box(-np.inf, np.inf, (len(FORCE_NAMES),), np.float64),
                "proprio": spaces.Box(-np.inf, np.inf, (len(PROPRIO_NAMES),), np.float64),
                "object_pose": spaces.Box(-np.inf, np.inf, (len(OBJECT_POSE_NAMES),), np.float64),
            }
        )

    # -- physics -------------------------------------------------------------------------------

    def _mujoco_step(self, action):
        # The parent runs all sub-steps in one `mj_step(nstep=...)` call; `data.contact` then only
        # holds the last sub-step's contacts, and most short pushes fall between reads.
        self._wrench[:] = 0.0
        for _ in range(self.n_substeps):
            self._mujoco.mj_step(self.model, self.data)
            self._wrench += self.gripper_object_wrench()

    def gripper_object_wrench(self) -> np.ndarray:
        """Force and torque the gripper applies to the object now, world frame.

        Torque is about the object's centre of mass: ``r × f`` for each contact point plus the
        contact's own torsional/rolling torque. Returns ``[fx, fy, fz, tx, ty, tz]``.
        """
        wrench = np.zeros(6)
        ncon = self.data.ncon
        if ncon == 0:
            return wrench
        contacts = self.data.contact
        bodies = self.model.geom_bodyid[contacts.geom[:ncon]]  # [ncon, 2]
        gripper = np.isin(bodies, self._gripper_body_ids)
        is_object = bodies == self._object_body_id
        # MuJoCo's contact normal points from geom1 to geom2, and the contact force pushes geom2
        # along it: +1 when the object is geom2, -1 when it is geom1.
        signs = (gripper[:, 0] & is_object[:, 1]).astype(float) - (gripper[:, 1] & is_object[:, 0])
        object_com = self.data.xipos[self._object_body_id]
        for i in np.flatnonzero(signs):
            mujoco.mj_contactForce(self.model, self.data, int(i), self._contact_buffer)
            frame = contacts.frame[i].reshape(3, 3)  # rows: normal, tangent1, tangent2
            force = signs[i] * frame.T @ self._contact_buffer[:3]
            torque = signs[i] * frame.T @ self._contact_buffer[3:]
            wrench[:3] += force
            wrench[3:] += np.cross(contacts.pos[i] - object_com, force) + torque
        return wrench

    # -- sensors -------------------------------------------------------------------------------

    def _sensors(self) -> dict[str, np.ndarray]:
        utils, model, data = self._utils, self.model, self.data
        grip_pos = utils.get_site_xpos(model, data, GRIP_SITE)
        grip_vel = utils.get_site_xvelp(model, data, GRIP_SITE)
        finger_pos = [utils.get_joint_qpos(model, data, j)[0] for j in FINGER_JOINTS]
        finger_vel = [utils.get_joint_qvel(model, data, j)[0] for j in FINGER_JOINTS]
        arm_pos = [utils.get_joint_qpos(model, data, j)[0] for j in ARM_JOINTS]
        return {
            "image": self.render(),
            "force": self._wrench.copy(),
            "proprio": np.concatenate([grip_pos, grip_vel, finger_pos, finger_vel, arm_pos]),
            # qpos of a free joint: position, then unit quaternion (w, x, y, z).
            "object_pose": utils.get_joint_qpos(model, data, OBJECT_JOINT).copy(),
        }

    def render(self):
        # gymnasium makes a viewer's GL context current only when it creates it: with a second env
        # in the process, frames would be drawn in that env's context, or nowhere once it closed.
        self.mujoco_renderer._get_viewer(self.render_mode).make_context_current()
        return super().render()

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = super().reset(seed=seed, options=options)
        self._wrench[:] = 0.0
        return {**obs, **self._sensors()}, info

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        return {**obs, **self._sensors()}, reward, terminated, truncated, info
