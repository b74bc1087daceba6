"""Exact optical flow (the motion field) from simulator states and depth, its colour coding, frame sampling.

The flow of a pixel between video frames k and k + 1 is where the surface point it sees at frame k is seen at
frame k + 1: unproject the pixel with its depth to a world point P on body b, carry it with the body
(`P' = R1 R0ᵀ (P − x0) + x1`), project P' with the camera and subtract the pixel centre (as Kubric's forward
flow). Static geometry (floor, sky) has zero flow. A flow vector is *occluded* when P' leaves the image, falls
behind the camera, or is out of sight at frame k + 1: MuJoCo's ray from the camera to P' meets a surface before
it (`scene_sight`; `raycast` casts the same test in its batches). A floor pixel that an object covers at k + 1
is occluded too. (Looking P' up in the next frame's depth and segmentation instead flagged 3.6 % of the object
pixels of 30 sampled scenes rendered at 160×120, the ray 1.2 %: the lookup also flags points landing just off
their object's edge and on surfaces seen at a slant.)

Frame convention: `simulate` gives T = 31 states for 1 s at 30 FPS (state 0 = initial). The video is the first
30 states (frames 0..29, frame k at t = k / fps); it has 29 flow maps, flow map k going from frame k to k + 1.
The model sees every third frame, `sample_frames(30) = [0, 3, ..., 27]` (frame 0 included), and the flow maps
at the same indices.

    flow, occluded = motion_flow(scene, rollout, frames.depth, cam, frames.segmentation)
    images = flow_to_color(flow)  # (T-1, H, W, 3) uint8, the standard colour wheel
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

from aynamics.camera import CameraMatrices
from aynamics.scene import Scene, require_scene
from aynamics.simulate import quat_to_mat

FRAME_STRIDE = 3  # the paper samples every third frame: 10 of 30
OCCLUSION_TOLERANCE = 0.01  # slack (1 %) for a rendered depth map's imprecision before a point counts as hidden


def sample_frames(n_frames: int, stride: int = FRAME_STRIDE) -> np.ndarray:
    """Indices of the sampled frames: 0, stride, 2·stride, ..., `n_frames // stride` of them (10 of 30).

    Frame 0 (the initial state) is always included. With 31 states this still gives 10 frames, 0..27.
    """
    if n_frames < 1 or stride < 1:
        raise ValueError(f"sample_frames(n_frames={n_frames}, stride={stride}): both must be >= 1")
    return np.arange(max(1, n_frames // stride)) * stride


def pixel_rays(cam: CameraMatrices, u: np.ndarray | None = None, v: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) world directions through the pixel centres (or through the image points of columns `u` and rows
    `v`, in pixels: `raycast.SampleGrid`), scaled so that their optical-axis component is 1.

    A point seen at depth z (along the optical axis) in pixel (v, u) is `cam.position + z * rays[v, u]`.
    """
    u = np.arange(cam.width) + 0.5 if u is None else np.asarray(u, float)
    v = np.arange(cam.height) + 0.5 if v is None else np.asarray(v, float)
    u, v = np.meshgrid(u, v)
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)  # (H, W, 3)
    cam_dirs = pix @ np.linalg.inv(cam.K).T  # z = 1 in camera coordinates
    return cam_dirs @ cam.R  # camera -> world: R^T x, written for row vectors


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


