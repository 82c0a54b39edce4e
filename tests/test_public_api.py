"""``mmf_rl.train`` and ``mmf_rl.evaluate``: the commands' Python entry points, imported on first use."""

import subprocess
import sys

import pytest

import mmf_rl
from mmf_rl.configuration import compose_config


@pytest.mark.slow
def test_import_mmf_rl_loads_no_torch():
    script = "import sys, mmf_rl; assert 'torch' not in sys.modules, 'torch imported'; print(dir(mmf_rl))"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['__version__', 'evaluate', 'train']"


def test_the_entry_points_are_the_commands_functions():
    from mmf_rl.eval.evaluation import evaluate
    from mmf_rl.trainers.training import train

    assert mmf_rl.train is train and mmf_rl.evaluate is evaluate
    with pytest.raises(AttributeError, match="no attribute 'trian'"):
        mmf_rl.trian  # noqa: B018


def test_a_config_and_overrides_together_are_refused():
    with pytest.raises(ValueError, match="a composed config or overrides, not both"):
        mmf_rl.evaluate(compose_config("eval", ["checkpoint=runs/x"]), overrides=["plots=false"])
