"""`mmf-rl train` + `mmf-rl eval` of the learned prior on a recording whose sensors fail in some windows."""

import json

import pytest
import torch

from mmf_rl.checkpoint import load_checkpoint
from mmf_rl.cli import main as cli
from mmf_rl.datasets import DataConfig, WindowDataset
from tests.conftest import push_train_overrides

NEW_COLUMNS = ("available", "minMSE@K (norm.)", "minADE@K", "minFDE@K", "NLL", "cover 50%", "cover 90%")


@pytest.fixture(scope="module")
def faulty_push_root(tmp_path_factory):
    """A push recording with sensor faults written as data (NaN force spans, frozen and black frames)."""
    from mmf_rl.record import RecordConfig, record

    root = tmp_path_factory.mktemp("faulty") / "push"
    return record(RecordConfig(out=root, episodes=6, steps=40, image_size=32, seed=3, faults=True))


def test_learned_prior_eval_pairs_subsets_on_windows_with_failed_sensors(faulty_push_root, tmp_path, capsys):
    run = tmp_path / "run"
    overrides = [
        *push_train_overrides(faulty_push_root, tmp_path / "cache", run, steps=40),
        "model.prior=learned",
        "loss.max_dropped=null",
        "loss.gsnn_weight=0.5",
        "loss.dropped_nll_weight=0.5",
    ]
    assert cli(["train", *overrides]) == 0
    assert cli(["eval", f"checkpoint={run}", "num_samples=5", "plot_windows=4"]) == 0
    out = capsys.readouterr().out
    header = next(line for line in out.splitlines() if line.startswith("| subset |"))
    assert all(f" {column} |" in header for column in NEW_COLUMNS), header

    # The windows every row is scored on: the test windows where no sensor failed.
    data = WindowDataset(DataConfig.from_dict(load_checkpoint(run / "checkpoints").meta["config"]["data"]))
    test = data.split_windows["test"]
    presence = {name: mask[test] for name, mask in data.presence.items()}
    shared = torch.stack(list(presence.values())).all(0)
    assert 0 < int(shared.sum()) < len(test), "the faults should remove a sensor from some test windows"

    rows = json.loads((run / "eval" / "results.json").read_text())["subsets"]
    assert set(rows) == {
        "all",
        "without_image",
        "without_force",
        "without_proprio",
        "only_image",
        "only_force",
        "only_proprio",
    }
    assert {row["windows"] for row in rows.values()} == {float(shared.sum())}
    assert rows["all"]["windows_available"] == len(test)
    for name, mask in presence.items():
        assert rows[f"only_{name}"]["windows_available"] == int(mask.sum())
    for row in rows.values():
        assert 0 <= row["coverage_50"] <= row["coverage_90"] <= 1
        assert row["min_mse_k"] >= 0 and row["min_fde_k"] >= 0 and row["nll"] == row["nll"]
    assert rows["all"]["degradation"] == 0
    # The learned prior's latents depend on the present modalities: the t-SNE has something to show.
    assert (run / "eval" / "latent_tsne.png").stat().st_size > 1000
