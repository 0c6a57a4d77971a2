"""A batch of views per step over devices, and photos on a common canvas.

The multi-device runs happen in subprocesses (tests/sharded_run.py): a
process's device count is fixed when JAX starts.
"""

import dataclasses
import os
import socket
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

from clipgs_jax import camera
from clipgs_jax import config
from clipgs_jax import config_file
from clipgs_jax import evaluation
from clipgs_jax import guidance
from clipgs_jax import guidance_config
from clipgs_jax import losses
from clipgs_jax import metrics
from clipgs_jax import sharding
from clipgs_jax import step
from clipgs_jax import train
from clipgs_jax import view
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.maps import residual
from clipgs_jax.maps import sources
from clipgs_jax.render import project
from clipgs_jax.render import rasterize
import sharded_run  # tests/, on sys.path under pytest
import synthetic
import test_train

TESTS = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(TESTS)


def _run(args, env=None, wait=True):
  env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + TESTS, **(env or {}))
  cmd = [sys.executable, os.path.join(TESTS, "sharded_run.py")] + args
  if not wait:
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
  proc = subprocess.run(cmd, env=env, capture_output=True, text=True,
                        check=False)
  assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
  return proc


def _state(folder):
  with np.load(os.path.join(folder, train.CHECKPOINT_NAME)) as data:
    return {k: data[k] for k in data.files if not k.startswith("meta/")}


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(("localhost", 0))
    return s.getsockname()[1]


class ShardedRunsTest(absltest.TestCase):

  def test_sharded_unsharded_resumed_and_two_processes(self):
    out = self.create_tempdir().full_path
    flags = os.environ.get("XLA_FLAGS", "")
    _run(["devices", out], {"XLA_FLAGS": (
        flags + " --xla_force_host_platform_device_count=2").strip()})
    port = str(_free_port())
    procs = [_run(["process", out, str(i), port], {"XLA_FLAGS": flags},
                  wait=False) for i in range(2)]
    for proc in procs:
      log, _ = proc.communicate(timeout=600)
      self.assertEqual(proc.returncode, 0, log[-3000:])
    sharded = _state(os.path.join(out, "sharded"))
    # A densify grew the capacity from 64 to 128; 30 steps of B = 2.
    self.assertEqual(sharded["state/alive"].shape, (128,))
    self.assertEqual(int(sharded["state/step"]), sharded_run.STEPS)
    for name in ("resumed", "two_process"):
      other = _state(os.path.join(out, name))
      for k, v in sharded.items():
        np.testing.assert_array_equal(v, other[k], err_msg=f"{name}: {k}")
    # One device computes the same two views in another compiled program:
    # rounding differs, nothing else. Parameters agree to 1e-6, Adam's
    # moments and the statistics to 1e-6 of their largest value.
    unsharded = _state(os.path.join(out, "unsharded"))
    for k, v in sharded.items():
      if v.dtype.kind != "f":
        np.testing.assert_array_equal(unsharded[k], v, err_msg=k)
        continue
      # The checkpoint's record of pruned rows is empty when no prune
      # removed any.
      scale = (1.0 if k.startswith("state/params/") or not v.size
               else np.max(np.abs(v)))
      np.testing.assert_allclose(unsharded[k], v, rtol=0, atol=1e-6 * scale,
                                 err_msg=k)
    # The residual map's memory: each device's view written to its row on
    # both, inside the photo only.
    with np.load(os.path.join(out, "memory.npz")) as data:
      memory, views = data["memory"], sorted(data["views"].tolist())
    scene = sharded_run.canvas_scene()
    self.assertLen(views, sharded_run.BATCH)
    for v, (w, h) in enumerate(scene.train.sizes):
      inside = np.zeros(memory.shape[1:], bool)
      inside[:h, :w] = v in views
      np.testing.assert_array_equal(memory[v], inside, err_msg=f"view {v}")


class LanesTest(absltest.TestCase):

  def test_lanes_deal_the_views_and_visit_each_once_per_epoch(self):
    views = test_train.synthetic_scene(num=4, size=16, num_train=7).train
    rows = sharding._rows(views, 7, 2, [0, 1])
    np.testing.assert_array_equal(rows, [[0, 2, 4, 6], [1, 3, 5, -1]])
    key = jax.random.key(3)
    for count in (3, 4):
      order = [int(view.lane_view(key, jnp.int32(s), count, 4))
               for s in range(3 * count)]
      for epoch in range(3):
        self.assertEqual(sorted(order[epoch * count:(epoch + 1) * count]),
                         list(range(count)))
    # A full lane is the one-view order, and lane 0's key is the run's.
    self.assertEqual(
        [int(view.lane_view(key, jnp.int32(s), 5, 5)) for s in range(10)],
        [int(view.view_index(key, jnp.int32(s), 5)) for s in range(10)])
    np.testing.assert_array_equal(
        jax.random.key_data(view.lane_key(key, jnp.int32(0))),
        jax.random.key_data(key))

  def test_batch_must_divide_over_the_devices(self):
    device = jax.devices()[0]
    with self.assertRaisesRegex(ValueError, "batch_size=3 does not divide "
                                "over the 2 devices"):
      sharding.make_mesh(3, [device, device])
    with self.assertRaisesRegex(Exception, "batch_size=0"):
      config_file.check({"train": {"batch_size": 0}})


