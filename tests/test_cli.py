import logging
import re
import subprocess
import sys

import pytest
import yaml
from omegaconf import OmegaConf

from mmf_rl import cli
from mmf_rl.configuration import DEFAULT_CONFIG_DIR, config_groups
from mmf_rl.log import _ProgressSafeHandler, configure_logging


@pytest.fixture
def commands(monkeypatch):
    monkeypatch.setattr(cli, "COMMANDS", {"echo": ("tests.test_cli", "print the arguments")})


def main(argv):
    print("echo:", *argv)
    return 3


def test_help_lists_commands(commands, capsys):
    assert cli.main(["--help"]) == 0
    assert "echo       print the arguments" in capsys.readouterr().out


def test_dispatches_to_the_command_module(commands, capsys):
    assert cli.main(["echo", "a", "--b"]) == 3
    assert capsys.readouterr().out == "echo: a --b\n"


def test_unknown_command_is_a_clear_error(commands, capsys):
    assert cli.main(["trian"]) == 2
    err = capsys.readouterr().err
    assert "unknown command 'trian'" in err and "echo" in err


def log(argv):
    logger = logging.getLogger("mmf_rl.tests")
    logger.debug("a detail")
    logger.info("progress")
    logger.warning("a problem")
    logging.getLogger("another_library").info("not ours")


@pytest.mark.parametrize(
    "options, shown",
    [
        ([], ["INFO mmf_rl.tests: progress", "WARNING mmf_rl.tests: a problem"]),
        (
            ["--verbose"],
            [
                "DEBUG mmf_rl.tests: a detail",
                "INFO mmf_rl.tests: progress",
                "WARNING mmf_rl.tests: a problem",
            ],
        ),
        (["-q"], ["WARNING mmf_rl.tests: a problem"]),
    ],
)
def test_log_messages_go_to_stderr_at_the_level_the_top_level_option_sets(
    monkeypatch, capsys, options, shown
):
    monkeypatch.setattr(cli, "COMMANDS", {"log": ("tests.test_cli:log", "log at every level")})
    assert cli.main([*options, "log"]) == 0
    out, err = capsys.readouterr()
    assert out == ""
    assert [line.split(" ", 1)[1] for line in err.splitlines()] == shown  # after the time


def test_a_config_command_takes_its_overrides_after_a_top_level_option(capsys):
    assert cli.main(["--quiet", "train", "--cfg", "trainer.lr=0.5"]) == 0
    assert yaml.safe_load(capsys.readouterr().out)["trainer"]["lr"] == 0.5


# --- every real command: --help with usage and examples, --cfg without running -----------------


@pytest.mark.parametrize("command", sorted(cli.COMMANDS))
def test_every_command_answers_help_with_usage_and_two_examples(command, capsys):
    assert cli.main([command, "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: mmf-rl {command}")
    examples = out.split("\nexamples:\n", 1)[1].splitlines()
    assert len([line for line in examples if line.startswith(f"  mmf-rl {command}")]) >= 2, out


@pytest.mark.parametrize("command", ["train", "eval", "calibrate"])
def test_config_commands_list_their_groups_options_and_settings(command, capsys, tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "mine.yaml").write_text("root: /data/mine\n")
    assert cli.main([command, "--config-dir", str(tmp_path), "--help"]) == 0
    out = capsys.readouterr().out
    own = OmegaConf.load(DEFAULT_CONFIG_DIR / f"{command}.yaml")
    groups = [next(iter(entry)) for entry in own.get("defaults", []) if not isinstance(entry, str)]
    for group, options in config_groups([tmp_path]).items():
        if group in groups:
            assert re.search(rf"^  {group} +.*" + ".*".join(options), out, re.MULTILINE), (group, out)
    if command == "train":
        assert "mine" in config_groups([tmp_path])["data"] and "push*" in out
    for key in (k for k in own if k != "defaults" and not OmegaConf.is_dict(own[k])):
        assert f"  {key}=" in out


def test_train_cfg_prints_the_composed_config_and_trains_nothing(capsys, tmp_path):
    run = tmp_path / "run"
    assert (
        cli.main(
            [
                "train",
                "--cfg",
                f"run_dir={run}",
                "data.modalities={cam: observation.images.top}",
                "data.target=observation.state",
                "model=lf_lstm",
            ]
        )
        == 0
    )
    cfg = yaml.safe_load(capsys.readouterr().out)
    assert (
        cfg["data"]["modalities"] == {"cam": "observation.images.top"} and cfg["model"]["name"] == "lf_lstm"
    )
    assert cfg["run_dir"] == str(run) and not run.exists()
    assert cli.main(["eval", "checkpoint=runs/x", "num_samples=3", "--cfg"]) == 0
    assert yaml.safe_load(capsys.readouterr().out)["num_samples"] == 3
    assert cli.main(["train", "--cfg", "trainer.lrr=1"]) == 1
    assert "Could not override 'trainer.lrr'" in capsys.readouterr().err


def test_a_script_run_by_the_cli_keeps_its_level_and_run_alone_shows_progress():
    logger = logging.getLogger("mmf_rl")
    try:
        configure_logging(logging.WARNING)  # `mmf-rl --quiet bench ...`
        configure_logging()  # then the benchmark script's own call
        assert logger.level == logging.WARNING
        logger.handlers = [h for h in logger.handlers if not isinstance(h, _ProgressSafeHandler)]
        configure_logging()  # the script run alone
        assert logger.level == logging.INFO
        assert sum(isinstance(h, _ProgressSafeHandler) for h in logger.handlers) == 1
    finally:
        configure_logging(logging.INFO)


@pytest.mark.slow
def test_a_library_logging_on_the_root_logger_does_not_print_mmf_rl_records_twice():
    """In a fresh process (pytest configures the root logger): a root-logger call, as lerobot makes,
    gives the root its default handler; an ``mmf_rl`` record still prints once, another library's
    warning still prints."""
    script = (
        "import logging; from mmf_rl.log import configure_logging; configure_logging(); "
        "logging.info('a library on the root logger'); "
        "logging.getLogger('mmf_rl.data').info('cache built'); "
        "logging.getLogger('other.library').warning('careful')"
    )
    err = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stderr
    assert err.count("cache built") == 1 and err.count("careful") == 1, err


def refuse(argv):
    raise SystemExit(f"echo: cannot use {argv[0]}")


def test_a_commands_exit_message_is_shown_and_its_code_is_one(monkeypatch, capsys):
    monkeypatch.setattr(cli, "COMMANDS", {"refuse": ("tests.test_cli:refuse", "exit with a message")})
    assert cli.main(["refuse", "this"]) == 1
    assert capsys.readouterr().err.strip().endswith("echo: cannot use this")
