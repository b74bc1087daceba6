"""Exact optical flow (the motion field) from simulator states and depth, its colour coding, frame sampling.

The flow of a pixel between video frames k and k + 1 is where the surface point it sees at frame k is seen at
frame k + 1: unproject the pixel with its depth to a world point P on body b, carry it with the body
(`P' = R1 R0ᵀ (P − x0) + x1`), project P' with the camera and subtract the pixel centre (as Kubric's forward
flow). Static geometry (floor, sky) has zero flow. A flow vector is *occluded* when P' leaves the image, falls
behind the camera, or is hidden at frame k + 1 (another surface is nearer there, or the target pixel shows a
different object).

Frame convention: `simulate` gives T = 31 states for 1 s at 30 FPS (state 0 = initial). The video is the first
30 states (frames 0..29, frame k at t = k / fps); it has 29 flow maps, flow map k going from frame k to k + 1.
The model sees every third frame, `sample_frames(30) = [0, 3, ..., 27]` (frame 0 included), and the flow maps
at the same indices.

    flow, occluded = motion_flow(scene, rollout, frames.depth, cam, frames.segmentation)
    images = flow_to_color(flow)  # (T-1, H, W, 3) uint8, the standard colour wheel
"""

from __future__ import annotations

import numpy as np

from aynamics.camera import CameraMatrices
from aynamics.scene import Scene

FRAME_STRIDE = 3  # the paper samples every third frame: 10 of 30
OCCLUSION_TOLERANCE = 0.01  # relative depth slack (1 %) before a carried point counts as hidden