class DeviceLanesTest(absltest.TestCase):

  def test_vmapped_lanes_equal_scanned_lanes(self):
    """A device's lanes rendered together (vmap, as on accelerators) give
    the scan's step: same parameters, densification statistics, evidence
    and residual histogram, to float32 rounding, on photos of three sizes
    with loss masking (ORACLE-PIXEL evidence; the residual map)."""
    scene = sharded_run.canvas_scene()
    mesh = sharding.make_mesh(4, jax.devices()[:1])
    self.assertFalse(step.lanes_vmapped(mesh))      # a CPU scans
    lanes, rows = sharding.lanes_of(scene, 4, mesh)
    h, w = lanes.images.shape[2:4]
    base = sharded_run.config()
    for scorer_name in ("oracle", "residual"):
      cfg = train.resolve(dataclasses.replace(
          base, train=dataclasses.replace(base.train, batch_size=4),
          semantic=dataclasses.replace(base.semantic, scorer=scorer_name)),
          scene)
      scorer = sharding.scorer_lanes(
          guidance.make_scorer(cfg, scene), rows, h, w, mesh)
      ends = []
      for vmap in (False, True):
        state = sharding.replicate(
            sharded_run.anisotropic_state(cfg, scene), mesh)
        step_fn = step.make_train_step(cfg, mesh, vmap_lanes=vmap)
        for _ in range(3):
          state, metrics = step_fn(state, lanes, scorer)
        ends.append((state, metrics))
      (scanned, m_scan), (vmapped, m_vmap) = ends
      if scorer_name == "oracle":
        self.assertGreater(float(jnp.sum(scanned.semantic.acc)), 0)
      else:
        self.assertGreater(float(jnp.sum(scanned.maps.histogram)), 0)
      paths = jax.tree_util.tree_flatten_with_path((scanned, m_scan))[0]
      for (path, a), b in zip(paths, jax.tree.leaves((vmapped, m_vmap))):
        name = f"{scorer_name} {jax.tree_util.keystr(path)}"
        if jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key):
          a, b = jax.random.key_data(a), jax.random.key_data(b)
        a, b = np.asarray(a), np.asarray(b)
        atol = 1e-6
        if "histogram" in name:
          # A residual on a bin edge may round into the next bin (1e-4
          # wide): the cumulative counts agree to a pixel or two.
          a, b, atol = np.cumsum(a), np.cumsum(b), 2.0
        elif "threshold" in name:
          atol = 2e-4                       # a bin's width, as above
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=atol, err_msg=name)


def _cut_second_view(split: str):
  """(two 24x24 views of a synthetic scene's `split`, the second an 18-wide
  photo on the canvas; that photo as a view by itself)."""
  scene = test_train.synthetic_scene(num=24, size=24, num_train=2,
                                     num_test=2)
  views = getattr(scene, split)
  images = np.array(views.images)
  images[1, :, 18:] = 0.0
  cut = scene_lib.Views(cameras=views.cameras, images=images,
                        names=views.names, masks=None,
                        sizes=np.array([[24, 24], [18, 24]], np.int32))
  alone = test_train.Views(
      cameras=jax.tree.map(lambda x: x[1:], views.cameras).replace(
          width=18),
      images=views.images[1:, :, :18], names=views.names[1:])
  return cut, alone


