"""What a planner maximises on the push task: the forecast object near the goal, the gripper
behind the object.

The world model forecasts the object's motion under an action sequence; that is the term that
makes the agent push. It cannot make the agent *start* a push: with a horizon of T = 10 steps
(0.4 s) and the gripper tens of centimetres away, no sampled sequence moves the object and every
candidate scores the same. So a second term guides the gripper to the pre-push point behind the
object (on the object→goal line), from kinematics the robot knows without any sensor: the
gripper moves by the commanded action (FetchPush: 0.05 m per unit, of which the arm covers ~2/3
in a step, `mmf_rl.envs.scripted.TRACKING_GAIN`). Unless the gripper is already behind the
object and on the push line, it is asked to travel above the block (`CLEARANCE`), so an approach
from the wrong side passes over the object instead of ploughing it away — a collision the world
model has seen too rarely to forecast well.

The approach has two modes, chosen from where the gripper is now, as the scripted pusher that
made the data does it: until the gripper is low behind the object on the push line, it aims for
the scripted pre-push point (`PRE_PUSH_DISTANCE` behind the object) and may come down only
clear of the block (`BEHIND_MARGIN` beyond the contact distance); once it is low behind the
block, it aims for contact (`CONTACT_DISTANCE`) and pushes. With a single mode
(contact distance throughout), traces of the agent showed it descending onto the block's back
edge from above and then pushing from on top: the block tipped or was pressed into the table,
moved a few millimetres per step, and long pushes ran out of time.

The world model rarely saw the gripper run into the block from the front or the side, so its
forecasts do not warn of it; the approach term alone let the planner cut the corner, rising while
already moving over the block, and the fingers caught it and pushed it away from the goal, often
off the table. Outside the push (in the approach mode) a third term keeps the gripper out of the
block's reach (`KEEP_OUT_RADIUS` around the forecast object) unless it is at travel height there:
the scripted pusher's "lift straight up first" as a cost the planner weighs.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from mmf_rl import keys
from mmf_rl.envs.scripted import ACTION_SCALE, CLEARANCE, CONTACT_DISTANCE, PRE_PUSH_DISTANCE, TRACKING_GAIN
from mmf_rl.envs.torchrl_env import GOAL, OBJECT_POSE

# Where the gripper may be low (metres, relative to the object, along and across the push line):
# behind the object by at least the fingers' contact distance minus this margin when pushing (plus
# it when coming down), and this close to the line. Everywhere else it travels above the block.
BEHIND_MARGIN = 0.01
LINE_WIDTH = 0.02
# The gripper counts as at pushing height this close above the object's centre (a third of the
# travel height above it).
LOW = CLEARANCE / 3
# Closer than this to the object's centre (in the plane) the fingers can catch a block turned by up
# to 45 degrees: the approach keeps out of it unless at travel height.
KEEP_OUT_RADIUS = CONTACT_DISTANCE + BEHIND_MARGIN
# Metres of goal distance per metre of the gripper's distance to where it should be.
REACH_WEIGHT = 0.5
# Metres of goal distance per metre below travel height there: enough to outweigh any progress a
# plan can make by cutting the corner (a few centimetres).
KEEP_OUT_WEIGHT = 10.0


class PushObjective:
    """Per-step rewards of candidate action sequences, for `SequenceCEMPlanner` and
    `ForecasterWorldModelEnv`.

    Reads from the env's tensordict (``in_keys``): ``"object_pose"`` (now), ``"goal"`` and the
    gripper position ``("obs", "proprio")[:3]`` (proprioception is the robot's own state; the
    camera and force sensors are the ones that fail).

    Args:
        reach_weight (float, optional): weight of the gripper's distance to its target against the
            forecast object→goal distance. Defaults to ``REACH_WEIGHT`` (0.5).
        height_weight (float, optional): weight of the gripper's height error against its planar
            distance. Defaults to ``2.0``.
        uncertainty_weight (float, optional): weight (>= 0) of the forecast's own uncertainty: each step's
            reward loses ``uncertainty_weight`` times the norm of the forecast's 2-D standard deviation of the
            object's position (metres). A plan whose outcome the world model cannot tell (e.g. a long push
            that may slip sideways) then scores below an equally promising plan it is sure of. Above 0 the
            objective sets ``uses_forecast_scale``, so the planners (`SequenceCEMPlanner`,
            `ForecasterWorldModelEnv`) pass it ``forecast_scale=``; at 0 (the default) it never asks, and
            plans as without the term.
        keep_out_weight (float, optional): weight (>= 0) of ``intrusion_t``, the gripper's depth below
            travel height near the forecast object outside a push. Defaults to ``KEEP_OUT_WEIGHT``
            (10.0).

    ``__call__(forecast [n, N, T, 2], actions [n, N, S, 4], context [n])`` returns rewards
    ``[n, N, T]``: ``-(|object_t - goal| + reach_weight * reach_t + uncertainty_weight * |std_t| +
    keep_out_weight * intrusion_t)``
    (``forecast_scale [n, N, T, 2]``: ``std_t``, needed when ``uncertainty_weight > 0``) with the
    object's position ``object_t`` = now + the forecast displacement (the push world model
    forecasts displacements, `data.target.relative`) and ``target_t`` the point behind
    ``object_t`` on the current object→goal line (`PRE_PUSH_DISTANCE` behind while approaching,
    `CONTACT_DISTANCE` once the gripper is low behind the object: the module docstring's two
    modes), ``reach_t`` the gripper's planar distance to it plus ``height_weight`` times its
    height error (pushing height only when behind the object on the line, travel height
    elsewhere), and ``intrusion_t`` the gripper's depth below travel height while within
    `KEEP_OUT_RADIUS` of ``object_t`` and not where it may be low (0 in contact mode).

    Raises:
        ValueError: a negative (or NaN) ``uncertainty_weight`` or ``keep_out_weight``.
    """

    in_keys = [OBJECT_POSE, GOAL, keys.obs_key("proprio")]

    def __init__(
        self,
        reach_weight: float = REACH_WEIGHT,
        height_weight: float = 2.0,
        uncertainty_weight: float = 0.0,
        keep_out_weight: float = KEEP_OUT_WEIGHT,
    ):
        for name, weight, what in [
            ("uncertainty_weight", uncertainty_weight, "the forecast's spread"),
            ("keep_out_weight", keep_out_weight, "the gripper low near the block"),
        ]:
            if not weight >= 0.0:  # NaN too
                raise ValueError(
                    f"PushObjective: {name} must be >= 0 (a penalty on {what}), found {weight}; use 0 "
                    "to plan without it"
                )
        self.reach_weight, self.height_weight = reach_weight, height_weight
        self.uncertainty_weight, self.keep_out_weight = uncertainty_weight, keep_out_weight

    @property
    def uses_forecast_scale(self) -> bool:
        return self.uncertainty_weight > 0.0

    def __call__(
        self,
        forecast: torch.Tensor,
        actions: torch.Tensor,
        context: TensorDictBase,
        forecast_scale: torch.Tensor | None = None,
    ) -> torch.Tensor:
        horizon, steps = forecast.shape[-2], actions.shape[-2]
        if steps % horizon:
            raise ValueError(
                f"PushObjective: {steps} action steps do not split into {horizon} forecast steps"
            )
        pose = context.get(OBJECT_POSE)[:, None, None]  # [n, 1, 1, 7]
        goal = context.get(GOAL)[:, None, None, :2]
        gripper_now = context.get(keys.obs_key("proprio"))[:, None, None, :3]

        obj = pose[..., :2] + forecast  # [n, N, T, 2]
        goal_distance = (goal - obj).norm(dim=-1)
        # The push line is fixed by where the object is now: a direction re-measured at every
        # forecast step would swing wildly as the object nears the goal.
        to_goal = goal - pose[..., :2]
        direction = to_goal / to_goal.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        # Contact mode (module docstring): the gripper is now low, behind the object, on the push
        # line; otherwise it goes to the pre-push point first.
        low_now = gripper_now[..., 2] - pose[..., 2] <= LOW
        pushing = low_now & behind_on_line(
            gripper_now[..., :2] - pose[..., :2], direction, CONTACT_DISTANCE - BEHIND_MARGIN
        )  # [n, 1, 1]
        standoff = torch.where(pushing, CONTACT_DISTANCE, PRE_PUSH_DISTANCE)
        pre_push = obj - standoff.unsqueeze(-1) * direction

        travel = (ACTION_SCALE / TRACKING_GAIN) * actions[..., :3].cumsum(-2)  # [n, N, S, 3]
        stride = steps // horizon
        gripper = gripper_now + travel[..., stride - 1 :: stride, :]  # at the forecast frames
        planar = (gripper[..., :2] - pre_push).norm(dim=-1)
        # Coming down is allowed a margin clear of the block (approach), pushing a margin into it.
        low_from = torch.where(pushing, CONTACT_DISTANCE - BEHIND_MARGIN, CONTACT_DISTANCE + BEHIND_MARGIN)
        may_be_low = behind_on_line(gripper[..., :2] - obj, direction, low_from)
        height = pose[..., 2] + CLEARANCE * (~may_be_low).float()
        reach = planar + self.height_weight * (gripper[..., 2] - height).abs()
        rewards = -(goal_distance + self.reach_weight * reach)
        if self.keep_out_weight:
            # Where the gripper may not be low, ``height`` is travel height: the depth below it.
            near = (gripper[..., :2] - obj).norm(dim=-1) < KEEP_OUT_RADIUS
            depth = (height - gripper[..., 2]).clamp_min(0.0)
            intrusion = (near & ~may_be_low & ~pushing).float() * depth
            rewards = rewards - self.keep_out_weight * intrusion
        if self.uses_forecast_scale:
            rewards = rewards - self.uncertainty_weight * self._spread(forecast_scale, forecast.shape)
        return rewards

    @staticmethod
    def _spread(forecast_scale: torch.Tensor | None, shape: torch.Size) -> torch.Tensor:
        """The norm of each step's 2-D standard deviation ``[n, N, T]``: the root mean square distance
        of the object from its forecast position, in metres like the goal distance (so the weight
        has no unit), and the same whichever way the table's axes point."""
        if forecast_scale is None:
            raise ValueError(
                "PushObjective(uncertainty_weight > 0) needs the forecast's standard deviation: call it "
                "with forecast_scale= (the planners do, from WorldModel.forecast_distribution)"
            )
        if forecast_scale.shape != shape:
            raise ValueError(
                f"PushObjective: forecast_scale has shape {list(forecast_scale.shape)}, expected the "
                f"forecast's {list(shape)}"
            )
        return forecast_scale.norm(dim=-1)


def behind_on_line(
    offset: torch.Tensor, direction: torch.Tensor, distance: float | torch.Tensor
) -> torch.Tensor:
    """Whether a planar offset from the object is at least ``distance`` behind it along the push
    ``direction`` and within `LINE_WIDTH` of the push line."""
    along = (offset * direction).sum(-1)
    across = (offset[..., 0] * direction[..., 1] - offset[..., 1] * direction[..., 0]).abs()
    return (along <= -distance) & (across <= LINE_WIDTH)
