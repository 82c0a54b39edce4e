"""Shared TensorDict fixtures: small multimodal batches and a synthetic forecasting task."""

from __future__ import annotations

import contextlib
import io
import itertools
import os
import shutil
import subprocess
import traceback
from collections.abc import Callable
from pathlib import Path

# pytest-xdist runs the suite in worker processes (`make test`: `-n 2`, one per core of a 2-core
# machine); each worker then runs on one thread, and so does every process it starts (the CLI
# subprocesses, torchrun's ranks, spawned workers read OMP_NUM_THREADS): two workers of two threads
# each would oversubscribe the cores, and OpenMP threads spin-wait for a busy core. Set before torch and
# numpy are imported, which size their thread pools from it. Run alone (no xdist), the tests use up to
# 2 threads (TEST_THREADS).
os.environ.update({"OMP_NUM_THREADS": "1"} if "PYTEST_XDIST_WORKER" in os.environ else {})

import pytest
import torch
from tensordict import TensorDict

from mmf_rl import keys
from mmf_rl.keys import ModalitySpec
from mmf_rl.models import ForecasterConfig, MultimodalForecaster

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")

XDIST_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
TEST_THREADS = 1 if XDIST_WORKER is not None else min(2, os.cpu_count() or 1)
torch.set_num_threads(TEST_THREADS)


def run_bench(name: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    """``mmf-rl bench NAME ARGS`` from ``cwd``, in this process as the CLI runs it (a subprocess would
    spend seconds importing torch again): its exit code, stdout and stderr, as a subprocess gives them.
    torch's thread count is restored after (a script may set its own)."""
    from mmf_rl.cli import main as cli

    stdout, stderr, threads = io.StringIO(), io.StringIO(), torch.get_num_threads()
    with contextlib.chdir(cwd), contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        try:
            code = cli(["bench", name, *args])
        except Exception:  # noqa: BLE001 - a crash is exit code 1 with its traceback, as in a subprocess
            traceback.print_exc()
            code = 1
    torch.set_num_threads(threads)
    return subprocess.CompletedProcess(
        ["mmf-rl", "bench", name, *args], code, stdout.getvalue(), stderr.getvalue()
    )


# The slow tier: `make test` runs every test, `make test-fast` (-m "not slow") leaves these out. A test
# reading a recorded or converted dataset (directly or through a run trained on it) is slow by its
# fixture: the session's push recording, tests/test_record.py's and tests/eval/test_eval_command.py's
# recordings, tests/benchmarks/pedestrians/test_scoring.py's converted ETH/UCY fold. The other slow
# tests (subprocesses, scripts run end to end, the docs' build, long training) are marked where they are
# written.
SLOW_FIXTURES = {"recorded_push_root", "recorded", "policy_recorded", "faulty_push_root", "eth_fold"}


def module_fixture_group(item: pytest.Item) -> str | None:
    """The test's file when it uses a module- or class-scoped fixture, else None."""
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return None
    for name in info.names_closure:
        definitions = info.name2fixturedefs.get(name)
        if definitions and definitions[-1].scope in ("module", "class"):
            return item.nodeid.split("::")[0]
    return None


# tryfirst: pytest-xdist's own hook reads the `xdist_group` marks added here.
@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if SLOW_FIXTURES.intersection(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)
        # Under `pytest -n 2 --dist loadgroup` (`make test`) the tests are handed to the workers one by
        # one, except those of one xdist_group, which one worker runs. A module-scoped fixture (a
        # recording, a trained run, an env) is built once per worker that runs a test of its module:
        # the tests of a file that uses one form a group, so it is built once.
        group = module_fixture_group(item)
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))


HISTORY = 4
HORIZON = 5
TARGET_DIM = 2

SMALL_MODALITIES = [
    ModalitySpec("image", "image", (3, 16, 16), encoder_kwargs={"channels": (8, 16)}),
    ModalitySpec("force", "sequence", (6,)),
    ModalitySpec("proprio", "sequence", (5,), encoder="mlp"),
]


def presence_patterns(names: list[str]) -> list[tuple[str, ...]]:
    """Every non-empty subset of ``names``."""
    return [c for r in range(1, len(names) + 1) for c in itertools.combinations(names, r)]


