"""``sb3_gccp tune``: hyperparameter search on Optuna for the baselines and the decision-maker.

- :mod:`~sb3_gccp.tune.space`: the search-space files (``zoo_configs/tune/<method>.yml``) and the pruner;
- :mod:`~sb3_gccp.tune.objective`: what a trial trains, and the callback that reports to Optuna;
- :mod:`~sb3_gccp.tune.study`: storage, worker processes, resuming, and the best trial as a zoo entry.
"""
