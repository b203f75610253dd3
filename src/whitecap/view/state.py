"""The viewer's state as plain data: what is shown, where the camera is, what plays.

Input handling changes these objects; drawing only reads them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class OrbitCamera:
    """A camera orbiting ``target`` at ``distance``; z is up.

    ``yaw`` is the angle about z and ``pitch`` the elevation, both in radians,
    of the eye as seen from the target.
    """

    target: np.ndarray
    distance: float
    yaw: float
    pitch: float
    fov: float = 45.0  # vertical field of view [deg]

    @classmethod
    def looking(cls, eye, target, fov: float) -> "OrbitCamera":
        eye, target = np.asarray(eye, float), np.asarray(target, float)
        d = eye - target
        dist = float(np.linalg.norm(d)) or 1.0
        return cls(target, dist, math.atan2(d[1], d[0]), math.asin(np.clip(d[2] / dist, -1, 1)), fov)

    @property
    def eye(self) -> np.ndarray:
        cp = math.cos(self.pitch)
        return self.target + self.distance * np.array(
            [cp * math.cos(self.yaw), cp * math.sin(self.yaw), math.sin(self.pitch)]
        )

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Forward, right and up unit vectors of the view."""
        f = self.target - self.eye
        f /= np.linalg.norm(f)
        r = np.cross(f, [0.0, 0.0, 1.0])
        r /= np.linalg.norm(r) or 1.0
        return f, r, np.cross(r, f)

    def orbit(self, dyaw: float, dpitch: float) -> None:
        self.yaw += dyaw
        self.pitch = float(np.clip(self.pitch + dpitch, -1.55, 1.55))

    def pan(self, dx: float, dy: float) -> None:
        """Move the target in the view plane by fractions of the distance."""
        _, r, u = self.basis()
        self.target = self.target + self.distance * (-dx * r - dy * u)

    def zoom(self, factor: float) -> None:
        self.distance = float(np.clip(self.distance * factor, 1e-3, 1e4))

    def move(self, forward: float, right: float, up: float) -> None:
        """Move eye and target together (WASD/QE), in metres."""
        f, r, _ = self.basis()
        self.target = self.target + forward * f + right * r + up * np.array([0.0, 0.0, 1.0])


@dataclass
class Visibility:
    fluid: bool = True
    diffuse: bool = True
    obstacles: bool = True
    domain: bool = True


@dataclass
class ViewerState:
    """Everything the viewer shows, independent of the window."""

    camera: OrbitCamera
    frame: int = 0                # index into the source's frames (playback) or frames simulated (live)
    sim_time: float = 0.0         # simulated time of the frame shown [s]
    paused: bool = False
    step_once: bool = False
    loop: bool = True
    show_help: bool = False
    recording: bool = False
    reset: bool = False
    screenshot: bool = False
    color_mode: str = "speed"
    color_range: tuple[float, float] | None = None
    visible: Visibility = field(default_factory=Visibility)
    steps_per_s: float = 0.0      # solver substeps per wall second (live)
    fps: float = 0.0              # drawn frames per wall second
    counts: dict[str, int] = field(default_factory=dict)
    record_index: int = 0
    shot_index: int = 0
    quit: bool = False
    last_advance: float | None = None  # clock reading at the last playback frame change [s]; None: never