# Small sizes of every registered model, for tests that build each of them by name.
SMALL_MODEL_SIZES = {
    "forecaster": {"d_model": 16, "d_latent": 4, "num_heads": 2, "mlp_hidden": 32, "head_hidden": 32},
    "lf_lstm": {"d_model": 16, "head_hidden": 32},
    "mvae": {"d_model": 16, "d_latent": 4, "head_hidden": 32},
    "mult": {"d_model": 16, "head_hidden": 32},
    "constant_velocity": {},
}


def small_registered_model(name: str, **settings):
    """The registered model ``name`` at ``SMALL_MODEL_SIZES`` over ``SMALL_MODALITIES``, with its other
    ``settings`` (e.g. ``prior="learned"``, or a composed model config group's: the sizes stay small).

    Seeded, in eval mode.
    """
    from mmf_rl.models import build_model

    torch.manual_seed(0)
    model_cfg = {"name": name, **settings, **SMALL_MODEL_SIZES[name]}
    return build_model(model_cfg, list(SMALL_MODALITIES), HISTORY, HORIZON, TARGET_DIM).eval()


def make_batch(
    batch_size: int,
    modalities=SMALL_MODALITIES,
    present: dict[str, torch.Tensor] | None = None,
    seed: int = 0,
    history: int = HISTORY,
    horizon: int = HORIZON,
    target_dim: int = TARGET_DIM,
) -> TensorDict:
    """A batch following ``mmf_rl.keys`` with random content; all modalities present by default."""
    g = torch.Generator().manual_seed(seed)
    data = {}
    for spec in modalities:
        shape = (batch_size, *spec.obs_shape(history))
        if spec.kind == "image":
            data[spec.obs_key] = torch.randint(0, 256, shape, generator=g, dtype=torch.uint8)
        else:
            data[spec.obs_key] = torch.randn(shape, generator=g)
        mask = None if present is None else present.get(spec.name)
        data[spec.present_key] = torch.ones(batch_size, dtype=torch.bool) if mask is None else mask.clone()
    data[keys.TARGET] = torch.randn(batch_size, horizon, target_dim, generator=g)
    data[keys.TARGET_PAST] = torch.randn(batch_size, history, target_dim, generator=g)
    return TensorDict(data, batch_size=[batch_size])


def assert_each_sample_alone_gives_its_batch_result(model, batch, out_keys) -> None:
    """One pass over a batch mixing presence patterns gives every sample what it gets alone."""
    with torch.no_grad():
        together = model(batch.clone())
        for i in range(batch.shape[0]):
            alone = model(batch[i : i + 1].clone())
            for key in out_keys:
                torch.testing.assert_close(alone.get(key)[0], together.get(key)[i], rtol=1e-4, atol=1e-5)


def assert_forecast_under_actions_is_one_forward_per_candidate(model, batch, actions) -> tuple:
    """``model.forecast_under_actions(batch, actions)`` equals one eval forward per candidate ``k`` with
    ``actions[:, k]`` as the future action; returns its ``(loc, scale)``."""
    with torch.no_grad():
        loc, scale = model.forecast_under_actions(batch, actions)
        for k in range(actions.shape[1]):
            td = batch.clone()
            td.set(keys.FUTURE_ACTION, actions[:, k])
            out = model(td)
            torch.testing.assert_close(loc[:, k], out.get(keys.FORECAST_LOC), rtol=1e-4, atol=1e-5)
            torch.testing.assert_close(scale[:, k], out.get(keys.FORECAST_SCALE), rtol=1e-4, atol=1e-5)
    return loc, scale


def assert_a_few_steps_reduce_the_loss(
    model, loss_module, action_shape: tuple[int, int] | None = None
) -> None:
    """15 Adam steps on a fixed mixed-presence batch cut the summed ``loss_*`` by at least 20%.

    ``action_shape = (S, A)`` adds random ``"future_action"`` for a world model."""
    names = [s.name for s in SMALL_MODALITIES]
    pattern = torch.arange(8) % 4
    batch = make_batch(8, present={n: (pattern != i) for i, n in enumerate(names)}, seed=2)
    if action_shape is not None:
        batch.set(
            keys.FUTURE_ACTION, torch.randn(8, *action_shape, generator=torch.Generator().manual_seed(3))
        )
    optimizer = torch.optim.Adam(model.parameters(), lr=5e-3)

    def total():
        return sum(v for k, v in loss_module(batch).items() if k.startswith("loss_"))

    torch.manual_seed(0)
    before = torch.stack([total().detach() for _ in range(4)]).mean()
    for _ in range(15):
        optimizer.zero_grad()
        total().backward()
        optimizer.step()
    after = torch.stack([total().detach() for _ in range(4)]).mean()
    assert after < before - 0.2 * before.abs(), (float(before), float(after))


