import pytest

from mmf_rl.cli import main as cli
from tests.conftest import push_train_overrides


def small_overrides(root, tmp_path):
    # The demo sets data.root and run_dir itself.
    return [
        o
        for o in push_train_overrides(root, tmp_path / "cache", tmp_path / "unused")
        if not o.startswith(("data.root=", "run_dir="))
    ]


@pytest.mark.slow
def test_demo_records_when_the_dataset_is_absent_then_reruns_on_it_without_starting_over(tmp_path, capsys):
    """The first run records (as `make demo` on a fresh clone), trains and evaluates; the second uses that
    recording and resumes the finished run."""
    data = tmp_path / "push"
    args = [
        "demo",
        "--data",
        str(data),
        "--episodes",
        "3",
        "--workers",
        "1",
        "--run-dir",
        str(tmp_path / "demo"),
        "--",
        *small_overrides(data, tmp_path),
        "data.image_size=[64,64]",
        "data.split_fractions=[0.34,0.33,0.33]",
    ]
    assert cli(args) == 0
    out, err = capsys.readouterr()
    assert "recording 3 push episodes" in err
    assert (data / "meta" / "info.json").is_file()
    assert "| all |" in out and "| constant velocity |" in out and "all modalities: MSE" in out
    assert (tmp_path / "demo" / "eval" / "forecasts.png").is_file()

    assert cli(args) == 0
    err = capsys.readouterr().err
    assert f"using the recording in {data}" in err
    assert "recording 3 push episodes" not in err, "a recording there is not made again"
    assert "has checkpoints: resuming" in err
