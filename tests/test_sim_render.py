"""The JAX ray caster against two independent references, on the real scene in several poses, both cameras:

* MuJoCo's OpenGL renderer (`mujoco.Renderer`, EGL surfaceless or OSMesa, software rasterised on CPU), run in a
  subprocess because MUJOCO_GL must be set before mujoco is imported: segmentation (geom ids) must agree on >= 98 %
  of pixels (the rest are silhouettes of GL's tessellated capsules/cylinders/spheres) and depth, where ids agree,
  within 5 mm on 99 % of pixels. Skipped, with the reason, when no GL context can be created.
* MuJoCo's own C ray caster `mj_ray`, per pixel (always runs): ids >= 99 % and depth within 1 mm on 99.5 %.
"""

import json
import os
import subprocess
import sys

import jax
import mujoco
import numpy as np
import pytest

from pi0_jax.sim import render, scene, tasks

RES = 64
POSES = [("object/red_block_in_bowl", 0, 0.0), ("spatial/left_black_block_on_plate", 3, 0.25),
         ("goal/stack_green_on_blue", 7, -0.3)]


def _pose(model, data, idx, task, init, arm_offset):
    lay = tasks.init_states(task)
    rng = np.random.default_rng(init)
    data.qpos[:7] = lay.arm_q[init] + arm_offset * rng.uniform(-1, 1, 7)
    data.qpos[7:9] = rng.uniform(0, scene.FINGER_OPEN, 2)
    for b, adr in enumerate(idx.block_qpos):
        x, y, z, yaw = lay.block[init, b]
        data.qpos[adr:adr + 7] = [x, y, z, np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
    data.mocap_pos[:] = lay.fixture[init]
    mujoco.mj_forward(model, data)


_GL_SCRIPT = r"""
import json, sys, numpy as np, mujoco
sys.path.insert(0, sys.argv[1])
from tests.test_sim_render import POSES, RES, _pose
from pi0_jax.sim import scene
m, idx = scene.build(); d = mujoco.MjData(m)
r = mujoco.Renderer(m, RES, RES)
out = {}
for k, (task, init, off) in enumerate(POSES):
    _pose(m, d, idx, task, init, off)
    for cam in scene.CAMERAS:
        r.enable_depth_rendering(); r.update_scene(d, cam); out[f"depth_{k}_{cam}"] = r.render().copy()
        r.disable_depth_rendering(); r.enable_segmentation_rendering(); r.update_scene(d, cam)
        seg = r.render().copy(); r.disable_segmentation_rendering()
        out[f"seg_{k}_{cam}"] = np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)
np.savez(sys.argv[2], **out)
r.close()
"""


@pytest.fixture(scope="module")
def posed():
    model, idx = scene.build()
    sc = render.Scene.from_model(model)
    cfg = render.RenderConfig(RES, RES)
    fn = jax.jit(lambda gx, gm, cx, cm: [render.render_camera(sc, cfg, c, gx, gm, cx, cm) for c in idx.camera])
    out = []
    for task, init, off in POSES:
        data = mujoco.MjData(model)
        _pose(model, data, idx, task, init, off)
        imgs = fn(data.geom_xpos, data.geom_xmat.reshape(-1, 3, 3), data.cam_xpos, data.cam_xmat.reshape(-1, 3, 3))
        out.append((data, [tuple(np.asarray(a) for a in im) for im in imgs]))
    return model, idx, out


def _gl_reference(tmp_path):
    errors = []
    for backend in ("egl", "osmesa"):
        env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend, "EGL_PLATFORM": "surfaceless"}
        path = tmp_path / f"gl_{backend}.npz"
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        res = subprocess.run([sys.executable, "-c", _GL_SCRIPT, root, str(path)], env=env, capture_output=True,
                             text=True, timeout=120, cwd=root)
        if path.exists():
            return backend, dict(np.load(path))
        errors.append(f"{backend}: {res.stderr.strip().splitlines()[-1] if res.stderr.strip() else res.returncode}")
    pytest.skip("no OpenGL context on this machine (" + "; ".join(errors) + "); the mj_ray comparison still runs")


def test_matches_mujoco_opengl_renderer(posed, tmp_path):
    model, idx, out = posed
    backend, gl = _gl_reference(tmp_path)
    report = {}
    for k, (_, imgs) in enumerate(out):
        for c, cam in enumerate(scene.CAMERAS):
            _, depth, seg = imgs[c]
            gl_seg, gl_depth = gl[f"seg_{k}_{cam}"], gl[f"depth_{k}_{cam}"]
            same = seg == gl_seg
            hit = same & (seg >= 0)
            err = np.abs(depth[hit] - gl_depth[hit])
            report[f"{k}/{cam}"] = (float(same.mean()), float(np.percentile(err, 99)))
            assert same.mean() >= 0.98, (backend, k, cam, same.mean())
            assert np.percentile(err, 99) < 5e-3, (backend, k, cam, np.percentile(err, 99))
            assert len(np.unique(seg[seg >= 0])) >= 3          # the views see several objects
    print(f"GL backend {backend}: (id agreement, depth err p99) per pose/camera:", json.dumps(report))


def test_matches_mj_ray(posed):
    model, idx, out = posed
    groups = np.array([1, 1, 1, 0, 0, 0], np.uint8)     # what both renderers draw: groups 0-2
    gid = np.zeros(1, np.int32)
    for k, (data, imgs) in enumerate(out):
        for c in range(len(scene.CAMERAS)):
            _, depth, seg = imgs[c]
            rays = render.camera_rays(float(model.cam_fovy[c]), RES, RES)
            rot, org = data.cam_xmat[c].reshape(3, 3), data.cam_xpos[c]
            ref_seg = np.empty(RES * RES, np.int32)
            ref_depth = np.empty(RES * RES)
            for i, r in enumerate(rays.astype(np.float64)):
                dist = mujoco.mj_ray(model, data, org, rot @ r, groups, 1, -1, gid)
                ref_seg[i] = gid[0] if dist >= 0 else -1
                ref_depth[i] = dist * -r[2] if dist >= 0 else np.inf   # ray length -> optical-axis depth
            same = seg.reshape(-1) == ref_seg
            hit = same & (ref_seg >= 0)
            err = np.abs(depth.reshape(-1)[hit] - ref_depth[hit])
            assert same.mean() >= 0.99, (k, c, same.mean())
            assert np.percentile(err, 99.5) < 1e-3, (k, c, np.percentile(err, 99.5))


def test_rgb_is_lit_and_colored(posed):
    _, idx, out = posed
    rgb, _, seg = out[0][1][0]
    assert rgb.shape == (RES, RES, 3) and rgb.dtype == np.uint8
    red = seg == idx.block_geom[scene.BLOCKS.index("red_block")]
    assert red.any()
    r, g, b = rgb[red].astype(int).mean(0)
    assert r > g + 40 and r > b + 40              # the red block is red
