"""The benchmark scripts (``python benchmarks/X.py``, ``mmf-rl bench NAME``) and the experiments they
run, in packages of their own (``benchmarks.push``, ...). They ship with the repository, not the wheel:
they import `mmf_rl`, which never imports them."""
