"""Pictures of the convoy in traffic through highway-env's renderer (pygame, off screen).

The view follows the convoy's middle; convoy vehicles carry their mode's colour
(``openconvoy.envs.render.MODE_COLOURS``), traffic highway-env's default colours.
"""

from __future__ import annotations

import os

import numpy as np

from openconvoy.envs.traffic.world import TrafficWorld


def draw_highway(
    world: TrafficWorld, size: tuple[int, int] = (100, 900), scaling: float = 5.0
) -> np.ndarray:
    """An RGB image (H x W x 3, uint8) of the road around the convoy; ``scaling`` px/m."""
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # off screen: no display needed
    import pygame
    from highway_env.road.graphics import RoadGraphics, WorldSurface

    h_px, w_px = size
    surface = WorldSurface((w_px, h_px), 0, pygame.Surface((w_px, h_px)))
    surface.scaling = scaling
    surface.centering_position = [0.5, 0.5]
    xs = [v.position[0] for v in world.convoy]
    ys = [v.position[1] for v in world.convoy]
    surface.move_display_window_to(np.array([0.5 * (min(xs) + max(xs)), 0.5 * (min(ys) + max(ys))]))
    RoadGraphics.display(world.road, surface)
    RoadGraphics.display_road_objects(world.road, surface, offscreen=True)
    RoadGraphics.display_traffic(world.road, surface, offscreen=True)
    return np.ascontiguousarray(np.moveaxis(pygame.surfarray.array3d(surface), 0, 1))
