"""The push experiments of ``benchmarks/mpc_push.py`` and ``benchmarks/bc_push.py``: closed-loop play
under sensor outages (`closed_loop`, `outage_evaluation`), MPC's evaluation and data aggregation
(`mpc_evaluation`, `aggregation`), behaviour cloning's evaluation, building and report (`bc_evaluation`,
`bc_experiment`, `bc_report`), DAgger (`dagger`), and their shared command-line pieces (`experiment`)."""