class CanvasTest(absltest.TestCase):
  """A photo padded onto a larger canvas changes no loss, map or metric."""

  def setUp(self):
    super().setUp()
    scene = test_train.synthetic_scene(num=24, size=24, num_train=2,
                                       num_test=1)
    self.photo = np.asarray(scene.train.images[0, :, :18])     # 24 x 18
    cam = camera.camera_at(scene.train.cameras, 0)
    self.cam = cam.replace(width=18)
    self.canvas_cam = cam.replace(width=32, height=30)
    self.params = synthetic.random_params(40, seed=2, degree=0, spread=0.6)
    self.alive = jnp.ones((40,), bool)

  def _padded(self, x):
    out = np.zeros((30, 32) + x.shape[2:], x.dtype)
    out[:24, :18] = x
    return out

  def test_padded_view_same_render_loss_and_psnr(self):
    bg = jnp.zeros(3)
    cfg = config.RenderConfig()
    photo_out = rasterize.render(self.params, self.alive, self.cam, bg, cfg)
    proj = project.project(self.params, self.alive, self.canvas_cam,
                                near=cfg.near, sh_degree=0)
    size = jnp.array([18, 24], jnp.int32)
    canvas_out = rasterize.rasterize(proj, self.canvas_cam, bg, cfg,
                                     valid_size=size)
    np.testing.assert_allclose(canvas_out.image[:24, :18], photo_out.image,
                               atol=1e-6)
    np.testing.assert_array_equal(canvas_out.image[24:], 0.0)
    np.testing.assert_allclose(canvas_out.contribution,
                               photo_out.contribution, rtol=1e-5, atol=1e-6)
    valid = sharding.valid_mask(size, 30, 32)
    target = jnp.asarray(self._padded(self.photo))
    pred = canvas_out.image
    for weight in (None, jnp.asarray(np.linspace(0, 1, 24 * 18).reshape(
        24, 18), jnp.float32)):
      padded_weight = None if weight is None else jnp.asarray(
          self._padded(np.asarray(weight)))
      loss, terms = losses.photometric(photo_out.image, self.photo, 0.2,
                                       weight)
      loss_c, terms_c = losses.photometric(pred, target, 0.2, padded_weight,
                                           valid=valid)
      self.assertAlmostEqual(float(loss_c), float(loss), places=6)
      self.assertAlmostEqual(float(terms_c["ssim"]), float(terms["ssim"]),
                             places=6)
    self.assertAlmostEqual(
        float(metrics.psnr(pred, target, valid)),
        float(metrics.psnr(photo_out.image, self.photo)), places=4)

  def test_padded_test_view_same_metrics(self):
    cfg = test_train.TEST_CFG
    cut, alone = _cut_second_view("test")
    params = synthetic.random_params(40, seed=2, degree=1, spread=0.6)
    alive = jnp.ones((40,), bool)
    on_canvas = evaluation.evaluate(params, alive, cut, cfg,
                                    keep_images=True)
    by_itself = evaluation.evaluate(params, alive, alone, cfg)
    for k in ("psnr", "ssim"):
      self.assertAlmostEqual(on_canvas[k][1], by_itself[k][0], places=4)
    self.assertEqual(on_canvas["images"][1].shape, (24, 18, 3))

  def test_padded_view_map_sees_the_photo_only(self):
    """The map mask quality and the loss-map report read for a photo on a
    larger canvas is the step's: nothing outside the photo, and the 3x3
    rule and share floor over its pixels (the photo alone gives it)."""
    cut, alone = _cut_second_view("train")
    cfg = test_train.TEST_CFG
    cfg = dataclasses.replace(cfg, residual=dataclasses.replace(
        cfg.residual, min_alpha=0.0, min_share=0.05))
    params = synthetic.random_params(40, seed=2, degree=1, spread=0.6)
    alive = jnp.ones((40,), bool)
    stats = residual.ResidualState.initial().replace(
        threshold=jnp.float32(0.1))
    args = (params, alive, stats, sources.ResidualSource())
    on_canvas = evaluation.view_map(*args, cut, 1, cfg, jnp.int32(1))
    by_itself = evaluation.view_map(*args, alone, 0, cfg, jnp.int32(1))
    self.assertGreater(float(np.sum(by_itself)), 0.05 * 18 * 24)
    np.testing.assert_array_equal(on_canvas[:, 18:], 0.0)
    np.testing.assert_array_equal(on_canvas[:, :18], by_itself)
    stages = evaluation.view_map(*args, cut, 1, cfg, jnp.int32(1),
                                 stages=True)
    np.testing.assert_array_equal(stages["share"], on_canvas)

  def test_padded_pixels_are_no_residual(self):
    res = jnp.asarray(np.random.default_rng(0).random((30, 32)), jnp.float32)
    valid = sharding.valid_mask(jnp.array([18, 24]), 30, 32)
    self.assertEqual(float(jnp.sum(residual.counts(res, valid))), 24 * 18)
    for rule in guidance_config.RESIDUAL_RULES:
      inlier = residual.inliers(res, 0.5, rule, valid)
      alone = residual.inliers(res[:24, :18], 0.5, rule)
      np.testing.assert_array_equal(inlier[:24, :18], alone)


if __name__ == "__main__":
  absltest.main()
