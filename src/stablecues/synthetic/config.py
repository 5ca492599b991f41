"""Settings of the synthetic town sequence."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import ConfigError

#: route rectangles (blocks along x, along y) tried when the size is chosen from the frame budget
ROUTE_SIZES = ((1, 1), (2, 1), (2, 2), (3, 2), (3, 3), (4, 3), (4, 4), (5, 4), (5, 5), (6, 5), (6, 6))
MEAN_BLOCK_M = 46.0


@dataclass(frozen=True)
class SyntheticTownConfig:
    """A synthetic drive through a procedural town.

    Attributes:
        frames: number of frames.
        width, height: image size in pixels.
        fov_deg: horizontal field of view (square pixels, principal point at the centre).
        baseline: stereo baseline in metres (the right camera sits this far to the right).
        loops: number of revisit laps after the first drive (0: no revisits). Revisit k cycles
            through: other lane offset, opposite direction, a third lane offset; every revisit is at
            another time of day, with other cars and people, and detours around a new block.
        clutter: density of trees, signs, fences, parked and moving cars, cyclists and
            pedestrians (0: an empty town, 1: normal, 2: busy).
        seed: everything (layout, textures, traffic, light) follows from it.
        step: wished metres between frames; the route rectangle is sized to come close (the
            actual step is the route length over ``frames``, reported in the sequence's metadata).
        route_blocks: (blocks along x, along y) of the route rectangle, or None to choose it from
            ``frames * step``.
        speed: driving speed in m/s; sets the timestamps.
        camera_height: metres above the road.
        noise: standard deviation of the sensor noise added to the images, grey levels.
        depth_map_factor: depth PNG units per metre (256: 4 mm steps, up to 256 m).
        max_depth: far clipping distance in metres.
    """

    frames: int = 300
    width: int = 512
    height: int = 384
    fov_deg: float = 70.0
    baseline: float = 0.3
    loops: int = 2
    clutter: float = 1.0
    seed: int = 0
    step: float = 2.0
    route_blocks: tuple[int, int] | None = None
    speed: float = 10.0
    camera_height: float = 1.5
    noise: float = 2.0
    depth_map_factor: float = 256.0
    max_depth: float = 250.0

    def validate(self) -> None:
        """Raise :class:`ConfigError` naming the first setting out of range."""
        checks = (
            ("frames", self.frames >= 1, ">= 1"),
            ("width", self.width >= 16, ">= 16"),
            ("height", self.height >= 16, ">= 16"),
            ("fov_deg", 10.0 <= self.fov_deg <= 150.0, "in [10, 150]"),
            ("baseline", self.baseline > 0, "> 0"),
            ("loops", 0 <= self.loops <= 50, "in [0, 50]"),
            ("clutter", 0.0 <= self.clutter <= 5.0, "in [0, 5]"),
            ("step", self.step > 0, "> 0"),
            ("speed", self.speed > 0, "> 0"),
            ("camera_height", 0.3 <= self.camera_height <= 5.0, "in [0.3, 5]"),
            ("noise", self.noise >= 0, ">= 0"),
            ("depth_map_factor", self.depth_map_factor > 0, "> 0"),
            ("max_depth", self.max_depth > 1.0, "> 1"),
        )
        for name, ok, want in checks:
            if not ok:
                raise ConfigError(f"SyntheticTownConfig.{name}: expected {want}, got {getattr(self, name)!r}")
        if self.route_blocks is not None:
            rb = tuple(self.route_blocks)
            if len(rb) != 2 or min(rb) < 1 or max(rb) > 20:
                raise ConfigError(
                    "SyntheticTownConfig.route_blocks: expected two integers in [1, 20], "
                    f"got {self.route_blocks!r}"
                )

    def route_size(self) -> tuple[int, int]:
        """Route rectangle in blocks: as set, or the one whose drive length best fits frames * step."""
        if self.route_blocks is not None:
            return int(self.route_blocks[0]), int(self.route_blocks[1])
        target = self.frames * self.step
        best, best_err = ROUTE_SIZES[0], math.inf
        for w, h in ROUTE_SIZES:
            lap = 2.0 * (w + h) * MEAN_BLOCK_M
            total = lap + self.loops * (lap + 2.0 * MEAN_BLOCK_M)
            err = abs(math.log(total / target))
            if err < best_err:
                best, best_err = (w, h), err
        return best
