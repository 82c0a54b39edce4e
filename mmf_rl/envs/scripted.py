"""A scripted pusher for `MultimodalPushEnv`, and the seeded rollout that records with it (or with
any other `Actor`, e.g. an MPC agent, plus the same exploration bursts).

The pusher is a small state machine over the gripper position:

    approach (travel above the pre-push point behind the object, on the goal line)
      -> descend (to pushing height) -> push (along object->goal, steering back onto the line)
      -> hold (object at the goal: step away, lift and wait; push again if it drifts off)

and a ``retreat`` (lift clear, then approach again) whenever the object gets away from the
fingers. Each episode draws a `PusherStyle` — speeds, approach error, action noise, pause and
re-approach rates — so that trajectories differ in tempo and contact pattern, and the object's
future is not a straight extrapolation of its past.

`MarkovPusher` is the same pusher as a function of the observation alone, the expert DAgger labels
with (see its docstring).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from mmf_rl.envs.push import MultimodalPushEnv

# Geometry of FetchPush, in metres (block half-size 0.025, closed fingers ~0.014 thick).
CONTACT_DISTANCE = 0.04  # gripper-site to object-centre distance when the fingers touch the block
PRE_PUSH_DISTANCE = 0.075  # where the push starts, behind the object on the goal line
CLEARANCE = 0.06  # travel height above the object's centre: fingertips clear the block's top
ACTION_SCALE = 0.05  # FetchPush moves the gripper target by 0.05 m per unit of action
MIN_START_DISTANCE = 0.08  # object-goal distance below which an episode would need no push
BACK_OFF_DISTANCE = 0.055  # closer than this, the fingers step away from the block before lifting
SLOW_DOWN_DISTANCE = 0.08  # closer than this to the goal, the push slows down
FREEZE_DIRECTION_DISTANCE = 0.06  # closer than this to the goal, the push direction stays fixed
RESUME_DISTANCE = 0.04  # an object this far from the goal is pushed again (success is < 0.05)
TRACKING_GAIN = 1.5  # the arm covers ~2/3 of a commanded move per step; ask for more
PUSH_HEIGHT_TOLERANCE = 0.008  # a gripper this close above pushing height is at it: the descent ends
PRE_PUSH_TOLERANCE = 0.015  # an approach this close to the pre-push point (in the plane) has arrived
LIFT_FIRST_DEPTH = 0.02  # an approach this far below travel height lifts straight up first
# The ranges `PusherStyle.sample` draws from.
TRAVEL_SPEEDS = (0.7, 1.0)
PUSH_LEADS = (0.01, 0.022)
STOP_RADII = (0.01, 0.025)


@dataclass(frozen=True)
class PusherStyle:
    """Per-episode behaviour of `ScriptedPusher`, drawn from the episode's generator by `sample`.

    Args:
        travel_speed (float): action-norm cap while travelling (FetchPush actions are in [-1, 1]).
        push_lead (float): metres per step the push target runs ahead of the contact point.
        approach_error (float): lateral error of the pre-push point, metres.
        action_noise (float): std of Gaussian noise added to every action.
        pause_rate (float): per-step probability of a pause.
        reapproach_rate (float): per-step probability, while pushing, of backing off to re-approach.
        stop_radius (float): object-goal distance at which the push stops, metres.
    """

    travel_speed: float  # action-norm cap while travelling (FetchPush actions are in [-1, 1])
    push_lead: float  # metres per step the push target runs ahead of the contact point
    approach_error: float  # lateral error of the pre-push point, metres
    action_noise: float  # std of Gaussian noise added to every action
    pause_rate: float  # per-step probability of a pause
    reapproach_rate: float  # per-step probability, while pushing, of backing off to re-approach
    stop_radius: float  # object-goal distance at which the push stops

    @classmethod
    def sample(cls, rng: np.random.Generator) -> PusherStyle:
        """A style drawn from the ranges the recorded episodes vary over.

        Args:
            rng (np.random.Generator): the episode's generator.

        Returns:
            The episode's style.
        """
        return cls(
            travel_speed=rng.uniform(*TRAVEL_SPEEDS),
            push_lead=rng.uniform(*PUSH_LEADS),
            approach_error=rng.normal(0.0, 0.008),
            action_noise=rng.uniform(0.0, 0.15),
            pause_rate=rng.choice([0.0, 0.03]),
            reapproach_rate=rng.choice([0.0, 0.0, 0.04]),
            stop_radius=rng.uniform(*STOP_RADII),
        )

    @classmethod
    def steady(cls) -> PusherStyle:
        """The middle of `sample`'s speeds, push lead and stop radius, no approach error, and no
        noise, pauses or re-approaches: a style whose actions depend on the observation only."""
        return cls(
            travel_speed=float(np.mean(TRAVEL_SPEEDS)),
            push_lead=float(np.mean(PUSH_LEADS)),
            approach_error=0.0,
            action_noise=0.0,
            pause_rate=0.0,
            reapproach_rate=0.0,
            stop_radius=float(np.mean(STOP_RADII)),
        )


class Actor(Protocol):
    """What `rollout` drives: `reset` with the episode's generator, then one `act` per step.

    ``act`` receives `MultimodalPushEnv`'s observation dict and returns a FetchPush action
    (float32 ``[4]`` in ``[-1, 1]``). An actor draws its randomness from the generator it was
    reset with (or seeds its own from it), so that episode ``i`` depends only on ``(seed, i)``.
    """

    def reset(self, rng: np.random.Generator) -> None: ...

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray: ...


class RandomBursts:
    """Exploration: with per-step probability ``probability``, a burst of 2-7 steps of one uniformly
    random move (the fingers' command left at 0). Drawn only when ``probability > 0``."""

    def __init__(self, probability: float = 0.0) -> None:
        if not 0.0 <= probability <= 1.0:
            raise ValueError(f"exploration must be a probability in [0, 1], found {probability}")
        self.probability = probability
        self.reset()

    def reset(self) -> None:
        self.steps, self.action = 0, np.zeros(4, dtype=np.float32)

    def draw(self, rng: np.random.Generator) -> np.ndarray | None:
        """This step's burst action, or ``None`` outside a burst."""
        if self.steps > 0:
            self.steps -= 1
            return self.action
        if self.probability and rng.random() < self.probability:
            self.steps = int(rng.integers(1, 7))
            self.action = np.r_[rng.uniform(-1.0, 1.0, 3), 0.0].astype(np.float32)
            return self.action
        return None


class ExploringActor:
    """``actor`` with `RandomBursts` on top: the scripted pusher's ``exploration`` for any `Actor`.

    Unlike the scripted pusher, the wrapped actor is asked for an action at every step, burst or
    not, and the burst overrides it: an agent that keeps a history of observations (an MPC
    agent's window) must see every one of them.
    """

    def __init__(self, actor: Actor, exploration: float = 0.0) -> None:
        self.actor, self.bursts = actor, RandomBursts(exploration)
        self.rng = np.random.default_rng(0)

    def reset(self, rng: np.random.Generator) -> None:
        self.actor.reset(rng)
        self.rng = rng
        self.bursts.reset()

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        action = self.actor.act(obs)
        burst = self.bursts.draw(self.rng)
        return action if burst is None else burst


@dataclass(frozen=True)
class _PushScene:
    """One observation seen by `ScriptedPusher`: positions, and the gripper's offset from the object
    along the push ``direction`` (``along``) and across it (``lateral``)."""

    grip: np.ndarray
    obj: np.ndarray
    to_goal: np.ndarray
    distance: float
    direction: np.ndarray
    lateral_axis: np.ndarray
    offset: np.ndarray
    along: float
    lateral: float

    @property
    def push_height(self) -> float:
        return self.obj[2]

    @property
    def at_push_height(self) -> bool:
        return self.grip[2] <= self.push_height + PUSH_HEIGHT_TOLERANCE

    @property
    def in_contact_window(self) -> bool:
        """The gripper is where a push keeps contact: behind the object, near the push line."""
        return abs(self.lateral) <= 0.03 and -0.12 <= self.along <= -0.02

    @property
    def travel_height(self) -> float:
        return self.obj[2] + CLEARANCE


class ScriptedPusher:
    """Pushes the object to the goal; call `reset` with the episode's generator, then `act`.

    Args:
        exploration (float, optional): per-step probability of an exploratory burst, 2-7 steps of
            one uniformly random move, after which the state machine carries on from wherever the
            gripper and the object ended up. Data for a world model needs them: without bursts the
            gripper moves sideways almost only while pushing, so a model learns "the object follows
            the gripper" and a planner exploits it; with them it also sees moves that miss or bump
            the block. Defaults to ``0``.
        steady (bool, optional): every episode in `PusherStyle.steady` instead of a style drawn per
            episode, so the actions are a function of the state and the phase: demonstrations
            without the pauses, noise and whims that a per-step imitation averages into a stalled
            action. Defaults to ``False``.

    Raises:
        ValueError: ``exploration`` is not in ``[0, 1]``.
    """

    def __init__(self, exploration: float = 0.0, steady: bool = False) -> None:
        self.bursts = RandomBursts(exploration)
        self.steady = steady
        self.reset(np.random.default_rng(0))

    def reset(self, rng: np.random.Generator) -> None:
        """Start an episode: its style is drawn from ``rng`` (unless steady), the phase is approach.

        Args:
            rng (np.random.Generator): the episode's generator, drawn from at every step after.
        """
        self.rng = rng
        self.style = PusherStyle.steady() if self.steady else PusherStyle.sample(rng)
        self.phase = "approach"
        self.pause_steps = 0
        self.direction = np.zeros(2)  # push direction in the plane, unit
        self.bursts.reset()

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """This step's action.

        Args:
            obs (dict[str, np.ndarray]): `MultimodalPushEnv`'s observation.

        Returns:
            A FetchPush action, float32 ``[4]`` in ``[-1, 1]`` (the fingers' command is 0).
        """
        # Drawn first and only when exploring, so episodes without it stay what they always were;
        # the state machine sleeps through a burst and carries on from wherever it left things.
        burst = self.bursts.draw(self.rng)
        if burst is not None:
            return burst
        scene = self._scene(obs)
        if self.pause_steps > 0:
            self.pause_steps -= 1
            return self._noisy(np.zeros(3))
        if self.phase != "hold" and self.rng.random() < self.style.pause_rate:
            self.pause_steps = int(self.rng.integers(2, 7))
        self._leave_push_if_done_or_lost(scene)
        return self._phase_action(scene)

    def _phase_action(self, scene: _PushScene) -> np.ndarray:
        """This step's action in the current phase (which may move on to the next one first)."""
        action = self._lift_off(scene) if self.phase in ("hold", "retreat") else None
        if action is None and self.phase in ("approach", "descend"):
            action = self._get_behind(scene)
        if action is not None:
            return action
        # push: aim just inside the block, on the push line, so the lateral error steers back onto
        # it; ease off near the goal, where a fast block slides past (or off the table).
        lead = self.style.push_lead * np.clip(scene.distance / SLOW_DOWN_DISTANCE, 0.3, 1.0)
        target = scene.obj[:2] - scene.direction * (CONTACT_DISTANCE - lead)
        return self._move(scene.grip, np.r_[target, scene.push_height], speed=1.0)

    def _scene(self, obs: dict[str, np.ndarray]) -> _PushScene:
        """Where gripper, object and goal are, in the frame of the push direction (updated here)."""
        grip, obj = obs["proprio"][:3], obs["object_pose"][:3]
        to_goal = obs["desired_goal"][:2] - obj[:2]
        distance = np.linalg.norm(to_goal)
        # Near the goal the object->goal bearing swings with every millimetre of lateral error;
        # pushing along the last bearing taken from afar keeps the push straight.
        if self.phase != "push" or distance > FREEZE_DIRECTION_DISTANCE:
            self.direction = to_goal / max(distance, 1e-6)
        direction = self.direction
        lateral_axis = np.array([-direction[1], direction[0]])
        offset = grip[:2] - obj[:2]  # gripper relative to the object, in the plane
        return _PushScene(
            grip,
            obj,
            to_goal,
            distance,
            direction,
            lateral_axis,
            offset,
            offset @ direction,
            offset @ lateral_axis,
        )

    def _leave_push_if_done_or_lost(self, scene: _PushScene) -> None:
        """Push -> hold at the goal, push -> retreat when the contact is lost (or on a whim), hold ->
        retreat when the object drifted off the goal."""
        if self.phase == "push":
            lost = not scene.in_contact_window
            if scene.distance < self.style.stop_radius or scene.to_goal @ scene.direction < 0.005:
                self.phase = "hold"
            elif lost or self.rng.random() < self.style.reapproach_rate:
                self.phase = "retreat"
        if self.phase == "hold" and scene.distance > RESUME_DISTANCE:
            self.phase = "retreat"

    def _lift_off(self, scene: _PushScene) -> np.ndarray | None:
        """Hold or retreat: back off and rise to travel height; then wait (hold) or approach anew
        (retreat, ``None``: the approach acts this step)."""
        grip, obj, offset = scene.grip, scene.obj, scene.offset
        if grip[2] < scene.travel_height - 0.01:
            if np.linalg.norm(offset) < BACK_OFF_DISTANCE:
                # Step away before lifting: lifting fingers pressed against the block can
                # drag it up and tip it over.
                away = offset / max(np.linalg.norm(offset), 1e-6)
                return self._move(grip, np.r_[obj[:2] + away * (BACK_OFF_DISTANCE + 0.01), grip[2]])
            return self._move(grip, np.r_[grip[:2], scene.travel_height])
        if self.phase == "hold":
            return self._move(grip, grip)  # done: wait above the table
        self.phase = "approach"
        return None

    def _get_behind(self, scene: _PushScene) -> np.ndarray | None:
        """Approach the pre-push point at travel height, then descend behind the object; ``None``
        once at pushing height (the push acts this step)."""
        grip, obj, direction = scene.grip, scene.obj, scene.direction
        if self.phase == "approach":
            pre_push = self._pre_push_point(scene)
            if np.linalg.norm(grip[:2] - pre_push) > PRE_PUSH_TOLERANCE:
                if grip[2] < scene.travel_height - LIFT_FIRST_DEPTH:
                    # Lift straight up first: a diagonal move from pushing height can clip the block.
                    return self._move(grip, np.r_[grip[:2], scene.travel_height])
                return self._move(grip, np.r_[pre_push, scene.travel_height])
            self.phase = "descend"
        behind = obj[:2] - direction * PRE_PUSH_DISTANCE
        if not scene.at_push_height:
            return self._move(grip, np.r_[behind, scene.push_height])
        self.phase = "push"
        return None

    def _pre_push_point(self, scene: _PushScene) -> np.ndarray:
        """Where the approach ends, in the plane: behind the object on the push line, off it by the
        style's approach error."""
        return (
            scene.obj[:2]
            - scene.direction * PRE_PUSH_DISTANCE
            + scene.lateral_axis * self.style.approach_error
        )

    def _move(self, grip: np.ndarray, target: np.ndarray, speed: float | None = None) -> np.ndarray:
        step = TRACKING_GAIN * (target - grip) / ACTION_SCALE
        cap = self.style.travel_speed if speed is None else speed
        norm = np.linalg.norm(step)
        if norm > cap:
            step *= cap / norm
        return self._noisy(step)

    def _noisy(self, step: np.ndarray) -> np.ndarray:
        step = step + self.rng.normal(0.0, self.style.action_noise, size=3)
        # The fourth action drives the fingers, which FetchPush keeps closed.
        return np.clip(np.r_[step, 0.0], -1.0, 1.0).astype(np.float32)


class MarkovPusher(ScriptedPusher):
    """`ScriptedPusher` as a function of the observation: its phase is inferred from the state at
    every call, never carried over from the calls before, so one state always gets one action.

    This is the expert DAgger labels with (`benchmarks/push/dagger.py`): DAgger assumes an expert policy of
    the state, asked at states the learner drives it to. The stateful pusher's phase follows the
    trajectory it drove itself; along the learner's it falls out of step with the state (still
    "approaching" when the learner is already behind the block at pushing height, "retreating" for
    many steps after one slip), so the same observation was labelled with contradictory actions
    (lift here, push there) and a policy trained on them learned to hover.

    The phase of a state, tried in order (then the stateful pusher's own rules and moves):

    * ``push``: the gripper is at pushing height behind the object, within the push's contact
      window (the push's stop rule turns it into ``hold`` at the goal);
    * ``hold``: the object is within the distance at which the pusher resumes a push (step away,
      lift and wait: the pusher's hold lasts that long);
    * ``descend``: the gripper is over the pre-push point (in the plane), or below travel height
      by more than an approach lifts straight up from, within the push's contact window (it goes
      down behind the object rather than up and round again);
    * ``retreat``: the gripper is that low anywhere else (back off if close to the block, lift);
    * ``approach``: anywhere else (travel to the pre-push point).

    The push direction is the object->goal bearing of the state (the stateful push freezes it near
    the goal). The style is `PusherStyle.steady`: the middle of the sampled speeds, push lead and
    stop radius, with no noise, pauses, re-approach whims or exploration bursts. ``reset`` ignores
    its generator.
    """

    def __init__(self) -> None:
        super().__init__(exploration=0.0, steady=True)

    def reset(self, rng: np.random.Generator | None = None) -> None:
        # Its own generator: the zero-noise draws of `_noisy` never change an action, and the
        # episode's generator is left to whoever else draws from it.
        super().reset(np.random.default_rng(0))

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        self.phase = "approach"  # any phase but push: the scene takes the state's own bearing
        scene = self._scene(obs)
        self.phase = self._phase_of(scene)
        self._leave_push_if_done_or_lost(scene)
        return self._phase_action(scene)

    def _phase_of(self, scene: _PushScene) -> str:
        if scene.at_push_height and scene.in_contact_window:
            return "push"  # `_leave_push_if_done_or_lost` stops it at the goal
        if scene.distance <= RESUME_DISTANCE:
            return "hold"
        low = scene.grip[2] < scene.travel_height - LIFT_FIRST_DEPTH
        if np.linalg.norm(scene.grip[:2] - self._pre_push_point(scene)) <= PRE_PUSH_TOLERANCE:
            return "descend"
        if low:
            return "descend" if scene.in_contact_window else "retreat"
        return "approach"


def episode_generator(seed: int, episode_index: int) -> np.random.Generator:
    """The generator of episode ``episode_index``: a function of (seed, index) only."""
    return np.random.default_rng(np.random.SeedSequence([seed, episode_index]))


def reset_for_push(env: MultimodalPushEnv, rng: np.random.Generator):
    """Reset until the goal is far enough from the object that reaching it takes a push."""
    while True:
        obs, info = env.reset(seed=int(rng.integers(2**31)))
        if np.linalg.norm(obs["desired_goal"][:2] - obs["object_pose"][:2]) >= MIN_START_DISTANCE:
            return obs, info


def rollout(
    env: MultimodalPushEnv,
    seed: int,
    episode_index: int,
    steps: int,
    exploration: float = 0.0,
    actor: Actor | None = None,
    steady: bool = False,
) -> dict[str, np.ndarray]:
    """Run one episode and return its per-step arrays.

    The scripted pusher acts, or ``actor`` with the same exploration bursts on top (`ExploringActor`).
    Either is reset with the episode's generator after the env, so the start and the actor's draws
    depend only on ``(seed, episode_index)``. The env is reset until the object starts far enough
    from the goal that reaching it takes a push.

    Args:
        env (MultimodalPushEnv): the env, reset here.
        seed (int): the recording's seed.
        episode_index (int): the episode's index; with ``seed`` it fixes the episode.
        steps (int): frames to record (the episode is not cut at success).
        exploration (float, optional): per-step probability of a random-move burst (`ScriptedPusher`).
            Defaults to ``0``.
        actor (Actor, optional): acts instead of the scripted pusher (e.g. an MPC agent).
        steady (bool, optional): the scripted pusher's one steady style (`ScriptedPusher`). Defaults
            to ``False``.

    Returns:
        The episode's arrays; frame ``t`` holds the observation before action ``t``: ``image``
        ``uint8 [steps, h, w, 3]``; ``force``, ``proprio``, ``object_pose``, ``goal``, ``action``
        ``float32 [steps, d]``; ``success`` ``bool [steps]`` (object within the env's threshold of
        the goal).

    Raises:
        ValueError: ``steps < 1``.
    """
    if steps < 1:
        raise ValueError(f"steps={steps}: an episode needs at least 1 step.")
    rng = episode_generator(seed, episode_index)
    obs, _ = reset_for_push(env, rng)
    pusher = ScriptedPusher(exploration, steady) if actor is None else ExploringActor(actor, exploration)
    pusher.reset(rng)
    frames: dict[str, list] = {k: [] for k in ("image", "force", "proprio", "object_pose", "goal", "action")}
    success = []
    for _ in range(steps):
        action = pusher.act(obs)
        for key in ("image", "force", "proprio", "object_pose"):
            frames[key].append(obs[key])
        frames["goal"].append(obs["desired_goal"])
        frames["action"].append(action)
        success.append(np.linalg.norm(obs["achieved_goal"] - obs["desired_goal"]) < env.distance_threshold)
        obs, *_ = env.step(action)
    arrays = {k: np.stack(v).astype(np.uint8 if k == "image" else np.float32) for k, v in frames.items()}
    arrays["success"] = np.array(success)
    return arrays
