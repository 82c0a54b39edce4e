"""Synthetic data for the benchmarks that need no recording: a small LeRobot dataset with video and
sensor gaps (`dataset`), and random push-shaped batches with the models built for them (`push_like`)."""
