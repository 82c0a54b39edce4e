"""The push experiments' tests read the RL tests' tiny recording, forecaster and demonstrations."""

from tests.rl.conftest import demonstrations, forecaster, forecasts, recorded_steps  # noqa: F401
