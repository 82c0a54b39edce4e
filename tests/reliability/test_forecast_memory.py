"""`ForecastTransform` under 16 envs: memory stays flat (short version of benchmarks/forecast_memory.py)."""

import pytest

from benchmarks.forecast_memory import measure

MIB = 2**20


@pytest.mark.slow
def test_forecast_transform_memory_stays_flat_over_500_steps_of_16_envs():
    rss = measure(num_envs=16, steps=500, warmup=100)
    growth = (rss["end"] - rss["warm"]) / MIB
    assert growth < 4, f"RSS grew by {growth:.1f} MiB over 500 steps after warm-up: {rss}"
