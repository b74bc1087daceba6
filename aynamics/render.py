"""Headless OpenGL rendering of a rollout: RGB, instance segmentation and depth, with randomised appearance.

MuJoCo renders offscreen through EGL or OSMesa (Mesa on the CPU), picked automatically: `MUJOCO_GL=egl|osmesa`
when set, else EGL when libEGL is installed, else OSMesa. The appearance (lights, object textures, floor and sky
photographs) is drawn from a seed by `aynamics.appearance` (`Appearance` and `sample_appearance` are re-exported
here); `render_model` puts it on the scene's MuJoCo model.

    rollout = simulate(scene)
    frames = render(scene, rollout, seed=3)        # 30 frames (states 0..29) at 480×320
    with Renderer() as r:                          # reuse one GL context across scenes
        frames = r.render(scene, rollout, rgb=False)

Segmentation holds the object index in `scene.objects` order, -1 for floor and sky; depth is metres along the
optical axis, np.inf where no surface is hit.
"""

from __future__ import annotations

import ctypes.util
import functools
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from aynamics import camera as camlib
from aynamics import simulate as sim
from aynamics.appearance import Appearance, sample_appearance  # re-exported: used as render.sample_appearance
from aynamics.scene import Scene, is_whole, require_scene
from aynamics.video_io import read_image

FLOOR_TEXTURE = 512  # pixels per side of the floor photograph texture
SKY_TEXTURE = 256
OBJECT_TEXTURE = 64
SHADOW_EXTENT = 8.0  # m: half-size of the region that shadows cover (also scales the clip planes)
SHADOW_SIZE = 512  # shadow map texels per side: each shadow-casting light renders one per frame (1024: 7-15 % slower)


class RenderError(RuntimeError):
    """OpenGL rendering is unavailable or failed; the message says which backend and what to install."""


# --------------------------------------------------------------------------------------------
# OpenGL backend
# --------------------------------------------------------------------------------------------
def gl_backend() -> str:
    """The headless OpenGL backend to use: 'egl' or 'osmesa'.

    Raises:
        RenderError: when neither library is installed, or `MUJOCO_GL` names something else.
    """
    chosen = os.environ.get("MUJOCO_GL", "").strip().lower()
    if chosen in ("egl", "osmesa"):
        return chosen
    if chosen not in ("", "1", "true", "on", "enable", "enabled"):
        raise RenderError(f"MUJOCO_GL = {chosen!r}: headless rendering needs 'egl' or 'osmesa'")
    pyopengl = os.environ.get("PYOPENGL_PLATFORM", "").strip().lower()
    if pyopengl in ("egl", "osmesa"):
        return pyopengl
    if ctypes.util.find_library("EGL"):
        return "egl"
    if ctypes.util.find_library("OSMesa"):
        return "osmesa"
    raise RenderError(
        "no headless OpenGL found: install Mesa's EGL (apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri "
        "libopengl0) or OSMesa (libosmesa6), or run `make mesa`; then MUJOCO_GL=egl or MUJOCO_GL=osmesa"
    )


def _gl_context(width: int, height: int):
    backend = gl_backend()
    try:
        if backend == "egl":
            from mujoco.egl import GLContext
        else:
            from mujoco.osmesa import GLContext
        ctx = GLContext(width, height)
        ctx.make_current()
    except Exception as e:  # ImportError, RuntimeError, OpenGL errors: all mean "this backend does not work here"
        other = "osmesa" if backend == "egl" else "egl"
        raise RenderError(
            f"OpenGL backend {backend!r} failed ({type(e).__name__}: {e}); install its Mesa packages or start "
            f"Python with MUJOCO_GL={other} PYOPENGL_PLATFORM={other}"
        ) from None
    return ctx


def gl_available() -> tuple[bool, str]:
    """Whether a headless GL context can be made here, and why not (for test skips and messages)."""
    try:
        ctx = _gl_context(16, 16)
    except RenderError as e:
        return False, str(e)
    ctx.free()
    return True, ""


