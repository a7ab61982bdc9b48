"""The GCCP module (paper III-C, III-E): goal-conditioned collision prediction, together.

- :mod:`~sb3_gccp.gccp.settings`: the collision check (``GCCPCheck``) and the decider stage's
  schedule and predictor training (``GCCPSettings``),
- :mod:`~sb3_gccp.gccp.predictor`: the trajectory predictors and their files,
- :mod:`~sb3_gccp.gccp.collision`: the SAT ``CollisionChecker``,
- :mod:`~sb3_gccp.gccp.mask`: ``GCCPMask``, the decider env's mask function,
- :mod:`~sb3_gccp.gccp.replay`: the ``EpisodeReplayBuffer`` of decisions,
- :mod:`~sb3_gccp.gccp.training`: Eq. 2, the predictor's trainer and ADE/FDE,
- :mod:`~sb3_gccp.gccp.callback`: ``GCCPCallback``, Algorithm 1 beside MaskablePPO.
"""
