"""RGB frames of the junction drawn with highway-env's road and vehicle graphics (offscreen pygame)."""

from __future__ import annotations

import os

import numpy as np

from gccp_envs.geometry import FloatArray
from gccp_envs.scenario import IntersectionLayout
from gccp_envs.world import IntersectionWorld

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("SDL_AUDIODRIVER", "dummy")  # pygame.init() would probe the sound card
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import pygame
from highway_env.road.graphics import RoadGraphics, WorldSurface
from highway_env.road.road import Road
from highway_env.vehicle.graphics import VehicleGraphics
from highway_env.vehicle.kinematics import Vehicle

CANDIDATE_COLOR = (80, 160, 255)
MASKED_COLOR = (220, 60, 60)
CHOSEN_COLOR = (255, 215, 0)
EGO_COLOR = (50, 200, 0)
OTHER_COLOR = (200, 200, 200)
CRASHED_COLOR = (255, 100, 100)
OFF_ROAD_COLOR = (60, 110, 60)
PREDICTED_EGO_COLOR = (170, 255, 120)
PREDICTED_NEIGHBOUR_COLOR = (255, 90, 255)
TEXT_COLOR = (255, 255, 255)
TEXT_BACKGROUND = (0, 0, 0)
LEGEND = (
    ("candidate", CANDIDATE_COLOR),
    ("masked", MASKED_COLOR),
    ("chosen", CHOSEN_COLOR),
    ("ego predicted", PREDICTED_EGO_COLOR),
    ("neighbours predicted", PREDICTED_NEIGHBOUR_COLOR),
)
"""What the colours of the subgoals and the predicted trajectories mean, written by ``legend=True``."""


class IntersectionRenderer:
    """Draws the road once per layout, then vehicles and subgoals on top of it each frame.

    :param layout: the junction to draw
    :param size: frame width and height [px]
    :param view: metres shown across the frame
    :param centre: the world point (x, y) [m] at the middle of the frame (default: the junction's centre)
    """

    def __init__(
        self,
        layout: IntersectionLayout,
        size: int = 600,
        view: float = 100.0,
        centre: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        pygame.init()
        self.layout = layout
        self.size = size
        self.road = Road(network=layout.road_network())
        self.surface = WorldSurface((size, size), 0, pygame.Surface((size, size)))
        self.surface.scaling = size / view
        self.surface.centering_position = [0.5, 0.5]
        self.surface.move_display_window_to(np.array(centre, dtype=float))
        RoadGraphics.display(self.road, self.surface)
        self._shade_off_road()
        self.background = self.surface.copy()
        self.font = pygame.font.Font(None, max(12, size // 32))

    def _shade_off_road(self) -> None:
        pixels = np.arange(self.size) + 0.5
        x = self.surface.origin[0] + pixels / self.surface.scaling
        y = self.surface.origin[1] + pixels / self.surface.scaling
        off_road = ~self.layout.is_drivable(x[:, None], y[None, :])  # surfarray is (W, H)
        rgb = pygame.surfarray.pixels3d(self.surface)
        rgb[off_road] = OFF_ROAD_COLOR
        del rgb  # unlock the surface

    def frame(
        self,
        world: IntersectionWorld,
        candidates: FloatArray | None = None,
        chosen: FloatArray | None = None,
        masked: np.ndarray | None = None,
        ego_prediction: FloatArray | None = None,
        neighbour_predictions: FloatArray | None = None,
        caption: str | None = None,
        legend: bool = False,
    ) -> np.ndarray:
        """One frame (H, W, 3) uint8 of the world's current step.

        :param candidates: subgoal candidates (N, 3) in world coordinates, drawn as dots
        :param chosen: the chosen subgoal (x, y, heading), drawn as a large dot with a heading tick
        :param masked: bool (N,), candidates the GCCP module masks (drawn red)
        :param ego_prediction: the ego's predicted future (T, >=2) in world coordinates, drawn on the road
            (under the vehicles) as a line with a dot per 0.1 s step
        :param neighbour_predictions: the neighbours' predicted futures (S, T, >=2), drawn the same way
        :param caption: text in the top-left corner (lines split at newlines)
        :param legend: write the colour key (:data:`LEGEND`) under the caption, one entry per line
        """
        surface = self.surface
        surface.blit(self.background, (0, 0))
        for path in [] if neighbour_predictions is None else neighbour_predictions:
            self._trajectory(path, PREDICTED_NEIGHBOUR_COLOR)
        if ego_prediction is not None:
            self._trajectory(ego_prediction, PREDICTED_EGO_COLOR)
        traffic = world.traffic
        for slot in traffic.indices:
            x, y, heading = traffic.pose[slot]
            color = CRASHED_COLOR if traffic.crashed[slot] else OTHER_COLOR
            self._vehicle(np.array([x, y]), heading, traffic.speed[slot], color)
        ego = world.ego
        self._vehicle(np.array([ego.x, ego.y]), ego.heading, ego.speed, EGO_COLOR)
        if candidates is not None:
            flags = np.zeros(len(candidates), bool) if masked is None else np.asarray(masked, bool)
            for (x, y, _), bad in zip(candidates, flags, strict=True):
                color = MASKED_COLOR if bad else CANDIDATE_COLOR
                pygame.draw.circle(surface, color, surface.pos2pix(x, y), max(3, surface.pix(0.6)))
        if chosen is not None:
            x, y, heading = chosen
            centre = surface.pos2pix(x, y)
            pygame.draw.circle(surface, CHOSEN_COLOR, centre, max(5, surface.pix(1.0)))
            tip = surface.pos2pix(x + 2.5 * np.cos(heading), y + 2.5 * np.sin(heading))
            pygame.draw.line(surface, CHOSEN_COLOR, centre, tip, 2)
        lines = [(line, TEXT_COLOR) for line in (caption or "").splitlines()]
        self._text(lines + (list(LEGEND) if legend else []))
        return np.ascontiguousarray(np.transpose(pygame.surfarray.array3d(surface), (1, 0, 2)))

    def _vehicle(
        self, position: FloatArray, heading: float, speed: float, color: tuple[int, int, int]
    ) -> None:
        vehicle = Vehicle(self.road, position, heading, speed)
        vehicle.color = color
        VehicleGraphics.display(vehicle, self.surface, offscreen=True)

    def _trajectory(self, path: FloatArray, color: tuple[int, int, int]) -> None:
        points = [self.surface.pos2pix(x, y) for x, y in np.asarray(path)[:, :2]]
        if len(points) > 1:
            pygame.draw.lines(self.surface, color, False, points, 2)
        for point in points:
            pygame.draw.circle(self.surface, color, point, 3)

    def _text(self, lines: list[tuple[str, tuple[int, int, int]]]) -> None:
        """Lines of coloured text on dark strips, one under the other from the top-left corner."""
        y = 4
        for text, color in lines:
            rendered = self.font.render(f" {text} ", True, color, TEXT_BACKGROUND)
            self.surface.blit(rendered, (4, y))
            y += rendered.get_height()
