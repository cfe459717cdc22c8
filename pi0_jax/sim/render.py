"""A batched ray caster over the scene's primitive geoms, in JAX: RGB, depth and geom-id images from MJX data.

Every pixel casts one ray from the camera centre; each ray is intersected analytically with every drawn geom
(plane, sphere, capsule, box, cylinder: the only types the scene uses), the nearest hit wins, and the pixel is shaded
with Lambert's law under the scene's directional light plus a headlight, using the geom's rgba. No shadows,
reflections or textures. Geoms in group >= 3 (collision proxies) and fully transparent geoms are not drawn, as in
MuJoCo's default visualisation.

Conventions, matched to MuJoCo's OpenGL renderer so the two can be compared pixel by pixel: the camera looks along
its local -z with +y up; `fovy` is the vertical field of view; pixel (i, j) (row i from the top) samples the ray
through its centre; depth is the distance along the optical axis (not along the ray), `inf` where nothing is hit;
geom id -1 is background. Planes are one-sided (seen from +z) and drawn within their `size` half-extents.

Cost is rays x geoms per image. Geoms are grouped by type (static under jit) and each group is reduced with one
argmin over geoms, so the (rays x geoms) intermediates stay inside fused reductions; `ray_chunk` additionally bounds
memory by processing the image in chunks of rays with lax.map (needed at 224 x 224 with thousands of environments).

`write_video` writes a camera's frames as an MP4.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

_PLANE, _SPHERE, _CAPSULE, _CYLINDER, _BOX = 0, 2, 3, 5, 6   # mujoco.mjtGeom values
_TYPES = (_PLANE, _SPHERE, _CAPSULE, _CYLINDER, _BOX)
_INF = jnp.inf
_EPS = 1e-9

BACKGROUND = (0.55, 0.6, 0.68)
AMBIENT, DIFFUSE, HEADLIGHT = 0.25, 0.6, 0.3


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    height: int = 224
    width: int = 224
    ray_chunk: int = 0          # rays per lax.map chunk; 0 = the whole image at once


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """Static (numpy) description of what is drawn, taken from an MjModel once; hashed by identity."""
    geom_ids: dict            # type -> (G_t,) geom ids
    size: dict                # type -> (G_t, 3)
    rgba: np.ndarray          # (ngeom, 4) model rgba (materials resolved)
    types: np.ndarray         # (ngeom,) geom type, for the winner's normal
    sizes: np.ndarray         # (ngeom, 3)
    light_dir: np.ndarray     # (3,) direction the directional light travels, world frame
    cam_fovy: np.ndarray      # (ncam,) degrees

    @classmethod
    def from_model(cls, model) -> "Scene":
        drawn = (model.geom_group < 3) & (model.geom_rgba[:, 3] > 0)
        unknown = set(np.unique(model.geom_type[drawn]).tolist()) - set(_TYPES)
        if unknown:
            raise ValueError(f"the JAX renderer draws primitives only; geom types {sorted(unknown)} are not supported")
        ids = {t: np.flatnonzero(drawn & (model.geom_type == t)) for t in _TYPES}
        rgba = model.geom_rgba.copy()
        # MuJoCo uses the material's rgba when a geom has a material and leaves its own rgba at the default
        use_mat = (model.geom_matid >= 0) & np.all(model.geom_rgba == [0.5, 0.5, 0.5, 1], axis=1)
        rgba[use_mat] = model.mat_rgba[model.geom_matid[use_mat]]
        directional = np.flatnonzero(model.light_type == 1) if hasattr(model, "light_type") else []
        light = model.light_dir[directional[0]] if len(directional) else np.array([0.0, 0.0, -1.0])
        return cls(geom_ids={t: v for t, v in ids.items() if len(v)},
                   size={t: model.geom_size[v].astype(np.float32) for t, v in ids.items() if len(v)},
                   rgba=rgba.astype(np.float32), types=model.geom_type.astype(np.int32),
                   sizes=model.geom_size.astype(np.float32),
                   light_dir=(light / np.linalg.norm(light)).astype(np.float32),
                   cam_fovy=model.cam_fovy.astype(np.float32))


@functools.lru_cache(maxsize=None)
def camera_rays(fovy: float, height: int, width: int) -> np.ndarray:
    """Unit ray directions in the camera frame, (height * width, 3), row-major from the top-left pixel."""
    t = np.tan(np.deg2rad(fovy) / 2)
    x = ((np.arange(width) + 0.5) / width * 2 - 1) * t * width / height
    y = (1 - (np.arange(height) + 0.5) / height * 2) * t
    xx, yy = np.meshgrid(x, y)
    d = np.stack([xx, yy, -np.ones_like(xx)], -1).reshape(-1, 3)
    return (d / np.linalg.norm(d, axis=-1, keepdims=True)).astype(np.float32)


# --- ray / primitive distances in the geom's local frame. p: (R, G, 3) origin, v: (R, G, 3) direction, s: (G, 3) ---

def _quad(a, b, c):
    """Smallest non-negative root of a x^2 + 2 b x + c = 0, inf if none."""
    det = b * b - a * c
    sq = jnp.sqrt(jnp.maximum(det, 0.0))
    a = jnp.where(jnp.abs(a) < _EPS, _EPS, a)
    x0, x1 = (-b - sq) / a, (-b + sq) / a
    ok = det >= 0
    return jnp.where(ok & (x0 >= 0), x0, jnp.where(ok & (x1 >= 0), x1, _INF))


def _t_plane(p, v, s):
    t = -p[..., 2] / jnp.where(jnp.abs(v[..., 2]) < _EPS, -_EPS, v[..., 2])
    hx, hy = p[..., 0] + t * v[..., 0], p[..., 1] + t * v[..., 1]
    inside = ((s[:, 0] <= 0) | (jnp.abs(hx) <= s[:, 0])) & ((s[:, 1] <= 0) | (jnp.abs(hy) <= s[:, 1]))
    return jnp.where((v[..., 2] < -_EPS) & (t >= 0) & inside, t, _INF)


def _t_sphere(p, v, s, r=None, dz=0.0):
    r = s[:, 0] if r is None else r
    pz = p[..., 2] - dz
    return _quad(jnp.sum(v * v, -1), p[..., 0] * v[..., 0] + p[..., 1] * v[..., 1] + pz * v[..., 2],
                 p[..., 0] ** 2 + p[..., 1] ** 2 + pz**2 - r * r)


def _t_side(p, v, r, h):
    """Infinite cylinder of radius r about z, kept where |z| <= h."""
    t = _quad(v[..., 0] ** 2 + v[..., 1] ** 2, p[..., 0] * v[..., 0] + p[..., 1] * v[..., 1],
              p[..., 0] ** 2 + p[..., 1] ** 2 - r * r)
    return jnp.where(jnp.abs(p[..., 2] + t * v[..., 2]) <= h, t, _INF)


def _t_capsule(p, v, s):
    r, h = s[:, 0], s[:, 1]
    return jnp.minimum(_t_side(p, v, r, h), jnp.minimum(_t_sphere(p, v, s, r, h), _t_sphere(p, v, s, r, -h)))


def _t_cylinder(p, v, s):
    r, h = s[:, 0], s[:, 1]
    t = _t_side(p, v, r, h)
    for sign in (1.0, -1.0):   # flat caps
        tc = (sign * h - p[..., 2]) / jnp.where(jnp.abs(v[..., 2]) < _EPS, _EPS, v[..., 2])
        hx, hy = p[..., 0] + tc * v[..., 0], p[..., 1] + tc * v[..., 1]
        t = jnp.minimum(t, jnp.where((tc >= 0) & (hx * hx + hy * hy <= r * r), tc, _INF))
    return t


def _t_box(p, v, s):
    """Slab test; a ray starting inside returns its exit distance (as MuJoCo's ray caster does)."""
    near, far = jnp.full(p.shape[:-1], -_INF), jnp.full(p.shape[:-1], _INF)
    for k in range(3):
        vk = jnp.where(jnp.abs(v[..., k]) < _EPS, _EPS, v[..., k])
        t1, t2 = (-s[:, k] - p[..., k]) / vk, (s[:, k] - p[..., k]) / vk
        near, far = jnp.maximum(near, jnp.minimum(t1, t2)), jnp.minimum(far, jnp.maximum(t1, t2))
    return jnp.where((near <= far) & (far >= 0), jnp.where(near >= 0, near, far), _INF)


_T = {_PLANE: _t_plane, _SPHERE: _t_sphere, _CAPSULE: _t_capsule, _CYLINDER: _t_cylinder, _BOX: _t_box}


def _local_normal(gtype, q, s):
    """Outward normal at local hit point q (R, 3) of geoms of type gtype (R,) and size s (R, 3)."""
    def unit(x):
        return x / jnp.maximum(jnp.linalg.norm(x, axis=-1, keepdims=True), _EPS)
    ez = jnp.zeros_like(q).at[:, 2].set(1.0)
    sphere = unit(q)
    capsule = unit(q - ez * jnp.clip(q[:, 2:], -s[:, 1:2], s[:, 1:2]))
    side = unit(q * jnp.array([1.0, 1.0, 0.0]))
    on_cap = jnp.abs(q[:, 2]) / jnp.maximum(s[:, 1], _EPS) > jnp.linalg.norm(q[:, :2], axis=-1) / jnp.maximum(
        s[:, 0], _EPS)
    cylinder = jnp.where(on_cap[:, None], ez * jnp.sign(q[:, 2:]), side)
    rel = jnp.abs(q) / jnp.maximum(s, _EPS)
    box = jax.nn.one_hot(jnp.argmax(rel, -1), 3) * jnp.sign(q)
    return jnp.select([gtype[:, None] == _PLANE, gtype[:, None] == _SPHERE, gtype[:, None] == _CAPSULE,
                       gtype[:, None] == _CYLINDER], [ez, sphere, capsule, cylinder], box)


def _cast(scene: Scene, geom_xpos, geom_xmat, org, dirs):
    """Nearest hit of rays (R, 3) from org (3,) in world frame -> (t (R,), geom id (R,), world normal (R, 3))."""
    best_t, best_g = jnp.full(dirs.shape[:1], _INF), jnp.full(dirs.shape[:1], -1, jnp.int32)
    for gtype, ids in scene.geom_ids.items():
        xpos, xmat = geom_xpos[ids], geom_xmat[ids]                          # (G, 3), (G, 3, 3)
        p = jnp.einsum("gji,gj->gi", xmat, org[None] - xpos)[None]           # (1, G, 3) local origin
        v = jnp.einsum("gji,rj->rgi", xmat, dirs)                            # (R, G, 3) local direction
        t = _T[gtype](jnp.broadcast_to(p, v.shape), v, jnp.asarray(scene.size[gtype]))
        k = jnp.argmin(t, axis=1)
        tk = jnp.take_along_axis(t, k[:, None], 1)[:, 0]
        closer = tk < best_t
        best_t, best_g = jnp.where(closer, tk, best_t), jnp.where(closer, jnp.asarray(ids, jnp.int32)[k], best_g)
    # the winner's normal, recomputed for one geom per ray
    g = jnp.maximum(best_g, 0)
    types, sizes = jnp.asarray(scene.types), jnp.asarray(scene.sizes)
    xmat = geom_xmat[g]                                                      # (R, 3, 3)
    hit = org[None] + jnp.where(jnp.isfinite(best_t), best_t, 0.0)[:, None] * dirs
    q = jnp.einsum("rji,rj->ri", xmat, hit - geom_xpos[g])
    normal = jnp.einsum("rij,rj->ri", xmat, _local_normal(types[g], q, sizes[g]))
    return best_t, best_g, normal


def render_camera(scene: Scene, cfg: RenderConfig, cam_id: int, geom_xpos, geom_xmat, cam_xpos, cam_xmat):
    """One camera of one environment. Returns rgb (H, W, 3) uint8, depth (H, W) f32, geom id (H, W) int32.

    geom_xpos (ngeom, 3), geom_xmat (ngeom, 3, 3), cam_xpos (ncam, 3), cam_xmat (ncam, 3, 3): MJX Data fields."""
    h, w = cfg.height, cfg.width
    rays = jnp.asarray(camera_rays(float(scene.cam_fovy[cam_id]), h, w))
    rot, org = cam_xmat[cam_id], cam_xpos[cam_id]
    dirs = rays @ rot.T                                                       # world-frame unit directions
    light = jnp.asarray(scene.light_dir)
    rgba = jnp.asarray(scene.rgba)

    def shade(d):
        t, g, n = _cast(scene, geom_xpos, geom_xmat, org, d)
        n = jnp.where(jnp.sum(n * d, -1, keepdims=True) > 0, -n, n)          # light the side facing the camera
        lit = AMBIENT + DIFFUSE * jnp.maximum(-(n @ light), 0) + HEADLIGHT * jnp.maximum(-jnp.sum(n * d, -1), 0)
        col = jnp.where((g >= 0)[:, None], rgba[jnp.maximum(g, 0), :3] * lit[:, None], jnp.asarray(BACKGROUND))
        return jnp.clip(col, 0, 1), t, g

    chunk = cfg.ray_chunk if 0 < cfg.ray_chunk < h * w else h * w
    if (h * w) % chunk:
        raise ValueError(f"ray_chunk {chunk} must divide {h} * {w}")
    col, t, g = jax.lax.map(shade, dirs.reshape(-1, chunk, 3))
    depth = t.reshape(h, w) * (-rays[:, 2]).reshape(h, w)                     # ray length -> optical-axis depth
    rgb = jnp.round(col.reshape(h, w, 3) * 255).astype(jnp.uint8)
    return rgb, depth, g.reshape(h, w)


def render(scene: Scene, cfg: RenderConfig, data, cam_ids=(0, 1)):
    """Every camera in cam_ids for one environment's mjx.Data: {"rgb": (C, H, W, 3) uint8, "depth": (C, H, W),
    "segmentation": (C, H, W) geom ids}. vmap it over environments."""
    outs = [render_camera(scene, cfg, c, data.geom_xpos, data.geom_xmat, data.cam_xpos, data.cam_xmat)
            for c in cam_ids]
    return {"rgb": jnp.stack([o[0] for o in outs]), "depth": jnp.stack([o[1] for o in outs]),
            "segmentation": jnp.stack([o[2] for o in outs])}


def write_video(path: Path, frames: np.ndarray, fps: int = 20) -> None:
    """(T, H, W, 3) uint8 -> H.264 MP4 through imageio-ffmpeg's bundled ffmpeg binary."""
    import warnings

    import imageio.v2 as imageio

    with warnings.catch_warnings():   # ffmpeg runs as fork + exec, which JAX's fork warning does not distinguish
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        with imageio.get_writer(path, fps=fps, codec="libx264", quality=7, macro_block_size=16) as w:
            for f in frames:
                w.append_data(f)
