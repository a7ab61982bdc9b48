"""SUMO traffic (config ``traffic: sumo``): SUMO's own drivers on our junction, with the ego inside.

- :mod:`gccp_envs.sumo.network`: the junction written as plain node, edge and connection XML from the
  layout and built by ``netconvert`` into a cache folder, so SUMO's lanes are our lane paths;
- :mod:`gccp_envs.sumo.simulation`: one SUMO instance, in this process through libsumo or as a ``sumo``
  process over TraCI;
- :mod:`gccp_envs.sumo.traffic`: :class:`~gccp_envs.sumo.traffic.SumoTraffic`, the traffic table the world
  reads, filled from SUMO every step, with the ego moved inside SUMO to the pose our kinematics give.

SUMO comes with the ``sumo`` extra; this module imports none of it, so that the config can say in one
line what is missing.
"""

from __future__ import annotations

from importlib.util import find_spec

SUMO_MODULES = ("sumo", "sumolib", "traci")
"""Modules the SUMO backend needs: the binaries (``eclipse-sumo``), sumolib and TraCI. libsumo, the
in-process SUMO, is used when it is installed too."""
SUMO_EXTRA = 'pip install -e ".[sumo]"'
"""How the SUMO backend is installed."""


def require_sumo_extra() -> None:
    """Raise ``ValueError`` in one line naming the ``sumo`` extra unless SUMO can be imported."""
    missing = [name for name in SUMO_MODULES if find_spec(name) is None]
    if missing:
        raise ValueError(
            f"traffic 'sumo' needs the sumo extra ({', '.join(missing)} not installed): {SUMO_EXTRA}"
        )