@pytest.fixture
def small_config() -> ForecasterConfig:
    return ForecasterConfig(
        modalities=list(SMALL_MODALITIES),
        history=HISTORY,
        horizon=HORIZON,
        target_dim=TARGET_DIM,
        d_model=16,
        d_latent=4,
        num_heads=2,
        mlp_hidden=32,
        head_hidden=32,
    )


@pytest.fixture
def small_model(small_config) -> MultimodalForecaster:
    torch.manual_seed(0)
    return MultimodalForecaster(small_config)


@pytest.fixture
def batch() -> TensorDict:
    return make_batch(8)


@pytest.fixture
def mixed_batch() -> TensorDict:
    """One sample per non-empty presence pattern of the small modalities."""
    names = [s.name for s in SMALL_MODALITIES]
    patterns = presence_patterns(names)
    present = {n: torch.tensor([n in p for p in patterns]) for n in names}
    return make_batch(len(patterns), present=present, seed=1)


# --- a synthetic task whose future depends on more than one modality --------------------------

SYNTH_DT = 0.1


def synthetic_motion_task(num_samples: int, seed: int, history: int = 8, horizon: int = 8) -> TensorDict:
    """2-D points with constant acceleration, seen through three noisy sensors.

    * ``pos``: position history (noisy) — velocity only by differencing, so poorly;
    * ``vel``: velocity history (noisy, but much better than differenced positions);
    * ``force``: the acceleration (noisy), which nothing else shows.

    The target is the future displacement from the last true position, so an accurate forecast
    needs velocity (``vel``, or worse ``pos``) **and** acceleration (``force``). ``"target_past"``
    holds the true position history for the constant-velocity baseline.
    """
    g = torch.Generator().manual_seed(seed)
    t_past = torch.arange(-history + 1, 1, dtype=torch.float32) * SYNTH_DT
    t_future = torch.arange(1, horizon + 1, dtype=torch.float32) * SYNTH_DT
    v0 = torch.randn(num_samples, 1, 2, generator=g)
    acc = 3.0 * torch.randn(num_samples, 1, 2, generator=g)
    p0 = torch.randn(num_samples, 1, 2, generator=g)

    def position(t):
        return p0 + v0 * t[None, :, None] + 0.5 * acc * t[None, :, None] ** 2

    pos_past = position(t_past)
    vel_past = v0 + acc * t_past[None, :, None]
    obs_pos = pos_past + 0.02 * torch.randn(pos_past.shape, generator=g)
    obs_vel = vel_past + 0.1 * torch.randn(vel_past.shape, generator=g)
    obs_force = acc.expand(-1, history, -1) + 0.3 * torch.randn(num_samples, history, 2, generator=g)
    target = position(t_future) - pos_past[:, -1:]
    ones = torch.ones(num_samples, dtype=torch.bool)
    return TensorDict(
        {
            keys.obs_key("pos"): obs_pos,
            keys.obs_key("vel"): obs_vel,
            keys.obs_key("force"): obs_force,
            keys.present_key("pos"): ones,
            keys.present_key("vel"): ones.clone(),
            keys.present_key("force"): ones.clone(),
            keys.TARGET: target,
            keys.TARGET_PAST: obs_pos - pos_past[:, -1:],
        },
        batch_size=[num_samples],
    )


SYNTH_MODALITIES = [
    ModalitySpec("pos", "sequence", (2,)),
    ModalitySpec("vel", "sequence", (2,)),
    ModalitySpec("force", "sequence", (2,)),
]


@pytest.fixture(scope="session")
def synthetic_task() -> dict[str, TensorDict]:
    return {"train": synthetic_motion_task(4096, seed=0), "test": synthetic_motion_task(1024, seed=1)}


