"""The ETH/UCY pedestrian benchmark of ``benchmarks/ethucy.py``: how each of its rows is made and the
check that a completed run was made so (`recipe`), and the scoring the ETH/UCY literature reports
(`scoring`: the four test modes, minADE20/minFDE20, constant velocity, the published table)."""
