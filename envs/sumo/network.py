"""The junction as a SUMO network, built by ``netconvert`` from the layout and cached per layout.

The network is written as plain XML: a priority node at the centre (the kerb radius of the layout), one
dead-end node per arm, one edge each way per arm (the east-west road with the higher priority) and one
connection per movement of the layout, whose internal-lane shape is our path through the junction. So
SUMO's lanes lie on our lane paths, and SUMO's stop lines on ours.

SUMO's y axis points up and ours down on screen: a point (x, y) of ours is (x, -y) in SUMO. SUMO numbers
the lanes of an edge from the kerb, ours from the centre line.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

from gccp_envs.geometry import FloatArray, wrap_angle
from gccp_envs.scenario import MAJOR_ARMS, IntersectionLayout

JUNCTION = "C"
"""Id of the junction node."""
NETWORK_FILE = "junction.net.xml"
"""The network netconvert writes, inside the layout's cache folder."""
CACHE_VARIABLE = "GCCP_SUMO_CACHE"
"""Environment variable naming the cache folder (default ``~/.cache/gccp_envs/sumo``)."""
SHAPE_SPACING = 0.5
"""Spacing [m] of the points of a connection's shape: the chord of our tightest turn (7 m radius) then
stays within 5 mm of the arc."""
NETCONVERT_OPTIONS = ("--offset.disable-normalization", "true", "--no-turnarounds", "true")
"""Keep our coordinates (netconvert moves the network to the origin otherwise); no U-turns, as ours."""


def inbound_edge(arm: int) -> str:
    """Id of the edge that enters the junction from ``arm``."""
    return f"in{arm}"


def outbound_edge(arm: int) -> str:
    """Id of the edge that leaves the junction on ``arm``."""
    return f"out{arm}"


def route_id(arm: int, exit_arm: int) -> str:
    """Id of the route from ``arm`` to ``exit_arm``."""
    return f"{inbound_edge(arm)}-{outbound_edge(exit_arm)}"


def sumo_lane_index(layout: IntersectionLayout, lane: int) -> int:
    """SUMO's index of our lane ``lane`` (SUMO counts from the kerb, we from the centre line)."""
    return layout.lanes - 1 - lane


def to_sumo(points: FloatArray) -> FloatArray:
    """Our points (..., 2) in SUMO's coordinates."""
    return np.asarray(points, float) * np.array([1.0, -1.0])


def heading_to_sumo_angle(heading: FloatArray | float) -> FloatArray:
    """SUMO's vehicle angle [deg, clockwise from north] of our headings [rad]."""
    return np.mod(90.0 + np.degrees(heading), 360.0)


def sumo_angle_to_heading(angle: FloatArray | float) -> FloatArray:
    """Our heading [rad, wrapped] of SUMO's vehicle angles [deg]."""
    return wrap_angle(np.radians(np.asarray(angle, float) - 90.0))


def network_sources(layout: IntersectionLayout) -> dict[str, str]:
    """The plain XML files netconvert reads (nodes, edges, connections), by file name."""
    centre = f'  <node id="{JUNCTION}" x="0" y="0" type="priority" radius="{layout.corner_radius:g}"/>'
    nodes, edges, connections = [centre], [], []
    for arm in range(4):
        x, y = to_sumo(_arm_end(layout, arm))
        nodes.append(f'  <node id="N{arm}" x="{x:.3f}" y="{y:.3f}" type="dead_end"/>')
        priority = 2 if arm in MAJOR_ARMS else 1
        lanes = f'numLanes="{layout.lanes}" width="{layout.lane_width:g}" priority="{priority}"'
        edges.append(f'  <edge id="{inbound_edge(arm)}" from="N{arm}" to="{JUNCTION}" {lanes}/>')
        edges.append(f'  <edge id="{outbound_edge(arm)}" from="{JUNCTION}" to="N{arm}" {lanes}/>')
    for p, move in enumerate(layout.movements):
        s = np.linspace(layout.stop_s, layout.junction_end_s[p], _shape_points(layout, p))
        shape = to_sumo(layout.paths.pose_at(np.full(len(s), p), s)[:, :2])
        from_lane, to_lane = sumo_lane_index(layout, move.lane), sumo_lane_index(layout, move.exit_lane)
        connections.append(
            f'  <connection from="{inbound_edge(move.arm)}" to="{outbound_edge(move.exit_arm)}" '
            f'fromLane="{from_lane}" toLane="{to_lane}" '
            f'shape="{" ".join(f"{px:.4f},{py:.4f}" for px, py in shape)}"/>'
        )
    return {
        "junction.nod.xml": _xml("nodes", nodes),
        "junction.edg.xml": _xml("edges", edges),
        "junction.con.xml": _xml("connections", connections),
    }


