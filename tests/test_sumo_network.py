"""The SUMO network netconvert builds from the layout: its lanes are our lane paths, and it is cached."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import sumolib

from gccp_envs.config import IntersectionConfig
from gccp_envs.scenario import IntersectionLayout, layout_for
from gccp_envs.sumo.network import (
    cache_folder,
    heading_to_sumo_angle,
    inbound_edge,
    network_file,
    outbound_edge,
    sumo_angle_to_heading,
    sumo_lane_index,
    to_sumo,
)

TOLERANCE = 0.03
"""How far [m] SUMO's lane centre lines may lie from our paths ("a few centimetres")."""


def sumo_lanes_of(net: sumolib.net.Net, layout: IntersectionLayout, path: int) -> list[sumolib.net.lane.Lane]:
    """SUMO's lanes of one movement, in driving order: approach, internal lane(s), exit."""
    move = layout.movements[path]
    lanes = [net.getLane(f"{inbound_edge(move.arm)}_{sumo_lane_index(layout, move.lane)}")]
    exit_lane = f"{outbound_edge(move.exit_arm)}_{sumo_lane_index(layout, move.exit_lane)}"
    while lanes[-1].getID() != exit_lane:
        (link,) = [c for c in lanes[-1].getOutgoing() if c.getToLane().getID() == exit_lane]
        lanes.append(net.getLane(link.getViaLaneID()) if link.getViaLaneID() else link.getToLane())
    return lanes


def densified(shape: list[tuple[float, float]], spacing: float = 0.1) -> np.ndarray:
    """Points every ``spacing`` metres along a polyline, in our coordinates."""
    points = to_sumo(np.array(shape))
    pieces = []
    for a, b in itertools.pairwise(points):
        steps = max(int(np.hypot(*(b - a)) / spacing), 1)
        pieces.append(a + np.linspace(0.0, 1.0, steps, endpoint=False)[:, None] * (b - a))
    return np.concatenate([*pieces, points[-1:]])


@pytest.mark.parametrize(
    "config",
    [IntersectionConfig(), IntersectionConfig(lanes_per_approach=1, lane_width=3.5, corner_radius=8.0)],
    ids=["default", "one-lane"],
)
def test_sumo_lane_centre_lines_are_our_route_paths(config):
    layout = layout_for(config)
    net = sumolib.net.readNet(str(network_file(layout)), withInternal=True)
    for path, move in enumerate(layout.movements):
        lanes = sumo_lanes_of(net, layout, path)
        points = densified([xy for lane in lanes for xy in lane.getShape()])
        s, d = layout.paths.project(np.full(len(points), path), points)
        assert np.abs(d).max() < TOLERANCE, move
        # They cover the whole path, and the stop line is ours: the approach lane ends where our path
        # enters the junction box, and SUMO's lengths add up to ours.
        assert s[0] < TOLERANCE and s[-1] > layout.paths.lengths[path] - TOLERANCE
        assert lanes[0].getLength() == pytest.approx(layout.stop_s, abs=TOLERANCE)
        total = sum(lane.getLength() for lane in lanes)
        assert total == pytest.approx(layout.paths.lengths[path], abs=TOLERANCE)


def test_the_priority_road_is_the_east_west_road(layout):
    net = sumolib.net.readNet(str(network_file(layout)))
    priority = {arm: net.getEdge(inbound_edge(arm)).getPriority() for arm in range(4)}
    assert priority[1] == priority[3] > priority[0] == priority[2]
    assert net.getNode("C").getType() == "priority"


def test_the_network_is_built_once_per_layout(tmp_path, monkeypatch):
    monkeypatch.setenv("GCCP_SUMO_CACHE", str(tmp_path))
    layout = layout_for(IntersectionConfig())
    first = network_file(layout)
    assert first.parent == cache_folder(layout) and first.is_file()
    stamp = first.stat().st_mtime_ns
    assert network_file(layout) == first and first.stat().st_mtime_ns == stamp
    other = network_file(layout_for(IntersectionConfig(corner_radius=6.0)))
    assert other != first
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([first.parent.name, other.parent.name])


def test_headings_and_sumo_angles_convert_both_ways():
    headings = np.array([-np.pi / 2, 0.0, np.pi / 2, 3.0, -3.0])  # north on screen, east, south, ...
    np.testing.assert_allclose(heading_to_sumo_angle(headings[:3]), [0.0, 90.0, 180.0])
    np.testing.assert_allclose(sumo_angle_to_heading(heading_to_sumo_angle(headings)), headings, atol=1e-12)
