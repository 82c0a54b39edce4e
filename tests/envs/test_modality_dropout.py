from __future__ import annotations

import pytest
import torch
from torchrl.envs import SerialEnv, TransformedEnv

from mmf_rl import keys
from mmf_rl.envs.modality_dropout import (
    GeometricBursts,
    ModalityDropout,
    UniformBursts,
    outage_start_prob,
    replay_outages,
)
from mmf_rl.envs.torchrl_env import MultimodalPushTorchEnv
from tests.envs.stamp_env import stamp_envs


# A rollout's time grows with its env-steps, the fewer steps of a batch of more envs the cheaper: the
# statistics below draw as many observations from 16 envs as they did from 4 over 4 times the steps.
def dropout_rollout(dropout: ModalityDropout, num_envs: int = 4, steps: int = 120, max_steps: int = 1000):
    env = TransformedEnv(stamp_envs(num_envs, max_steps), dropout)
    try:
        return env.rollout(steps, break_when_any_done=False)
    finally:
        env.close()


def presence_over_time(td, name: str) -> torch.Tensor:
    """``[envs, steps + 1]``: the reset observation, then every step's."""
    return torch.cat([td[keys.present_key(name)][:, :1], td["next", keys.PRESENT, name]], dim=1)


def runs_of_absence(present: torch.Tensor) -> list[int]:
    """Lengths of the runs of False in each row, without runs cut by the rollout's ends."""
    lengths = []
    for row in present.tolist():
        run, started_inside = 0, False
        for i, p in enumerate(row):
            if not p:
                if run == 0:
                    started_inside = i > 0
                run += 1
            else:
                if run and started_inside:
                    lengths.append(run)
                run = 0
    return lengths


def test_dropout_zeroes_data_and_clears_presence():
    td = dropout_rollout(
        ModalityDropout(["image", "force"], outage_prob=0.2, bursts=UniformBursts(1, 4), seed=0)
    )
    nxt = td["next"]
    for name in ("image", "force"):
        absent = ~nxt[keys.PRESENT, name]
        assert 0 < absent.float().mean() < 1
        obs = nxt[keys.obs_key(name)].flatten(2)
        assert (obs[absent] == 0).all(), "an absent modality carries zeros"
        assert (obs[~absent] != 0).all(), "a present modality keeps its data"
    assert nxt[keys.PRESENT, "proprio"].all(), "modalities not listed never fail"


def test_dropout_is_reproducible_from_its_seed_and_independent_per_env():
    def pattern(seed):
        td = dropout_rollout(ModalityDropout(["image", "force"], outage_prob=0.1, seed=seed), steps=60)
        return torch.stack([presence_over_time(td, m) for m in ("image", "force")])

    first = pattern(3)
    assert torch.equal(first, pattern(3))
    assert not torch.equal(first, pattern(4))
    assert not torch.equal(first[:, 0], first[:, 1]), "each env draws its own outages"


@pytest.mark.parametrize("bursts", [UniformBursts(2, 4), GeometricBursts(3.0)])
def test_dropout_bursts_have_the_configured_lengths(bursts):
    td = dropout_rollout(
        ModalityDropout(["force"], outage_prob=0.15, bursts=bursts, seed=1), num_envs=16, steps=75
    )
    lengths = torch.tensor(runs_of_absence(presence_over_time(td, "force")))
    assert len(lengths) > 40
    if isinstance(bursts, UniformBursts):
        assert set(lengths.tolist()) == {2, 3, 4}
    else:
        assert lengths.min() == 1 and lengths.max() > 6
        assert abs(lengths.float().mean().item() - 3.0) < 0.6


def test_replay_outages_gives_each_modality_its_measured_fraction_and_bursts():
    outages = {
        "force": {"fraction": 0.2, "mean_burst": 4.0},
        "image": {"fraction": 0.05, "mean_burst": 2.0},
        "proprio": {"fraction": 0.0, "mean_burst": 0.0},
    }
    replay = replay_outages(outages, seed=3)
    assert [t.modalities for t in replay] == [["force"], ["image"]]  # nothing to replay for proprio
    td = dropout_rollout(replay, num_envs=16, steps=150)
    for name in ("force", "image"):
        present = presence_over_time(td, name)
        assert abs((~present).float().mean().item() - outages[name]["fraction"]) < 0.04, name
        lengths = torch.tensor(runs_of_absence(present)).float()
        assert (
            abs(lengths.mean().item() - outages[name]["mean_burst"]) < 0.25 * outages[name]["mean_burst"]
        ), name
    assert presence_over_time(td, "proprio").all()
    assert outage_start_prob(0.2, 4.0) == pytest.approx(0.0625)  # 4 / (4 + 1 / p) = 0.2
    with pytest.raises(ValueError, match="no modality .* has outages to replay"):
        replay_outages({"proprio": outages["proprio"]})


def test_dropout_per_episode_holds_for_the_whole_episode():
    td = dropout_rollout(
        ModalityDropout(["image"], outage_prob=0.5, outage="episode", seed=0),
        num_envs=8,
        steps=40,
        max_steps=10,
    )
    present = presence_over_time(td, "image")  # 4 episodes of 10 steps per env
    steps = torch.arange(present.shape[1])
    for env in range(present.shape[0]):
        for episode in range(4):
            # Step 10 of an episode is its terminal observation; the reset observation follows in the root td.
            chunk = present[env, (steps > 10 * episode) & (steps <= 10 * episode + 9)]
            assert chunk.all() or not chunk.any()
    assert 0 < present.float().mean() < 1


