"""The training stages and their run folders.

- :mod:`~sb3_gccp.training.run_folder`: a stage's request, run options, run folder and MaskablePPO,
- :mod:`~sb3_gccp.training.checkpoints`: checkpoints written atomically and checked before a resume,
- :mod:`~sb3_gccp.training.episodes`: the episode log (``episodes.csv``),
- :mod:`~sb3_gccp.training.workers`: the fork server that worker processes start from,
- :mod:`~sb3_gccp.training.planner`: the motion-planner stage, with
  :mod:`~sb3_gccp.training.imitation` (cloning an expert planner before PPO),
- :mod:`~sb3_gccp.training.decider`: the decision-maker stage (and ``--stage all``),
- :mod:`~sb3_gccp.training.predictor`: the predictor stage (the GCCP predictor alone),
- :mod:`~sb3_gccp.training.baselines`: DQN, PPO and SAC-Discrete on the flat env.
"""
