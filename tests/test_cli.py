import pytest

from mmf_rl import cli


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
