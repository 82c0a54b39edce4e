"""Composing configs: whole mappings replace, dotted keys edit their entries, configs outside the
package, the configs in a wheel."""

import re
import shlex
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from mmf_rl.checkpoint import load_checkpoint
from mmf_rl.cli import main as cli
from mmf_rl.configuration import DEFAULT_CONFIG_DIR, ConfigError, compose_config, config_groups
from tests.conftest import push_train_overrides

REPO = Path(__file__).resolve().parents[1]


def data_of(overrides, **kwargs) -> dict:
    return OmegaConf.to_container(compose_config("train", overrides, **kwargs).data)


def test_a_whole_mapping_replaces_the_base_configs():
    data = data_of(
        [
            "data.modalities={cam: observation.images.top, joints: observation.state}",
            "data.target=observation.state",
            "data.missing={cam: 0.5}",
            "data.action={feature: action}",
        ]
    )
    assert data["modalities"] == {"cam": "observation.images.top", "joints": "observation.state"}
    assert data["target"] == "observation.state"  # not merged with push's dims [0, 1] and relative: true
    assert data["missing"] == {"cam": 0.5} and data["action"] == {"feature": "action"}
    # Replaced, then edited and extended by the overrides that follow it, in order.
    data = data_of(
        [
            "data.modalities={cam: observation.images.top}",
            "data.modalities.cam={feature: x, required: true}",
            "+data.modalities.joints=observation.state",
            "data.missing=observed",
        ]
    )
    assert data["modalities"] == {"cam": {"feature": "x", "required": True}, "joints": "observation.state"}
    assert data["missing"] == "observed"
    # A dotted key still edits one entry of the base config's mapping.
    data = data_of(["data.target.dims=[0]"])
    assert data["target"] == {
        "feature": "observation.object_pose",
        "dims": [0],
        "relative": True,
        "relative_to": None,
    }
    # The same over a data config that lacks the key (push_world_model has `action`, push has none).
    assert data_of(["data=push_world_model", "data.action=null"])["action"] is None


TWO_MODALITIES = (
    "data.modalities={image: {feature: observation.images.front}, force: {feature: observation.force}}"
)


def test_a_dotted_key_sets_a_key_its_entry_does_not_give_yet():
    """After a whole mapping, and over a feature-name entry: the entry's keys have defaults (Hydra
    alone needs `+` for them, in struct mode)."""
    replaced = {"image": {"feature": "observation.images.front"}, "force": {"feature": "observation.force"}}
    with_mlp = {**replaced, "force": {"feature": "observation.force", "encoder": "mlp"}}
    assert data_of([TWO_MODALITIES, "data.modalities.force.encoder=mlp"])["modalities"] == with_mlp
    for prefix in ("+", "++"):  # Hydra's spellings keep working
        assert (
            data_of([TWO_MODALITIES, f"{prefix}data.modalities.force.encoder=mlp"])["modalities"] == with_mlp
        )
    # In command-line order: a whole mapping given later replaces the edit.
    assert data_of(["data.modalities.force.encoder=mlp", TWO_MODALITIES])["modalities"] == replaced
    # An entry given as a feature name is {feature: name}; the others stay as they are.
    assert data_of(["data.modalities.force.required=true"])["modalities"] == {
        "image": "observation.images.front",
        "force": {"feature": "observation.force", "required": True},
        "proprio": "observation.state",
    }
    assert data_of(["data.target=observation.state", "data.target.dims=[0]"])["target"] == {
        "feature": "observation.state",
        "dims": [0],
    }
    assert data_of(["data=push_world_model", "data.action.dims=[0,1]"])["action"] == {
        "feature": "action",
        "dims": [0, 1],
    }
    outage = data_of(["data.missing={force: {fraction: 0.1}}", "data.missing.force.mean_burst=5"])
    assert outage["missing"] == {"force": {"fraction": 0.1, "mean_burst": 5}}
    assert data_of(["+data.action.feature=action"])["action"] == {"feature": "action"}


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            ["data.modalities.forse.encoder=mlp"],
            "data.modalities.forse.encoder=mlp: data.modalities has no entry 'forse' (it has image, force, "
            "proprio); fix the name, or give the whole entry: +data.modalities.forse='{...}'",
        ),
        (
            [TWO_MODALITIES, "data.modalities.proprio.encoder=mlp"],
            "data.modalities.proprio.encoder=mlp: data.modalities has no entry 'proprio' (it has image, "
            "force)",
        ),
        (
            ["data.modalities.forse=observation.force"],
            "data.modalities.forse=observation.force: data.modalities has no 'forse' (it has image, force, "
            "proprio); fix the name, or add it with +data.modalities.forse=observation.force",
        ),
        (
            ["+data.modalities.force=observation.force"],
            "+data.modalities.force=observation.force: data.modalities.force is already in the config; "
            "change it with data.modalities.force=observation.force",
        ),
        (
            ["data.action.feature=action"],
            "data.action.feature=action: data.action is not set; fix the name, or give the whole entry: "
            "+data.action='{...}'",
        ),
        (
            ["data.missing={force: 0.5}", "data.missing.force.fraction=0.1"],
            "data.missing.force.fraction=0.1: data.missing.force is 0.5, not a mapping; give the whole "
            "entry: data.missing.force='{...}'",
        ),
        (
            ["~data.modalities.force.encoder"],
            "~data.modalities.force.encoder: data.modalities.force.encoder is not in the config; nothing "
            "to delete",
        ),
    ],
)
def test_an_edit_of_an_entry_that_is_not_there_is_a_one_line_error(overrides, message):
    with pytest.raises(ConfigError) as error:
        compose_config("train", overrides)
    assert str(error.value).startswith(message) and "\n" not in str(error.value)


