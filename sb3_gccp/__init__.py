"""sb3_gccp: goal-conditioned hierarchical RL with Goal-Conditioned Collision Prediction (GCCP).

Importing the package registers the intersection environments (``GCCPPlanner-v0``,
``GCCPDecider-v0``, ``GCCPFlat-v0``) with gymnasium.
"""

import gccp_envs as _gccp_envs  # noqa: F401  (registers the environments)

__version__ = "0.1.0"
