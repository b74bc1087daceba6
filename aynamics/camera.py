"""Camera geometry of a scene: pose, OpenCV intrinsics/extrinsics, projection, view test.

The scene's camera sits at `position` and looks along +y, tilted down by `90 - orientation`
degrees: `orientation` is the angle between the optical axis and straight down (MuJoCo
`euler="orientation 0 0"`). MuJoCo/OpenGL cameras look down their -z axis with y up; the
OpenCV convention used for export has x right, y down, z forward.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from aynamics.scene import Camera

WIDTH, HEIGHT = 480, 320  # default image size (pixels): the paper's 480×320

# OpenGL camera axes (x right, y up, -z forward) -> OpenCV axes (x right, y down, z forward)
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def gl_rotation(camera: Camera) -> np.ndarray:
    """(3, 3) rotation from the MuJoCo (OpenGL) camera frame to the world: columns are cam x, y, z in world."""
    a = math.radians(camera.orientation)
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def gl_quaternion(camera: Camera) -> np.ndarray:
    """MuJoCo `cam_quat` (w, x, y, z) of the camera: a rotation about world x by `orientation`."""
    a = math.radians(camera.orientation) / 2
    return np.array([math.cos(a), math.sin(a), 0.0, 0.0])


@dataclass(frozen=True)
class CameraMatrices:
    """Pinhole camera in the OpenCV convention.

    Attributes:
        K: (3, 3) intrinsics, f = 0.5 H / tan(fovy / 2), principal point at the image centre.
        R: (3, 3) world -> camera rotation (x right, y down, z forward).
        t: (3,) world -> camera translation: x_cam = R @ x_world + t.
        width, height: image size in pixels.
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int

    @property
    def position(self) -> np.ndarray:
        return -self.R.T @ self.t

    def to_json(self) -> dict:
        return {
            "convention": "opencv: x right, y down, z forward; x_cam = R @ x_world + t; pixel = K @ x_cam / z",
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "world_to_camera": np.vstack([np.hstack([self.R, self.t[:, None]]), [0, 0, 0, 1]]).tolist(),
        }

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (..., 3) to pixels (..., 2) (x right, y down; pixel centres at +0.5) and depth (...)."""
        cam = points @ self.R.T + self.t
        z = cam[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (cam @ self.K.T)[..., :2] / z[..., None]
        return uv, z


def matrices(camera: Camera, width: int = WIDTH, height: int = HEIGHT) -> CameraMatrices:
    """OpenCV intrinsics and extrinsics of a scene camera for an image of `width` × `height`."""
    f = 0.5 * height / math.tan(math.radians(camera.fovy) / 2)
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    r_cv_to_world = gl_rotation(camera) @ _GL_TO_CV
    R = r_cv_to_world.T
    t = -R @ np.asarray(camera.position, dtype=float)
    return CameraMatrices(K=K, R=R, t=t, width=width, height=height)


def sphere_in_view(cam: CameraMatrices, centers: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Whether spheres (centres (..., 3), radii broadcastable) intersect the view frustum (conservative)."""
    x = centers @ cam.R.T + cam.t  # (..., 3) in camera coordinates
    fx, fy = cam.K[0, 0], cam.K[1, 1]
    half_w, half_h = cam.width / 2 / fx, cam.height / 2 / fy  # tan of the half-angles
    inside = x[..., 2] > -radii
    for axis, half in ((0, half_w), (1, half_h)):
        # distance of the centre to each side plane |x| = half * z, normalised
        norm = math.sqrt(1 + half * half)
        inside &= (x[..., axis] - half * x[..., 2]) / norm < radii
        inside &= (-x[..., axis] - half * x[..., 2]) / norm < radii
    return inside