def sample_frames(n_frames: int, stride: int = FRAME_STRIDE) -> np.ndarray:
    """Indices of the sampled frames: 0, stride, 2·stride, ..., `n_frames // stride` of them (10 of 30).

    Frame 0 (the initial state) is always included. With 31 states this still gives 10 frames, 0..27.
    """
    if n_frames < 1 or stride < 1:
        raise ValueError(f"sample_frames(n_frames={n_frames}, stride={stride}): both must be >= 1")
    return np.arange(max(1, n_frames // stride)) * stride


def pixel_rays(cam: CameraMatrices) -> np.ndarray:
    """(H, W, 3) world directions through the pixel centres, scaled so that their optical-axis component is 1.

    A point seen at depth z (along the optical axis) in pixel (v, u) is `cam.position + z * rays[v, u]`.
    """
    u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)  # (H, W, 3)
    cam_dirs = pix @ np.linalg.inv(cam.K).T  # z = 1 in camera coordinates
    return cam_dirs @ cam.R  # camera -> world: R^T x, written for row vectors


def quat_to_mat(q: np.ndarray) -> np.ndarray:
    """(..., 4) w, x, y, z quaternions (normalised here) -> (..., 3, 3) rotation matrices."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def carry_points(
    points: np.ndarray,
    body: np.ndarray,
    pos0: np.ndarray,
    rot0: np.ndarray,
    pos1: np.ndarray,
    rot1: np.ndarray,
) -> np.ndarray:
    """Move world points (P, 3) rigidly with their bodies (P,) from pose 0 to pose 1.

    Poses are per body: positions (N, 3), rotation matrices (N, 3, 3). `P' = R1 R0ᵀ (P − x0) + x1`.
    """
    local = np.einsum("pji,pj->pi", rot0[body], points - pos0[body])  # R0ᵀ (P − x0)
    return np.einsum("pij,pj->pi", rot1[body], local) + pos1[body]


def motion_field(
    depth: np.ndarray,
    segmentation: np.ndarray,
    cam: CameraMatrices,
    position: np.ndarray,
    orientation: np.ndarray,
    next_depth: np.ndarray | None = None,
    next_segmentation: np.ndarray | None = None,
    rays: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Flow of one frame to the next from depth, segmentation and the two poses of every object.

    Args:
        depth: (H, W) metres along the optical axis at frame k (np.inf where nothing is hit).
        segmentation: (H, W) object index at frame k, -1 for floor and background (static: zero flow).
        cam: the camera (same at both frames).
        position: (2, N, 3) object centres at frames k and k + 1.
        orientation: (2, N, 4) w, x, y, z quaternions at frames k and k + 1.
        next_depth, next_segmentation: depth and segmentation at frame k + 1, for the occlusion test; without
            them only points leaving the image or passing behind the camera count as occluded.
        rays: `pixel_rays(cam)`, when the caller has it already (it depends on the camera only).

    Returns:
        flow (H, W, 2) float32 pixels (dx right, dy down) and occluded (H, W) bool.
    """
    h, w = segmentation.shape
    flow = np.zeros((h, w, 2), np.float32)
    occluded = np.zeros((h, w), bool)
    if next_segmentation is not None:
        occluded |= (segmentation < 0) & (next_segmentation >= 0)  # static floor point covered by an object
    vv, uu = np.nonzero((segmentation >= 0) & np.isfinite(depth))
    if len(vv) == 0:
        return flow, occluded
    body = segmentation[vv, uu].astype(np.intp)
    rays = (pixel_rays(cam) if rays is None else rays)[vv, uu]  # (P, 3)
    points = cam.position + depth[vv, uu, None] * rays
    rot = quat_to_mat(np.asarray(orientation, float))
    moved = carry_points(points, body, position[0], rot[0], position[1], rot[1])
    uv1, z1 = cam.project(moved)
    uv0 = np.stack([uu + 0.5, vv + 0.5], axis=-1)
    flow[vv, uu] = uv1 - uv0
    hidden = (z1 <= 0) | (uv1[:, 0] < 0) | (uv1[:, 0] >= w) | (uv1[:, 1] < 0) | (uv1[:, 1] >= h)
    if next_depth is not None and next_segmentation is not None:
        inside = ~hidden
        tu = np.clip(uv1[:, 0], 0, w - 1).astype(np.intp)
        tv = np.clip(uv1[:, 1], 0, h - 1).astype(np.intp)
        nearer = next_depth[tv, tu] < z1 * (1 - OCCLUSION_TOLERANCE)
        other = next_segmentation[tv, tu] != body
        hidden |= inside & (nearer | other)
    occluded[vv, uu] = hidden
    return flow, occluded


def motion_flow(
    scene: Scene,
    rollout,
    depth: np.ndarray,
    cam: CameraMatrices,
    segmentation: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact forward flow between consecutive rendered frames, with an occlusion mask.

    Args:
        scene: the scene (its objects index the segmentation).
        rollout: its `Rollout`; rendered frame k is state k.
        depth: (T, H, W) metres along the optical axis (np.inf: background), T <= the rollout's states.
        cam: the camera matrices at the depth maps' resolution.
        segmentation: (T, H, W) object index, -1 for floor and background.

    Returns:
        flow (T-1, H, W, 2) float32 pixels (dx right, dy down) and occluded (T-1, H, W) bool: 29 maps for 30 frames.
    """
    depth = np.asarray(depth)
    segmentation = np.asarray(segmentation)
    n_frames = depth.shape[0]
    if segmentation.shape != depth.shape:
        raise ValueError(f"segmentation shape {segmentation.shape} != depth shape {depth.shape}")
    if depth.shape[1:] != (cam.height, cam.width):
        raise ValueError(f"depth maps are {depth.shape[1:]} (H, W) but the camera is {cam.height}×{cam.width}")
    if n_frames > len(rollout.t):
        raise ValueError(f"{n_frames} depth maps but the rollout has only {len(rollout.t)} states")
    if len(rollout.names) != len(scene.objects):
        raise ValueError(f"rollout has {len(rollout.names)} objects, scene has {len(scene.objects)}")
    h, w = depth.shape[1:]
    flow = np.zeros((max(n_frames - 1, 0), h, w, 2), np.float32)
    occluded = np.zeros((max(n_frames - 1, 0), h, w), bool)
    rays = pixel_rays(cam)
    for k in range(n_frames - 1):
        flow[k], occluded[k] = motion_field(
            depth[k],
            segmentation[k],
            cam,
            rollout.position[k : k + 2],
            rollout.orientation[k : k + 2],
            depth[k + 1],
            segmentation[k + 1],
            rays,
        )
    return flow, occluded


# --------------------------------------------------------------------------------------------
# The standard flow colour wheel (Baker et al., "A Database and Evaluation Methodology for Optical Flow")
# --------------------------------------------------------------------------------------------
def _color_wheel() -> np.ndarray:
    """(55, 3) colours of the Middlebury wheel: red, yellow, green, cyan, blue, magenta in 15/6/4/11/13/6 steps."""
    segments = [(15, (255, 0, 0), (255, 255, 0)), (6, (255, 255, 0), (0, 255, 0)), (4, (0, 255, 0), (0, 255, 255))]
    segments += [(11, (0, 255, 255), (0, 0, 255)), (13, (0, 0, 255), (255, 0, 255)), (6, (255, 0, 255), (255, 0, 0))]
    rows = []
    for n, a, b in segments:
        f = np.arange(n)[:, None] / n
        rows.append((1 - f) * np.array(a) + f * np.array(b))
    return np.concatenate(rows)


_WHEEL = _color_wheel()


def flow_to_color(flow: np.ndarray, max_norm: float | None = None) -> np.ndarray:
    """Flow (..., 2) as colour images (..., 3) uint8 on the standard colour wheel.

    Hue gives the direction (right = red, down = orange-yellow, left = cyan, up = blue-violet, as in Middlebury),
    saturation the magnitude relative to `max_norm` (default: the largest finite magnitude in the array, so a
    whole video shares one scale when passed at once); zero flow is white. Magnitudes above `max_norm` are darkened.
    """
    flow = np.nan_to_num(np.asarray(flow, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if flow.shape[-1] != 2:
        raise ValueError(f"flow_to_color: last axis must be 2 (dx, dy), got shape {flow.shape}")
    u, v = flow[..., 0], flow[..., 1]
    mag = np.hypot(u, v)
    if max_norm is None:
        max_norm = float(mag.max()) if mag.size else 0.0
    if max_norm < 0:
        raise ValueError(f"max_norm = {max_norm}: must be >= 0")
    rad = mag / max_norm if max_norm > 0 else np.zeros_like(mag)
    ncols = len(_WHEEL)
    a = np.arctan2(-v, -u) / np.pi  # in [-1, 1]
    fk = (a + 1) / 2 * (ncols - 1)
    k0 = np.floor(fk).astype(int)
    k1 = (k0 + 1) % ncols
    f = (fk - k0)[..., None]
    col = ((1 - f) * _WHEEL[k0] + f * _WHEEL[k1]) / 255.0  # (..., 3)
    r = rad[..., None]
    inside = r <= 1
    col = np.where(inside, 1 - r * (1 - col), col * 0.75)
    return np.floor(255 * np.clip(col, 0, 1)).astype(np.uint8)