def test_mmf_rl_train_trains_with_the_edited_entry(recorded_push_root, tmp_path, capsys):
    run = tmp_path / "run"
    edit = [
        "data.modalities={image: observation.images.front, force: {feature: observation.force}}",
        "data.modalities.force.encoder=mlp",
    ]
    assert (
        cli(["train", *push_train_overrides(recorded_push_root, tmp_path / "cache", run, steps=2), *edit])
        == 0
    )
    modalities = {
        m["name"]: m for m in load_checkpoint(run / "checkpoints").meta["model_config"]["modalities"]
    }
    assert sorted(modalities) == ["force", "image"] and modalities["force"]["encoder"] == "mlp"
    assert yaml.safe_load((run / "config.yaml").read_text())["data"]["modalities"]["force"] == {
        "feature": "observation.force",
        "encoder": "mlp",
    }

    capsys.readouterr()
    assert cli(["train", "--cfg", edit[0], "data.modalities.forse.encoder=mlp"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("mmf-rl train: error: data.modalities.forse.encoder=mlp: data.modalities has no ")
    assert "\n" not in err


def test_configs_outside_the_package(tmp_path):
    mine = {
        "root": "/data/mine",
        "modalities": {"cam": "observation.images.top"},
        "target": "observation.state",
    }
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "mine.yaml").write_text(yaml.safe_dump(mine))
    assert data_of(["data=mine"], config_dirs=[tmp_path]) == mine
    assert data_of([f"data={tmp_path / 'data' / 'mine.yaml'}"]) == mine
    assert "mine" in config_groups([tmp_path])["data"]
    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "quick.yaml").write_text("# @package _global_\ntrainer:\n  total_steps: 7\n")
    assert (
        compose_config("train", [f"experiment={tmp_path / 'experiment' / 'quick.yaml'}"]).trainer.total_steps
        == 7
    )

    with pytest.raises(ConfigError, match=r"data=/nonexistent/mine\.yaml: no such file"):
        compose_config("train", ["data=/nonexistent/mine.yaml"])
    (tmp_path / "data" / "push.yaml").write_text("root: x\n")
    with pytest.raises(ConfigError, match=r"push\.yaml has the name of mmf-rl's own .*rename yours"):
        compose_config("train", ["data=mine"], config_dirs=[tmp_path])
    with pytest.raises(ConfigError, match=r"--config-dir .*nowhere: no such directory"):
        compose_config("train", [], config_dirs=[tmp_path / "nowhere"])


def readme_commands(command: str) -> list[list[str]]:
    """The README's ``mmf-rl <command>`` lines from its bash blocks (continuations joined), as argv."""
    text = (REPO / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, re.DOTALL)
    lines = [line.split(" #")[0] for block in blocks for line in block.replace("\\\n", " ").splitlines()]
    return [shlex.split(line)[2:] for line in lines if line.startswith(f"mmf-rl {command} ")]


def test_the_readmes_override_command_composes_what_it_says():
    commands = [
        argv for argv in readme_commands("train") if any(a.startswith("data.modalities=") for a in argv)
    ]
    assert commands, "the README shows no `mmf-rl train data.modalities=...` command"
    for argv in commands:
        given = {a.split("=", 1)[0]: a.split("=", 1)[1] for a in argv}
        data = data_of(argv)
        assert data["modalities"] == yaml.safe_load(given["data.modalities"])
        assert data["target"] == given["data.target"]
        assert data["root"] == given["data.root"]


@pytest.mark.slow
def test_the_configs_ship_in_the_wheel(tmp_path):
    """A wheel built from the repository (setuptools, no network) holds every config file."""
    source = tmp_path / "src"
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        (source / name).write_bytes((REPO / name).read_bytes())
    subprocess.run(["cp", "-a", str(REPO / "mmf_rl"), str(REPO / "configs"), str(source)], check=True)
    out = tmp_path / "wheel"
    build = subprocess.run(
        [sys.executable, "-c", f"from setuptools import build_meta; build_meta.build_wheel({str(out)!r})"],
        cwd=source,
        capture_output=True,
        text=True,
    )
    assert build.returncode == 0, build.stderr[-2000:]
    (wheel,) = out.glob("*.whl")
    shipped = {n for n in zipfile.ZipFile(wheel).namelist() if n.startswith("mmf_rl/configs/")}
    expected = {
        f"mmf_rl/configs/{p.relative_to(DEFAULT_CONFIG_DIR)}" for p in DEFAULT_CONFIG_DIR.rglob("*.yaml")
    }
    assert "mmf_rl/configs/train.yaml" in expected and shipped == expected