def test_dropout_reset_clears_the_outages_of_the_envs_that_reset():
    env = TransformedEnv(
        stamp_envs(2), ModalityDropout(["force"], outage_prob=1.0, bursts=UniformBursts(5, 5))
    )
    try:
        td = env.reset()
        # An outage starts at the reset observation: 5 absent observations, then one present.
        for _ in range(3):
            td = env.step(env.rand_action(td))["next"]
        td["_reset"] = torch.tensor([[True], [False]])
        td = env.reset(td)
        present = [td[keys.present_key("force")].tolist()]
        for _ in range(5):
            td = env.step(env.rand_action(td))["next"]
            present.append(td[keys.present_key("force")].tolist())
        # env 0 restarted its 5-step outage at the reset; env 1 finished its outage 2 steps later.
        assert [p[0] for p in present] == [False] * 5 + [True]
        assert [p[1] for p in present] == [False, False, True, False, False, False]
    finally:
        env.close()


def episode_presence(present: torch.Tensor, episode_steps: int) -> torch.Tensor:
    """``[envs, episodes, episode_steps]``: each episode's observations, from its reset observation on,
    cut out of a rollout of whole episodes (``presence_over_time``; after its first episode a step's
    terminal observation is replaced by the next reset's in the root td, which this reads)."""
    envs, length = present.shape
    episodes = (length - 1) // episode_steps
    return present[:, : episodes * episode_steps].reshape(envs, episodes, episode_steps)


def test_dropout_dies_stays_dead_until_the_episode_ends():
    dropout = ModalityDropout(
        ["force"], outage_prob=0.7, outage="dies", dies_after=UniformBursts(2, 6), seed=5
    )
    td = dropout_rollout(dropout, num_envs=4, steps=80, max_steps=10)
    # The root td holds every episode's reset observation and its steps until the last one.
    present = td[keys.present_key("force")]  # [envs, steps]: observation t of episode t // 10
    episodes = episode_presence(torch.cat([present, present[:, -1:]], 1), 10)
    deaths = []
    for row in episodes.reshape(-1, 10).tolist():
        alive = sum(row)
        assert row == [True] * alive + [False] * (10 - alive), (
            "a dead sensor never comes back within its episode"
        )
        deaths.append(alive)
    assert set(deaths) == {2, 3, 4, 5, 6, 10}, "it dies after 2..6 readings, or survives (p = 0.3)"
    nxt = td["next"]
    absent = ~nxt[keys.PRESENT, "force"]
    assert (nxt[keys.obs_key("force")][absent] == 0).all() and (
        nxt[keys.obs_key("force")][~absent] != 0
    ).all()


def test_dropout_dies_is_seeded_and_revived_by_a_reset():
    def deaths(seed):
        td = dropout_rollout(
            ModalityDropout(["image"], outage_prob=1.0, outage="dies", seed=seed),
            num_envs=3,
            steps=150,
            max_steps=50,
        )
        return td[keys.present_key("image")].reshape(3, 3, 50).sum(-1)  # readings before death, per episode

    first = deaths(0)
    assert torch.equal(first, deaths(0)) and not torch.equal(first, deaths(1))
    assert first.min() >= 1 and first.max() <= 49, (
        "UniformBursts(1, 49): dies mid-episode, after the reset reading"
    )
    assert len(set(first.flatten().tolist())) > 3, "each env and episode draws its own death step"


@pytest.fixture(scope="module")
def push_envs():
    """Two real MuJoCo push envs of 12-step episodes, one pair (and GL contexts, ~1 s each) for the
    outage types below: each wraps it in a `TransformedEnv` of its own (which leaves its base env open)
    and seeds it. 8 px frames: the smallest the env renders; a frame is never all zero at any size."""
    env = SerialEnv(2, lambda: MultimodalPushTorchEnv(image_size=8, max_episode_steps=12))
    yield env
    env.close()


@pytest.mark.parametrize("outage", ["bursts", "episode", "dies"])
def test_every_outage_type_on_the_push_env(outage, push_envs):
    """The real MuJoCo env: outages zero the sensor's data and clear its flag; the type shapes when."""
    dropout = ModalityDropout(
        ["image", "force"],
        outage_prob={"image": 0.5, "force": 0.5},
        outage=outage,
        bursts=UniformBursts(2, 3),
        dies_after=UniformBursts(3, 8),
        seed=1,
    )
    env = TransformedEnv(push_envs, dropout)
    env.set_seed(0)
    torch.manual_seed(0)
    td = env.rollout(36, break_when_any_done=False)
    for name in ("image", "force"):
        present = td[keys.present_key(name)]  # [2, 36]: 3 episodes of 12 observations from the reset on
        absent = ~td["next", keys.PRESENT, name]
        data = td["next", keys.obs_key(name)].flatten(2)
        assert (data[absent] == 0).all()
        if name == "image":  # the force is zero without contact; a frame never is
            assert (data[~absent].abs().sum(-1) > 0).all()
        assert 0 < present.float().mean() < 1
        for row in present.reshape(-1, 12).tolist():
            alive = sum(row)
            if outage == "episode":
                assert alive in (0, 12)
            elif outage == "dies":
                assert row == [True] * alive + [False] * (12 - alive) and (alive == 12 or 3 <= alive <= 8)
    assert td["next", keys.PRESENT, "proprio"].all()


def test_unknown_outage_type_is_refused():
    with pytest.raises(ValueError, match=r"outage='mid'.*\['bursts', 'episode', 'dies'\]"):
        ModalityDropout(["image"], outage="mid")
