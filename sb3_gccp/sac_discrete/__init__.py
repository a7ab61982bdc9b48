"""SAC-Discrete (Christodoulou 2019, https://arxiv.org/abs/1910.07207) as an SB3 off-policy algorithm."""

from sb3_gccp.sac_discrete.policies import CnnPolicy, MlpPolicy, MultiInputPolicy
from sb3_gccp.sac_discrete.sac_discrete import SACDiscrete

__all__ = ["CnnPolicy", "MlpPolicy", "MultiInputPolicy", "SACDiscrete"]
