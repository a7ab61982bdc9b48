"""The SMARTS simulator (config ``simulator: smarts``): the paper's simulator, driving our three tasks.

- :mod:`gccp_envs.smarts.scenario`: the tasks as SMARTS scenarios (our junction, SUMO flows at our density,
  the ego's mission), generated with ``smarts.sstudio`` into a cache folder on first use;
- :mod:`gccp_envs.smarts.fixes`: the two repairs SMARTS 2.0.1 needs, each applied only while needed;
- :mod:`gccp_envs.smarts.world`: :class:`~gccp_envs.smarts.world.SmartsWorld`, the world the envs read,
  stepped by SMARTS: the ego moved by ``RelativeTargetPose``, the outcomes from SMARTS's events, and SUMO
  started with the same seed when SMARTS has to start it again.

SMARTS comes with the ``smarts`` extra; this module imports none of it, so that the config can say in one
line what is missing.
"""

from __future__ import annotations

from importlib.util import find_spec

SMARTS_EXTRA = 'pip install -e ".[smarts]"'
"""How the SMARTS backend is installed."""
VEHICLE_SIZE = (3.68, 1.47)
"""(length, width) [m] of every vehicle in SMARTS, the ego and its traffic: SMARTS's passenger car. SMARTS
gives SUMO's passenger-class traffic these boxes (its observations and its collisions), though SUMO
drives them at its own default of 5 x 1.8 m."""


def require_smarts_extra() -> None:
    """Raise ``ValueError`` in one line naming the ``smarts`` extra unless SMARTS and SUMO can be imported."""
    missing = [name for name in ("smarts", "sumo", "sumolib", "traci") if find_spec(name) is None]
    if missing:
        raise ValueError(
            f"simulator 'smarts' needs the smarts extra ({', '.join(missing)} not installed): {SMARTS_EXTRA}"
        )