class InMemoryLoader:
    """A loader over an in-memory TensorDict with the WindowLoader protocol: one epoch per
    iteration, a seeded permutation per ``set_epoch``."""

    def __init__(self, data: TensorDict, batch_size: int, seed: int = 0):
        self.data, self.batch_size, self.seed, self.epoch = data, batch_size, seed, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return self.data.shape[0] // self.batch_size

    def __iter__(self):
        order = torch.randperm(
            self.data.shape[0], generator=torch.Generator().manual_seed(self.seed * 1000 + self.epoch)
        )
        for i in range(len(self)):
            yield self.data[order[i * self.batch_size : (i + 1) * self.batch_size]]


def file_states(root: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``root`` by its path relative to it: its size and modification time (ns)."""
    return {
        str(path.relative_to(root)): (path.stat().st_size, path.stat().st_mtime_ns)
        for path in root.rglob("*")
        if path.is_file()
    }


@contextlib.contextmanager
def left_unchanged(root: Path, what: str):
    """Yields ``root``; after the block, fails naming the files a test added, changed or removed under
    it. The session's recording and trained runs are shared by every test that reads them: a test that
    writes into one must copy it first (into its ``tmp_path``)."""
    before = file_states(root)
    yield root
    after = file_states(root)
    changed = sorted(name for name in before.keys() | after.keys() if before.get(name) != after.get(name))
    assert not changed, f"a test wrote into the session's {what} {root} (copy it first): {changed[:10]}"


def built_once(tmp_path_factory, name: str, build: Callable[[Path], object]) -> Path:
    """A directory ``build(directory)`` filled once for the whole test session, ``directory`` returned.

    Alone, that is a session fixture's ``tmp_path_factory.mktemp(name)``. Under pytest-xdist every
    worker process runs the session fixtures of its own: the recording and the trained runs would be
    made once per worker, each costing its worker tens of seconds. So, as pytest-xdist documents, the
    directory sits in the temp root all workers of one run share (the parent of each worker's basetemp),
    built under a file lock: the first worker to need it builds it while the others wait, then they all
    read the same one. The ``.built`` marker, created only after ``build`` returned, tells a finished
    directory from one a failed build left (a later worker removes that and builds again, failing with
    the same error in its own tests).
    """
    if XDIST_WORKER is None:
        directory = tmp_path_factory.mktemp(name)
        build(directory)
        return directory
    from filelock import FileLock

    directory = tmp_path_factory.getbasetemp().parent / name
    built = directory / ".built"
    with FileLock(f"{directory}.lock"):
        if not built.is_file():
            shutil.rmtree(directory, ignore_errors=True)
            directory.mkdir()
            build(directory)
            built.touch()
    return directory


@pytest.fixture(scope="session")
def recorded_push_root(tmp_path_factory):
    """A small multimodal push dataset recorded by the project's own recorder (real MuJoCo data)."""
    from mmf_rl.record import RecordConfig, record

    def record_push(directory: Path) -> None:
        record(RecordConfig(out=directory / "push", episodes=6, steps=40, image_size=32, seed=3))

    root = built_once(tmp_path_factory, "recorded", record_push) / "push"
    with left_unchanged(root, "recording"):
        yield root


@pytest.fixture(scope="session")
def push_cache_dir(tmp_path_factory) -> Path:
    """One window cache directory for the runs on the recording: entries are keyed by dataset and config
    (and locked: the xdist workers share this one, each reading the caches the first one built)."""
    return built_once(tmp_path_factory, "window-cache", lambda directory: None)


def push_train_overrides(root, cache_dir, run_dir, steps: int = 6, every: int = 3) -> list[str]:
    """`mmf-rl train` overrides for a tiny, fast run on ``recorded_push_root``: validated and checkpointed
    ``every`` steps."""
    return [
        f"data.root={root}",
        f"data.cache_dir={cache_dir}",
        f"run_dir={run_dir}",
        "data.image_size=[32,32]",
        "data.history=4",
        "data.horizon=3",
        "data.split_fractions=[0.5,0.25,0.25]",
        "model.d_model=16",
        "model.d_latent=4",
        "model.num_heads=2",
        "model.mlp_hidden=32",
        "model.head_hidden=32",
        f"trainer.total_steps={steps}",
        "trainer.batch_size=16",
        "trainer.log_every=2",
        f"trainer.eval_every={every}",
        f"trainer.checkpoint_every={every}",
        "trainer.warmup_steps=2",
        "trainer.progress_bar=false",
        "logger=csv",
        "num_workers=0",
    ]


@pytest.fixture(scope="session")
def push_forecaster_run(recorded_push_root, push_cache_dir, tmp_path_factory):
    """A tiny forecaster trained by `mmf-rl train` (data=push, `push_train_overrides`' 6 steps, calibrated
    at the end) on the recorded push data: the one trained run of every test that only reads one."""
    from mmf_rl.cli import main as cli

    def train(directory: Path) -> None:
        run = directory / "run"
        assert cli(["train", *push_train_overrides(recorded_push_root, push_cache_dir, run)]) == 0

    run = built_once(tmp_path_factory, "push_forecaster", train) / "run"
    with left_unchanged(run, "trained run"):
        yield run


@pytest.fixture(scope="session")
def push_world_model_run(recorded_push_root, tmp_path_factory):
    """A tiny action-conditioned world model trained by `mmf-rl train data=push_world_model` on the
    recorded push data (H = 4, T = 3, 32 px): the real pipeline end to end, for the RL glue tests."""
    from mmf_rl.cli import main as cli

    def train(base: Path) -> None:
        overrides = push_train_overrides(recorded_push_root, base / "cache", base / "run", steps=6)
        assert cli(["train", "data=push_world_model", *overrides]) == 0

    run = built_once(tmp_path_factory, "world_model", train) / "run"
    with left_unchanged(run, "world model run"):
        yield run


@pytest.fixture(scope="session")
def push_world_model(push_world_model_run):
    """The world model of `push_world_model_run`, loaded for planning."""
    from mmf_rl.rl import WorldModel

    return WorldModel.from_checkpoint(push_world_model_run / "checkpoints")


@pytest.fixture(scope="module")
def push_history_env(push_world_model):
    """The real push env (32 px, as recorded) emitting the world model's ``"history"`` window and
    ``"is_init"``; one env (one GL context) per test module."""
    from torchrl.envs import Compose, InitTracker, TransformedEnv

    from mmf_rl.envs import MultimodalPushTorchEnv

    env = TransformedEnv(
        MultimodalPushTorchEnv(image_size=32), Compose(push_world_model.history_window(), InitTracker())
    )
    env.set_seed(0)
    yield env
    env.close()


@pytest.fixture(scope="session")
def ethucy_cut(tmp_path_factory) -> tuple[Path, Path]:
    """``(raw, data)``: a cut of the real ETH/UCY files (`cut_ethucy_raw`: 6 agents within the first 30
    steps of each file) and its conversion, every fold, made once for the session (every xdist worker
    reads the same one) by benchmarks/ethucy.py from ``--raw`` as its first invocation makes it (the
    conversion takes tens of seconds); skipped without the files. Both read only: a benchmark run writes
    its window cache and held-out configs beside the fold configs, so a test running one reads a copy of
    them (tests/benchmarks/conftest.py: `ethucy_fold_configs`); a test of one fold reads its config with
    a window cache of its own."""
    from benchmarks import ethucy as bench
    from mmf_rl.datasets import ethucy
    from tests.datasets.conftest import SHARED_DATA, cut_ethucy_raw

    if not (SHARED_DATA / "ethucy" / "trajectories").is_dir():
        pytest.skip(f"ETH/UCY data not at {SHARED_DATA / 'ethucy'} (set MMF_RL_SHARED_DATA)")

    def convert(directory: Path) -> None:
        raw = cut_ethucy_raw(directory, steps=30, agents=6)
        args = bench.parse_args(["--raw", str(raw), "--data", str(directory / "data")])
        assert bench.ensure_data(args, tuple(ethucy.FOLDS)) > 0  # converted: no fold config was there
        assert bench.ensure_data(args, tuple(ethucy.FOLDS)) == 0.0  # found: not converted again

    directory = built_once(tmp_path_factory, "ethucy_cut", convert)
    return directory / "raw", directory / "data"
