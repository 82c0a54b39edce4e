"""The push experiments of ``benchmarks/mpc_push.py`` and ``benchmarks/bc_push.py``: closed-loop play
under sensor outages (`closed_loop`, `outage_evaluation`), MPC's evaluation and data aggregation
(`mpc_evaluation`, `aggregation`), behaviour cloning's evaluation, building and report (`bc_evaluation`,
`bc_experiment`, `bc_report`), and the options they measured not to help: DAgger (`dagger`), the
Gaussian-mixture action head (`gmm_head`) and training on replayed outages (`replayed_outages`);
their shared command-line pieces are `experiment`'s."""