def body_homographies(
    cam: CameraMatrices, position: np.ndarray, orientation: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-body maps from a pixel's depth-scaled homogeneous coordinates at frame k to its image at frame k + 1.

    A pixel (u, v) at depth z is the camera-frame point `p = z K⁻¹ [u, v, 1]` and the world point
    `P = Rcᵀ (p − tc)`. Body b carries it to `P' = M (P − o0) + o1` (`M = R1 R0ᵀ`, centres o0, o1), seen at
    `p' = Rc P' + tc = (Rc M Rcᵀ) p + Rc (o1 − M o0) + tc − Rc M Rcᵀ tc`. Hence `q = K p' = A (z [u, v, 1]) + c` with
    `A = K Rc M Rcᵀ K⁻¹` and `c = K (Rc (o1 − M o0) + tc − Rc M Rcᵀ tc)`: the pixel at frame k + 1 is q[:2] / q[2]
    and q[2] its depth (K's last row is [0, 0, 1]). One 3×3 product per pixel instead of unproject, carry, project.

    Args:
        cam: the camera.
        position: (2, N, 3) body centres at frames k and k + 1.
        orientation: (2, N, 4) w, x, y, z quaternions at frames k and k + 1.

    Returns:
        A (N, 3, 3) and c (N, 3).
    """
    rot = quat_to_mat(np.asarray(orientation, float))  # (2, N, 3, 3)
    position = np.asarray(position, float)
    motion = rot[1] @ np.swapaxes(rot[0], -1, -2)  # (N, 3, 3): R1 R0ᵀ
    cam_motion = cam.R @ motion @ cam.R.T  # (N, 3, 3): the same rotation in camera axes
    A = cam.K @ cam_motion @ np.linalg.inv(cam.K)
    shift = position[1] - np.einsum("nij,nj->ni", motion, position[0])  # (N, 3): x1 − M x0 (world)
    c = (shift @ cam.R.T + cam.t - cam_motion @ cam.t) @ cam.K.T
    return A, c


def motion_field(
    depth: np.ndarray,
    segmentation: np.ndarray,
    cam: CameraMatrices,
    position: np.ndarray,
    orientation: np.ndarray,
    next_depth: np.ndarray | None = None,
    next_segmentation: np.ndarray | None = None,
    rays: np.ndarray | None = None,
    occlusion: bool = True,
    sight: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Flow of one frame to the next from depth, segmentation and the two poses of every object.

    Args:
        depth: (H, W) metres along the optical axis at frame k (np.inf where nothing is hit).
        segmentation: (H, W) object index at frame k, -1 for floor and background (static: zero flow).
        cam: the camera (same at both frames).
        position: (2, N, 3) object centres at frames k and k + 1.
        orientation: (2, N, 4) w, x, y, z quaternions at frames k and k + 1.
        next_depth, next_segmentation: depth and segmentation at frame k + 1, for the occlusion test; without
            them only points leaving the image or passing behind the camera count as occluded.
        rays: unused (kept for callers of the ray-based version: pixels are now mapped by `body_homographies`).
        occlusion: False skips the occlusion mask (returned as None) when only the flow is wanted.
        sight: given the object pixels' points carried to frame k + 1 ((P, 3) world), whether each is the first
            surface the camera's ray to it meets there (`scene_sight`): the exact test. Without it a carried point
            is hidden where the next frame's pixel it lands in shows another object or a surface more than
            `OCCLUSION_TOLERANCE` nearer, which also flags points landing just off their object's edge and on
            surfaces seen at a slant.

    Returns:
        flow (H, W, 2) float32 pixels (dx right, dy down) and occluded (H, W) bool (None if `occlusion` is False).
    """
    del rays
    h, w = segmentation.shape
    flow = np.zeros((h, w, 2), np.float32)
    occluded = np.zeros((h, w), bool) if occlusion else None
    if occlusion and next_segmentation is not None:
        occluded |= (segmentation < 0) & (next_segmentation >= 0)  # static floor point covered by an object
    vv, uu = np.nonzero((segmentation >= 0) & np.isfinite(depth))
    if len(vv) == 0:
        return flow, occluded
    body = segmentation[vv, uu].astype(np.intp)
    A, c = body_homographies(cam, position, orientation)
    z = depth[vv, uu].astype(np.float64)
    u0, v0 = uu + 0.5, vv + 0.5
    zpix = np.stack([z * u0, z * v0, z], axis=-1)  # (P, 3)
    q = np.einsum("pij,pj->pi", A[body], zpix) + c[body]  # (P, 3): K x1
    z1 = q[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u1, v1 = q[:, 0] / z1, q[:, 1] / z1
    flow[vv, uu, 0] = u1 - u0
    flow[vv, uu, 1] = v1 - v0
    if not occlusion:
        return flow, None
    # a point without a landing place (a diverged rollout's NaN pose) is lost too; comparisons with NaN are False
    hidden = ~(np.isfinite(u1) & np.isfinite(v1) & (z1 > 0)) | (u1 < 0) | (u1 >= w) | (v1 < 0) | (v1 >= h)
    if sight is not None:  # q = K p' is the carried point in camera axes: P' = Rcᵀ K⁻¹ q + the camera's centre
        hidden |= ~sight(cam.position + (q @ np.linalg.inv(cam.K).T) @ cam.R)
    elif next_depth is not None and next_segmentation is not None:
        inside = ~hidden
        tu = np.clip(np.nan_to_num(u1), 0, w - 1).astype(np.intp)  # (NaN cast to an index was -2^63: IndexError)
        tv = np.clip(np.nan_to_num(v1), 0, h - 1).astype(np.intp)
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
    require_scene(scene, "motion_flow: scene")
    if not isinstance(cam, CameraMatrices):
        raise TypeError(f"motion_flow: cam is a {type(cam).__name__}, not CameraMatrices (render(...).camera)")
    depth = np.asarray(depth)
    segmentation = np.asarray(segmentation)
    if depth.ndim != 3 or not np.issubdtype(depth.dtype, np.number):
        raise ValueError(f"depth: shape {depth.shape}, dtype {depth.dtype}: must be (T, H, W) numbers")
    n_frames = depth.shape[0]
    if segmentation.shape != depth.shape:
        raise ValueError(f"segmentation shape {segmentation.shape} != depth shape {depth.shape}")
    n_obj = len(scene.objects)
    seg_ok = np.issubdtype(segmentation.dtype, np.number) and segmentation.dtype != bool
    if seg_ok and segmentation.size:
        with np.errstate(invalid="ignore"):
            bad = ~((segmentation == np.round(segmentation)) & (segmentation >= -1) & (segmentation < n_obj))
        if bad.any():  # an id past the scene's objects was an IndexError inside; 0.5 was truncated to object 0
            f, v, u = (int(k) for k in np.argwhere(bad)[0])
            raise ValueError(
                f"segmentation: value {segmentation[f, v, u]} at frame {f}, row {v}, column {u}: must be -1 "
                f"(background) or an object index 0..{n_obj - 1} of the scene"
            )
    elif not seg_ok:
        raise ValueError(f"segmentation: dtype {segmentation.dtype}: must hold object indices (-1 background)")
    on_object = segmentation >= 0
    with np.errstate(invalid="ignore"):
        bad = on_object & ~(np.isfinite(depth) & (depth > 0))
    if bad.any():  # NaN depth dropped the pixel (flow 0, not occluded); a negative depth gave a wrong flow
        f, v, u = (int(k) for k in np.argwhere(bad)[0])
        raise ValueError(
            f"depth: {depth[f, v, u]} m at frame {f}, row {v}, column {u}, an object pixel: object depths must be "
            "finite and > 0 (np.inf only where the segmentation is -1)"
        )
    if depth.shape[1:] != (cam.height, cam.width):
        raise ValueError(f"depth maps are {depth.shape[1:]} (H, W) but the camera is {cam.height}×{cam.width}")
    if n_frames > len(rollout.t):
        raise ValueError(f"{n_frames} depth maps but the rollout has only {len(rollout.t)} states")
    if len(rollout.names) != len(scene.objects):
        raise ValueError(f"rollout has {len(rollout.names)} objects, scene has {len(scene.objects)}")
    h, w = depth.shape[1:]
    flow = np.zeros((max(n_frames - 1, 0), h, w, 2), np.float32)
    occluded = np.zeros((max(n_frames - 1, 0), h, w), bool)
    sight = scene_sight(scene, rollout, cam.position)
    for k in range(n_frames - 1):
        flow[k], occluded[k] = motion_field(
            depth[k],
            segmentation[k],
            cam,
            rollout.position[k : k + 2],
            rollout.orientation[k : k + 2],
            depth[k + 1],
            segmentation[k + 1],
            sight=functools.partial(sight, k + 1),
        )
    return flow, occluded


def scene_sight(
    scene: Scene, rollout, origin: np.ndarray, slack: float = OCCLUSION_TOLERANCE
) -> Callable[[int, np.ndarray], np.ndarray]:
    """`sight(k, points)`: (P,) whether each world point (P, 3) is what a camera at `origin` sees in its direction at
    state k of the rollout: MuJoCo's ray from the camera to the point (`mj_multiRay`, floor and objects) meets
    nothing before `1 - slack` of the way. `slack` covers the depth the point was unprojected from: a rendered
    depth map's precision (`OCCLUSION_TOLERANCE`, 1 %); ray-cast depth is exact (`raycast.RAY_SLACK`)."""
    import mujoco

    from aynamics.simulate import compile_scene

    model, tpl = compile_scene(scene)
    data = mujoco.MjData(model)
    origin = np.asarray(origin, float)
    cols = tpl.qpos_adr[:, None] + np.arange(7)

    def sight(k: int, points: np.ndarray) -> np.ndarray:
        pose = np.concatenate([rollout.position[k], rollout.orientation[k]], axis=-1)  # (N, 7)
        data.qpos[cols] = np.nan_to_num(pose)  # a diverged rollout's NaN pose: its points are not finite, unseen
        mujoco.mj_kinematics(model, data)
        to_point = np.asarray(points, float) - origin
        length = np.linalg.norm(to_point, axis=1)
        ok = np.isfinite(length) & (length > 0)
        seen = np.zeros(len(to_point), bool)
        if ok.any():
            vec = np.ascontiguousarray(to_point[ok] / length[ok, None])
            dist = np.empty(len(vec))
            geom = np.empty(len(vec), np.int32)
            mujoco.mj_multiRay(model, data, origin, vec.ravel(), None, True, -1, geom, dist, None, len(vec), np.inf)
            seen[ok] = (dist < 0) | (dist >= length[ok] * (1 - slack))  # -1: nothing met (a grazing miss)
        return seen

    return sight


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
    Only moving pixels are coloured (zero, NaN and infinite flow are white): a static floor and sky cost nothing.
    """
    flow = np.asarray(flow)
    if flow.ndim == 0 or flow.shape[-1] != 2:
        raise ValueError(f"flow_to_color: last axis must be 2 (dx, dy), got shape {flow.shape}")
    if flow.ndim == 1:  # one vector
        return flow_to_color(flow[None], max_norm)[0]
    out = np.full((*flow.shape[:-1], 3), 255, np.uint8)
    candidates = (flow[..., 0] != 0) | (flow[..., 1] != 0)  # (...,) moving, NaN or infinite: one pass, no copies
    sub = flow[candidates].astype(np.float64)  # (P, 2)
    sub[~np.isfinite(sub)] = 0.0  # NaN and infinite flow count as zero
    mag = np.hypot(sub[:, 0], sub[:, 1])
    if max_norm is None:
        max_norm = float(mag.max()) if mag.size else 0.0
    if max_norm < 0:
        raise ValueError(f"max_norm = {max_norm}: must be >= 0")
    moving = mag > 0
    if max_norm == 0 or not moving.any():
        return out
    where = tuple(ix[moving] for ix in np.nonzero(candidates))
    u, v, rad = sub[moving, 0], sub[moving, 1], mag[moving] / max_norm  # (P,)
    ncols = len(_WHEEL)
    a = np.arctan2(-v, -u) / np.pi  # in [-1, 1]
    fk = (a + 1) / 2 * (ncols - 1)
    k0 = np.floor(fk).astype(int)
    k1 = (k0 + 1) % ncols
    f = (fk - k0)[:, None]
    col = ((1 - f) * _WHEEL[k0] + f * _WHEEL[k1]) / 255.0  # (P, 3)
    inside = rad <= 1
    col[inside] = 1 - rad[inside, None] * (1 - col[inside])  # desaturate towards white with the magnitude
    col[~inside] *= 0.75  # beyond max_norm: darker
    np.clip(col, 0, 1, out=col)
    col *= 255
    out[where] = np.floor(col, out=col).astype(np.uint8)
    return out


# Hue knots of the Middlebury wheel (red, yellow, green, cyan, blue, magenta, red) and their positions on the
# 55-colour wheel above (segments of 15, 6, 4, 11, 13, 6 colours).
_HUE_KNOTS = np.array([0, 1, 2, 3, 4, 5, 6]) / 6
_WHEEL_KNOTS = np.array([0, 15, 21, 25, 36, 49, 55], float)
_NCOLS = 55


def decode_flow_colors(images: np.ndarray, flow_max: float) -> np.ndarray:
    """Invert `flow_to_color` (without darkened over-range pixels): colour images back to flow.

    The wheel colour of a direction has one channel at 1 and one at 0, so with saturation r the encoded colour
    is `1 - r (1 - wheel)`: r = 1 - min channel, and the wheel colour (hence the direction, through the hue,
    which is piecewise linear along the wheel) follows. Quantisation to 8 bits limits the accuracy to about
    `flow_max / 255` in magnitude and a fraction of a wheel step (360° / 55) in direction.

    Args:
        images: (..., 3) uint8 colour-coded flow.
        flow_max: The magnitude of saturation 1 (pixels), as stored with the images.

    Returns:
        (..., 2) float32 flow (dx right, dy down) in pixels; white decodes to 0.
    """
    from matplotlib.colors import rgb_to_hsv

    images = np.asarray(images)
    if images.shape[-1:] != (3,) or images.dtype != np.uint8:
        raise ValueError(f"flow images: shape {images.shape} dtype {images.dtype}, expected (..., 3) uint8")
    if not np.isfinite(flow_max) or flow_max < 0:
        raise ValueError(f"flow_max = {flow_max}: must be a finite number >= 0")
    col = np.clip((images.astype(np.float64) + 0.5) / 255.0, 0.0, 1.0)  # undo the floor of the encoder
    col[images == 255] = 1.0
    r = 1.0 - col.min(axis=-1)  # (...,)
    moving = r > 1.0 / 255.0
    out = np.zeros((*images.shape[:-1], 2), np.float32)
    if flow_max == 0 or not moving.any():
        return out
    rm = r[moving][:, None]
    wheel = np.clip(1.0 - (1.0 - col[moving]) / rm, 0.0, 1.0)  # (M, 3) the wheel colour
    hue = rgb_to_hsv(wheel)[:, 0]
    pos = np.interp(hue, _HUE_KNOTS, _WHEEL_KNOTS)  # position on the wheel, [0, 55)
    pos = np.where(pos > _NCOLS - 0.5, 0.0, np.minimum(pos, _NCOLS - 1))  # past the last colour: back to red
    theta = (pos / (_NCOLS - 1) * 2 - 1) * np.pi  # = atan2(-v, -u)
    mag = np.minimum(rm[:, 0], 1.0) * flow_max
    out[moving] = np.stack([-mag * np.cos(theta), -mag * np.sin(theta)], axis=-1)
    return out


def on_own_scale(images: np.ndarray) -> np.ndarray:
    """Colour-wheel flow images (F, H, W, 3) uint8 re-coloured on the scale of their own largest flow, the
    convention of generated records (whose sampled flows share one scale) and so of what a flow-trained model saw.

    `aynamics render` colours all 29 flows of a video on one scale, other tools on theirs: the sampled images of
    such a video are paler or darker than the model knows. Re-colouring decodes the relative magnitudes and
    encodes them against their maximum (within 2 levels of 255); images already on it come back unchanged.
    """
    images = np.asarray(images)
    relative = decode_flow_colors(images, 1.0)  # (F, H, W, 2), magnitudes <= 1
    if not relative.any() or np.hypot(relative[..., 0], relative[..., 1]).max() > 1 - 1 / 255:
        return images
    return flow_to_color(relative)