def _arm_end(layout: IntersectionLayout, arm: int) -> FloatArray:
    """The outer end of an arm's centre line (where its dead-end node sits): arm 0's, rotated."""
    angle = arm * np.pi / 2.0
    return layout.extent * np.array([-np.sin(angle), np.cos(angle)])


def _shape_points(layout: IntersectionLayout, path: int) -> int:
    length = layout.junction_end_s[path] - layout.stop_s
    return max(int(np.ceil(length / SHAPE_SPACING)) + 1, 2)


def _xml(root: str, lines: list[str]) -> str:
    return "\n".join([f"<{root}>", *lines, f"</{root}>", ""])


def cache_root() -> Path:
    """The folder of the cached networks: ``$GCCP_SUMO_CACHE``, else ``$XDG_CACHE_HOME/gccp_envs/sumo``."""
    if os.environ.get(CACHE_VARIABLE):
        return Path(os.environ[CACHE_VARIABLE])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "gccp_envs" / "sumo"


def cache_folder(layout: IntersectionLayout) -> Path:
    """The layout's cache folder: named by its parameters, plus a digest of the XML and SUMO's version."""
    digest = hashlib.sha256(repr((sorted(network_sources(layout).items()), _sumo_version())).encode())
    name = (
        f"lanes{layout.lanes}-width{layout.lane_width:g}-radius{layout.corner_radius:g}"
        f"-arm{layout.approach_length:g}-{digest.hexdigest()[:12]}"
    )
    return cache_root() / name


def _sumo_version() -> str:
    try:
        return version("eclipse-sumo")
    except PackageNotFoundError:
        return "unknown"


def network_file(layout: IntersectionLayout) -> Path:
    """The layout's SUMO network, built with netconvert on first use (see :func:`build_once`).

    :raises RuntimeError: netconvert's own message when it fails
    """
    return build_once(cache_folder(layout), NETWORK_FILE, lambda build: _write_network(layout, build))


def build_once(folder: Path, marker: str, build: Callable[[Path], None]) -> Path:
    """``folder / marker``, after ``build`` has filled ``folder`` if ``marker`` is not there yet.

    ``build`` fills a temporary folder next to ``folder``, which is then renamed into place, so concurrent
    workers never read a half-built folder; the temporary folder is removed whatever happens.

    :param folder: the cache folder to fill
    :param marker: the file, relative to ``folder``, whose presence means the folder is built
    :param build: fills the folder it is given
    """
    if (folder / marker).is_file():
        return folder / marker
    folder.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".build-", dir=folder.parent))
    try:
        staging.chmod(0o755)  # a shared cache: mkdtemp makes the folder private
        build(staging)
        try:
            staging.rename(folder)
        except OSError:
            if not (folder / marker).is_file():  # not another worker's identical build
                raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return folder / marker


def _write_network(layout: IntersectionLayout, folder: Path) -> None:
    for name, text in network_sources(layout).items():
        (folder / name).write_text(text)
    _netconvert(folder)


def _netconvert(folder: Path) -> None:
    import sumolib

    command = [
        sumolib.checkBinary("netconvert"),
        "--node-files",
        "junction.nod.xml",
        "--edge-files",
        "junction.edg.xml",
        "--connection-files",
        "junction.con.xml",
        "--output-file",
        NETWORK_FILE,
        *NETCONVERT_OPTIONS,
    ]
    result = subprocess.run(command, cwd=folder, capture_output=True, text=True, timeout=60)
    if result.returncode != 0:
        message = (result.stderr or result.stdout).strip().splitlines()
        raise RuntimeError(f"netconvert failed: {message[-1] if message else result.returncode}")
