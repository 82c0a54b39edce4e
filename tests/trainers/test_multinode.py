"""Two torchrun "nodes" on this machine (c10d rendezvous, gloo, one process each), started for real:
the ranks train in lockstep, agree, and checkpoint as one run. (One node of two ranks is started in
tests/reliability/test_distributed_faults.py.)"""

import re
import subprocess
import sys

from benchmarks.kill_loop import final_weights, subprocess_env
from mmf_rl.checkpoint import load_checkpoint
from mmf_rl.cli import main as cli
from mmf_rl.models import load_trained_model
from tests.reliability.conftest import free_port, single_thread

STEPS = 4
LR = 1e-3  # the trainer's default learning rate


def deterministic_run(root, cache_dir, run_dir, batch_size: int) -> list[str]:
    """A model and loss without random draws (lf_lstm, Gaussian NLL): one process on the union of
    the ranks' batches must then train the same weights as two data-parallel ranks."""
    return [
        f"data.root={root}",
        f"data.cache_dir={cache_dir}",
        f"run_dir={run_dir}",
        "data.image_size=[32,32]",
        "data.history=4",
        "data.horizon=3",
        "data.split_fractions=[0.5,0.25,0.25]",
        "model=lf_lstm",
        "model.d_model=16",
        "model.head_hidden=32",
        f"trainer.total_steps={STEPS}",
        f"trainer.batch_size={batch_size}",
        "trainer.warmup_steps=2",
        f"trainer.lr={LR}",
        "trainer.progress_bar=false",
        "logger=none",
        "num_workers=0",
        "calibrate=false",
    ]


def test_two_nodes_build_the_cache_once_and_train_the_weights_of_one_process(recorded_push_root, tmp_path):
    port = free_port()
    node = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nnodes=2",
        "--nproc_per_node=1",
        "--rdzv-backend=c10d",
        f"--rdzv-endpoint=127.0.0.1:{port}",
        "--rdzv-id=mmf-rl-two-nodes",
        "-m",
        "mmf_rl.cli",
        "train",
        # One cache directory for both: a shared filesystem (each node's own disk works alike).
        *deterministic_run(recorded_push_root, tmp_path / "cache", tmp_path / "nodes", batch_size=16),
    ]
    nodes = [
        subprocess.Popen(
            node, env=subprocess_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
        )
        for _ in range(2)
    ]
    errors = [process.communicate(timeout=300)[1] for process in nodes]
    assert [process.returncode for process in nodes] == [0, 0], "\n".join(e[-3000:] for e in errors)
    log = "\n".join(errors)
    assert log.count("window cache built") == 1 and log.count("window cache opened") == 1, log[-3000:]
    # Each rank's weights against rank 0's, after the last step (Trainer.check_replicas_agree).
    gap = re.search(r"data parallel: 2 ranks agree after 4 steps \(max weight difference (\S+)\)", log)
    assert gap is not None and float(gap.group(1)) == 0.0, log[-3000:]
    # The checkpoint of the two ranks: both ranks' generators, the plain model's weights (no DDP names).
    checkpoint = load_checkpoint(tmp_path / "nodes" / "checkpoints")
    assert checkpoint.step == STEPS and checkpoint.meta["world_size"] == 2
    assert len(checkpoint.trainer_state["rng"]) == 2
    load_trained_model(tmp_path / "nodes" / "checkpoints")

    with single_thread():  # the kernels of the single-threaded node processes
        run = deterministic_run(recorded_push_root, tmp_path / "cache", tmp_path / "one", batch_size=32)
        assert cli(["train", *run]) == 0
    two_nodes, one_process = final_weights(tmp_path / "nodes"), final_weights(tmp_path / "one")
    deltas = {name: float((two_nodes[name] - value).abs().max()) for name, value in one_process.items()}
    # Two ranks' mean gradient and one batch's differ in summation order (and, on some CPUs, in the
    # convolution kernels chosen per batch size); Adam divides by each gradient's running RMS, so a
    # rounding difference in a near-zero gradient can move its weight by a small fraction of a step.
    # A tenth of the learning rate: far below what training on one rank's batch alone moves a weight
    # (several learning rates after these steps).
    assert max(deltas.values()) <= 0.1 * LR, sorted(deltas.items(), key=lambda item: -item[1])[:5]