# --------------------------------------------------------------------------------------------
# The appearance on the MuJoCo model (appearance.py samples it)
# --------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=32)
def _load_texture(path: Path, size: int) -> bytes:
    """RGB bytes of an image (as `video_io.read_image` reads a photograph: EXIF rotation, 16-bit and CMYK
    images), centre-cropped to a square and resized to size × size."""
    from PIL import Image

    try:
        img = Image.fromarray(read_image(path))
    except ValueError as e:
        raise ValueError(f"texture image {str(path)!r} cannot be read: {e}") from None
    w, h = img.size
    s = min(w, h)
    img = img.crop(((w - s) // 2, (h - s) // 2, (w - s) // 2 + s, (h - s) // 2 + s)).resize((size, size))
    return np.asarray(img, np.uint8).tobytes()


def render_model(scene: Scene, appearance: Appearance, width: int, height: int) -> tuple[mujoco.MjModel, sim.Template]:
    """The scene's MuJoCo model with the appearance's lights, materials and textures (same ids as simulation)."""
    spec = sim.build_spec(scene.structure)
    spec.visual.global_.offwidth = max(width, 64)
    spec.visual.global_.offheight = max(height, 64)
    spec.visual.quality.shadowsize = SHADOW_SIZE
    spec.visual.quality.offsamples = 0  # no MSAA: crisp ids at object borders, 3× faster RGB
    spec.visual.headlight.active = 1  # ambient only (diffuse and specular 0): MuJoCo ignores an inactive headlight
    spec.visual.headlight.ambient = [appearance.ambient] * 3
    spec.visual.headlight.diffuse = [0.0] * 3
    spec.visual.headlight.specular = [0.0] * 3
    spec.visual.map.znear = 0.002  # × extent: 1.6 cm
    spec.visual.map.zfar = 20.0  # × extent: 160 m

    def image_texture(name: str, kind: mujoco.mjtTexture, path: Path, size: int) -> None:
        tex = spec.add_texture(name=name, type=kind)
        tex.width, tex.height, tex.nchannel = size, size, 3
        tex.data = _load_texture(path, size)

    def flat_texture(name: str, kind: mujoco.mjtTexture, rgb: tuple[float, float, float]) -> None:
        spec.add_texture(
            name=name,
            type=kind,
            builtin=mujoco.mjtBuiltin.mjBUILTIN_FLAT,
            width=8,
            height=8,
            rgb1=list(rgb),
            rgb2=list(rgb),
        )

    rgb_role = int(mujoco.mjtTextureRole.mjTEXROLE_RGB)
    if appearance.floor_image is None:
        flat_texture("floor_tex", mujoco.mjtTexture.mjTEXTURE_2D, appearance.floor_rgb)
    else:
        image_texture("floor_tex", mujoco.mjtTexture.mjTEXTURE_2D, appearance.floor_image, FLOOR_TEXTURE)
    if appearance.sky_image is None:
        flat_texture("sky_tex", mujoco.mjtTexture.mjTEXTURE_SKYBOX, appearance.sky_rgb)
    else:
        image_texture("sky_tex", mujoco.mjtTexture.mjTEXTURE_SKYBOX, appearance.sky_image, SKY_TEXTURE)
    floor_mat = spec.add_material(name="floor_mat", texrepeat=[appearance.floor_repeat] * 2, texuniform=True)
    floor_mat.textures[rgb_role] = "floor_tex"
    builtin = {
        "checker": mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        "gradient": mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
        "plain": mujoco.mjtBuiltin.mjBUILTIN_FLAT,
    }
    for i in range(len(scene.objects)):
        look = appearance.objects[i % len(appearance.objects)]
        spec.add_texture(
            name=f"obj{i}_tex",
            type=mujoco.mjtTexture.mjTEXTURE_CUBE,
            builtin=builtin[look.kind],
            width=OBJECT_TEXTURE,
            height=OBJECT_TEXTURE,
            rgb1=list(look.rgb1),
            rgb2=list(look.rgb2 if look.kind != "plain" else look.rgb1),
        )
        mat = spec.add_material(name=f"obj{i}_mat", specular=0.3, shininess=0.3)
        mat.textures[rgb_role] = f"obj{i}_tex"
        spec.geom(f"obj{i}_geom").material = f"obj{i}_mat"
    spec.geom("floor").material = "floor_mat"
    for k, light in enumerate(appearance.lights):
        spec.worldbody.add_light(
            name=f"light{k}",
            type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
            dir=list(light.direction),
            pos=[-light.direction[0] * 10, -light.direction[1] * 10, -light.direction[2] * 10],
            diffuse=[light.diffuse] * 3,
            specular=[0.2] * 3,
            castshadow=light.castshadow,
        )
    try:
        model = spec.compile()
    except ValueError as e:
        raise RenderError(f"cannot build the render model: {e}") from None
    tpl = sim.template(scene.structure)
    sim.write_params(model, sim.scene_params(scene, tpl))
    mujoco.mj_setConst(model, mujoco.MjData(model))
    # shadow maps of directional lights cover stat.extent around stat.center: centre them where the camera looks
    cam = scene.camera
    down = np.radians(90.0 - cam.orientation)  # optical axis below the horizon
    reach = cam.position[2] / np.tan(down) if down > 0.05 else SHADOW_EXTENT
    model.stat.center[:] = [cam.position[0], cam.position[1] + min(reach, SHADOW_EXTENT), 0.0]
    model.stat.extent = SHADOW_EXTENT
    return model, tpl


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------
@dataclass
class Frames:
    """A rendered video. Frame k shows rollout state `states[k]` (default: states 0..T-1 of T + 1).

    Attributes:
        rgb: (T, H, W, 3) uint8, or None when not asked for.
        segmentation: (T, H, W) int16: object index in `scene.objects` order, -1 for floor and sky.
        depth: (T, H, W) float32 metres along the optical axis; np.inf where nothing is hit.
        camera: OpenCV intrinsics/extrinsics at this resolution.
        states: (T,) rollout state index of each frame.
    """

    rgb: np.ndarray | None
    segmentation: np.ndarray | None
    depth: np.ndarray | None
    camera: camlib.CameraMatrices | None = None
    states: np.ndarray | None = None


def video_states(n_states: int) -> np.ndarray:
    """Rollout states shown as video frames: all but the last (31 states at 30 FPS -> frames 0..29)."""
    return np.arange(max(1, n_states - 1))


def rollout_qpos(rollout, tpl: sim.Template) -> np.ndarray:
    """(T, nq) qpos of every rollout state."""
    qpos = np.zeros((len(rollout.t), tpl.model.nq))
    for i, a in enumerate(tpl.qpos_adr):
        qpos[:, a : a + 3] = rollout.position[:, i]
        qpos[:, a + 3 : a + 7] = rollout.orientation[:, i]
    return qpos


class Renderer:
    """An offscreen OpenGL context reused across scenes. Close it (or use `with`) to free the context.

    Args:
        width, height: image size in pixels (default 480×320).
    """

    def __init__(self, width: int = camlib.WIDTH, height: int = camlib.HEIGHT):
        whole = is_whole(width) and is_whole(height)
        if not (whole and 1 <= width <= 4096 and 1 <= height <= 4096):  # 20.5 failed in MjrRect, True in MuJoCo
            raise ValueError(f"image size {width!r}×{height!r}: width and height must be whole numbers in [1, 4096]")
        width, height = int(width), int(height)
        self.width, self.height = width, height
        self._ctx = _gl_context(max(width, 64), max(height, 64))
        self._rect = mujoco.MjrRect(0, 0, width, height)

    def close(self) -> None:
        if self._ctx is not None:
            self._ctx.free()
            self._ctx = None

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def render(
        self,
        scene: Scene,
        rollout,
        *,
        seed: int = 0,
        textures_dir: str | Path | None = None,
        backdrop: str = "photos",
        appearance: Appearance | None = None,
        rgb: bool = True,
        segmentation: bool = True,
        depth: bool = True,
        states: np.ndarray | None = None,
    ) -> Frames:
        """Render the rollout's states (default `video_states`) from the scene's camera."""
        if self._ctx is None:
            raise RenderError("Renderer.render called after close()")
        require_scene(scene, "render: scene")
        positions = getattr(rollout, "position", None)
        shaped = isinstance(positions, np.ndarray) and positions.ndim == 3
        if not shaped or positions.shape[1] != len(scene.objects):
            # another scene's rollout: an IndexError with fewer objects, its first objects' poses with more
            got = f"of {positions.shape[1]} object(s)" if shaped else f"a {type(rollout).__name__}"
            raise ValueError(
                f"render: rollout ({got}) is not a rollout of this scene (of {len(scene.objects)} object(s)): "
                "pass simulate(scene)"
            )
        if not is_whole(seed) or seed < 0:
            raise ValueError(f"render: seed = {seed!r}: must be a whole number >= 0")
        if appearance is None:
            appearance = sample_appearance(seed, textures_dir, n_objects=max(1, len(scene.objects)), backdrop=backdrop)
        states = video_states(len(rollout.t)) if states is None else np.asarray(states, int)
        if len(states) and (states.min() < 0 or states.max() >= len(rollout.t)):
            raise ValueError(f"states {states.tolist()}: must index the rollout's {len(rollout.t)} states")
        model, tpl = render_model(scene, appearance, self.width, self.height)
        data = mujoco.MjData(model)
        qpos = rollout_qpos(rollout, tpl)
        geom_to_obj = np.full(model.ngeom, -2, np.int16)  # -2: floor (drawn, not an object)
        geom_to_obj[tpl.geom_ids] = np.arange(len(tpl.geom_ids))
        n, h, w = len(states), self.height, self.width
        out_rgb = np.empty((n, h, w, 3), np.uint8) if rgb else None
        out_seg = np.empty((n, h, w), np.int16) if segmentation else None
        out_depth = np.empty((n, h, w), np.float32) if depth else None

        self._ctx.make_current()
        ctx = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100.value)
        try:
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, ctx)
            ctx.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
            scn = mujoco.MjvScene(model, maxgeom=100 + 4 * model.ngeom)
            opt = mujoco.MjvOption()
            cam = mujoco.MjvCamera()
            cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
            cam.fixedcamid = tpl.camera_id
            extent = model.stat.extent
            near, far = np.float32(model.vis.map.znear * extent), np.float32(model.vis.map.zfar * extent)
            # reversed-Z buffer value b -> metres along the optical axis: d / (b + c)
            c = np.float32(-0.5) * (-(far + near) / (far - near)) - np.float32(0.5)
            d = np.float32(-0.5) * (-(np.float32(2) * far * near) / (far - near))
            rgb_buf = np.empty((h, w, 3), np.uint8)
            depth_buf = np.empty((h, w), np.float32)
            z = np.empty((h, w), np.float64)
            geom_type = int(mujoco.mjtObj.mjOBJ_GEOM)  # int once: comparing enum members per geom is slow
            flag_segment, flag_idcolor = mujoco.mjtRndFlag.mjRND_SEGMENT, mujoco.mjtRndFlag.mjRND_IDCOLOR
            for f, s in enumerate(states):
                data.qpos[:] = qpos[s]
                mujoco.mj_kinematics(model, data)
                mujoco.mj_camlight(model, data)  # camera and light poses: mj_kinematics leaves them at zero
                mujoco.mjv_updateScene(model, data, opt, None, cam, mujoco.mjtCatBit.mjCAT_ALL.value, scn)
                if rgb:
                    mujoco.mjr_render(self._rect, scn, ctx)
                    mujoco.mjr_readPixels(rgb_buf, None, self._rect, ctx)
                    out_rgb[f] = rgb_buf[::-1]  # OpenGL rows run bottom-up
                if not (segmentation or depth):
                    continue
                scn.flags[flag_segment] = scn.flags[flag_idcolor] = 1
                mujoco.mjr_render(self._rect, scn, ctx)
                mujoco.mjr_readPixels(rgb_buf, depth_buf, self._rect, ctx)
                scn.flags[flag_segment] = scn.flags[flag_idcolor] = 0
                # pixel colour = segid + 1 (0: nothing drawn) -> object index; -2: drawn but not an object (floor)
                lut = np.full(max(256, scn.ngeom + 2), -2, np.int16)
                lut[0] = -1
                for g in scn.geoms[: scn.ngeom]:
                    if g.segid >= 0 and g.objtype == geom_type:
                        lut[g.segid + 1] = geom_to_obj[g.objid]
                if scn.ngeom < 255:  # every colour fits the red byte: one uint8 lookup per pixel
                    ids = lut[rgb_buf[::-1, :, 0]]
                else:
                    code = rgb_buf[::-1].astype(np.int32)
                    ids = lut[np.minimum(code[..., 0] + (code[..., 1] << 8) + (code[..., 2] << 16), len(lut) - 1)]
                if segmentation:
                    np.maximum(ids, -1, out=out_seg[f])
                if depth:
                    np.add(depth_buf[::-1], c, out=z, dtype=np.float64)
                    np.divide(d, z, out=z)
                    z[ids == -1] = np.inf
                    out_depth[f] = z
        finally:
            ctx.free()
        return Frames(out_rgb, out_seg, out_depth, camlib.matrices(scene.camera, w, h), states)


def render(
    scene: Scene,
    rollout,
    *,
    width: int = camlib.WIDTH,
    height: int = camlib.HEIGHT,
    seed: int = 0,
    textures_dir: str | Path | None = None,
    backdrop: str = "photos",
    rgb: bool = True,
    segmentation: bool = True,
    depth: bool = True,
) -> Frames:
    """Render a rollout once (a fresh GL context; use `Renderer` to render many scenes)."""
    with Renderer(width, height) as r:
        return r.render(
            scene,
            rollout,
            seed=seed,
            textures_dir=textures_dir,
            backdrop=backdrop,
            rgb=rgb,
            segmentation=segmentation,
            depth=depth,
        )


def _ensure_backend_env() -> None:
    """Set MUJOCO_GL/PYOPENGL_PLATFORM for subprocesses and late imports (PyOpenGL reads them once)."""
    if "OpenGL" in sys.modules:
        return
    try:
        backend = gl_backend()
    except RenderError:
        return
    os.environ.setdefault("PYOPENGL_PLATFORM", backend)


_ensure_backend_env()
