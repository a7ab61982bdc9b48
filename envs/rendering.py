"""RGB frames of the junction drawn with highway-env's road and vehicle graphics (offscreen pygame)."""

from __future__ import annotations

import os

import numpy as np

from gccp_envs.geometry import FloatArray
from gccp_envs.scenario import IntersectionLayout
from gccp_envs.world import IntersectionWorld

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
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


class IntersectionRenderer:
    """Draws the road once per layout, then vehicles and subgoals on top of it each frame.

    :param layout: the junction to draw
    :param size: frame width and height [px]
    :param view: metres shown across the frame, centred on the junction
    """

    def __init__(self, layout: IntersectionLayout, size: int = 600, view: float = 100.0) -> None:
        pygame.init()
        self.layout = layout
        self.size = size
        self.road = Road(network=layout.road_network())
        self.surface = WorldSurface((size, size), 0, pygame.Surface((size, size)))
        self.surface.scaling = size / view
        self.surface.centering_position = [0.5, 0.5]
        self.surface.move_display_window_to(np.zeros(2))
        RoadGraphics.display(self.road, self.surface)
        self._shade_off_road()
        self.background = self.surface.copy()

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
    ) -> np.ndarray:
        """One frame (H, W, 3) uint8 of the world's current step.

        :param candidates: subgoal candidates (N, 3) in world coordinates, drawn as dots
        :param chosen: the chosen subgoal (x, y, heading), drawn as a large dot with a heading tick
        :param masked: bool (N,), candidates the GCCP module masks (drawn red)
        """
        surface = self.surface
        surface.blit(self.background, (0, 0))
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
        return np.ascontiguousarray(np.transpose(pygame.surfarray.array3d(surface), (1, 0, 2)))

    def _vehicle(
        self, position: FloatArray, heading: float, speed: float, color: tuple[int, int, int]
    ) -> None:
        vehicle = Vehicle(self.road, position, heading, speed)
        vehicle.color = color
        VehicleGraphics.display(vehicle, self.surface, offscreen=True)
