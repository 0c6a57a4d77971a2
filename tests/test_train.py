"""Tests for train: view order, backgrounds, and an end-to-end smoke run.

`synthetic_scene` and `TEST_CFG` are shared with test_checkpoint.py, so one
pytest process compiles the train step once for both files.
"""

import dataclasses
import os
import types

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

from clipgs_jax.lab import timing
from clipgs_jax import camera
from clipgs_jax import compiled
from clipgs_jax import config
from clipgs_jax import densify
from clipgs_jax import evaluation
from clipgs_jax import gaussians
from clipgs_jax import guidance
from clipgs_jax import guidance_config
from clipgs_jax import loop
from clipgs_jax import sh
from clipgs_jax import sharding
from clipgs_jax import step
from clipgs_jax import train
from clipgs_jax import view

TEST_CFG = config.Config(
    gaussians=config.GaussiansConfig(capacity=256, max_capacity=256,
                                     sh_degree=1),
    optim=config.OptimConfig(means_lr_init=1e-3, means_lr_final=1e-4,
                             sh_dc_lr=0.02, opacity_lr=0.05),
    densify=config.DensifyConfig(start=20, stop=100, every=20,
                                 opacity_reset_every=60, sh_degree_every=40),
    train=config.TrainConfig(steps=120, log_every=20, eval_every=40,
                             checkpoint_every=0))


@dataclasses.dataclass(frozen=True)
class Views:
  """The fields of data.scene.Views that training reads."""
  cameras: camera.Camera
  images: np.ndarray
  names: tuple[str, ...]
  masks: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class Scene:
  """The fields of data.scene.Scene that training reads."""
  train: Views
  test: Views
  points: np.ndarray
  point_colors: np.ndarray
  extent: float
  path: str = ""


def synthetic_scene(num=48, size=32, num_train=8, num_test=2, seed=0):
  """Ground-truth Gaussians rendered from an orbit of size x size cameras.

  The point cloud is the true centres with noise and the true colours
  with noise, like a sparse SfM reconstruction.
  """
  rng = np.random.default_rng(seed)
  params, _ = gaussians.empty(num, 0)
  means = rng.uniform(-0.6, 0.6, (num, 3)).astype(np.float32)
  colors = rng.uniform(0.1, 0.9, (num, 3)).astype(np.float32)
  params = params.replace(
      means=jnp.asarray(means),
      log_scales=jnp.full((num, 3), np.log(0.12), jnp.float32),
      opacity_logits=jnp.full((num,), 2.0, jnp.float32),
      sh_dc=jnp.asarray(sh.rgb_to_dc(colors), jnp.float32))
  alive = jnp.ones((num,), bool)
  cams = []
  total = num_train + num_test
  for i in range(total):
    a = 2 * np.pi * i / total
    eye = [3.0 * np.cos(a), 0.8 * np.sin(3 * a), 3.0 * np.sin(a)]
    cams.append(camera.look_at(eye, [0, 0, 0], [0, 1, 0], size, size, size,
                               size))
  stacked = jax.tree.map(lambda *x: np.stack(x), *cams)
  render = evaluation._render_fn(TEST_CFG.render)
  images = np.stack([
      np.asarray(render(params, alive, camera.camera_at(stacked, i),
                        jnp.zeros(3), jnp.int32(0))[0])
      for i in range(total)])

  def views(idx):
    return Views(cameras=jax.tree.map(lambda x: x[idx], stacked),
                 images=images[idx], names=tuple(str(i) for i in idx))

  noisy = lambda x, s: (x + rng.normal(0, s, x.shape)).astype(np.float32)
  return Scene(train=views(np.arange(num_train)),
               test=views(np.arange(num_train, total)),
               points=noisy(means, 0.05),
               point_colors=np.clip(noisy(colors, 0.15), 0, 1),
               extent=3.3)


class CompileCounter:
  """Counts XLA compilations per function name (jax.monitoring events)."""

  _EVENT = "/jax/core/compile/backend_compile_duration"

  def __init__(self):
    self.names = []

  def _listener(self, event, duration, **kwargs):
    del duration
    if event == self._EVENT:
      self.names.append(kwargs.get("fun_name", ""))

  def count(self, name):
    return sum(name in n for n in self.names)

  def __enter__(self):
    jax.monitoring.register_event_duration_secs_listener(self._listener)
    return self

  def __exit__(self, *exc):
    jax.monitoring.unregister_event_duration_listener(self._listener)


class ViewAndBackgroundTest(absltest.TestCase):

  def test_each_epoch_is_a_permutation(self):
    key = jax.random.key(0)
    order = [int(view.view_index(key, jnp.int32(s), 5)) for s in range(15)]
    for epoch in range(3):
      self.assertEqual(sorted(order[5 * epoch:5 * epoch + 5]), list(range(5)))
    self.assertNotEqual(order[:5], order[5:10])     # reshuffled per epoch
    again = [int(view.view_index(key, jnp.int32(s), 5)) for s in range(15)]
    self.assertEqual(order, again)                  # pure in (key, step)

  def test_background(self):
    key = jax.random.key(1)
    fixed = dataclasses.replace(TEST_CFG, train=config.TrainConfig(
        background=(1.0, 0.5, 0.0)))
    np.testing.assert_array_equal(
        view.background(key, jnp.int32(3), fixed), [1.0, 0.5, 0.0])
    rand = dataclasses.replace(TEST_CFG, train=config.TrainConfig(
        random_background=True))
    b3 = view.background(key, jnp.int32(3), rand)
    b4 = view.background(key, jnp.int32(4), rand)
    self.assertTrue(np.all((b3 >= 0) & (b3 <= 1)))
    self.assertFalse(np.allclose(b3, b4))
    np.testing.assert_array_equal(b3, view.background(key, jnp.int32(3),
                                                       rand))

  def test_boundary_errors(self):
    with self.assertRaisesRegex(FloatingPointError, "non-finite loss"):
      loop.check_finite(7, {"loss": float("nan"), "psnr": 1.0})
    scene = synthetic_scene(num=4, size=16, num_train=2, num_test=1)
    bad = dataclasses.replace(scene.train, images=scene.train.images[:, :8])
    with self.assertRaisesRegex(ValueError, "cameras are 16x16"):
      sharding.lanes_of(dataclasses.replace(scene, train=bad), 1,
                        sharding.make_mesh(1))
    with self.assertRaisesRegex(ValueError, "extent .* is not positive"):
      train.resolve(TEST_CFG, dataclasses.replace(scene, extent=0.0))
    with self.assertRaisesRegex(ValueError, "resolve"):
      train.init_state(TEST_CFG, *gaussians.empty(4, 1))

  def test_resolve_renders_onto_the_photos_background(self):
    # Photos with alpha composited onto black: the run renders onto black
    # (and fills the extent); photos without alpha keep the config's.
    # resolve reads a scene's extent and background alone.
    white = dataclasses.replace(TEST_CFG, train=dataclasses.replace(
        TEST_CFG.train, background=(1.0, 1.0, 1.0)))
    on_black = types.SimpleNamespace(extent=2.5, background=(0.0, 0.0, 0.0))
    cfg = train.resolve(white, on_black)
    self.assertEqual(tuple(cfg.train.background), (0.0, 0.0, 0.0))
    self.assertEqual(cfg.scene_extent, 2.5)
    kept = train.resolve(white, types.SimpleNamespace(extent=2.5,
                                                      background=None))
    self.assertEqual(tuple(kept.train.background), (1.0, 1.0, 1.0))

  def test_a_perfect_render_gives_finite_step_metrics(self):
    # No Gaussian alive, a black background and black photos: the render
    # equals the target exactly. PSNR is capped at -10 log10(MIN_MSE) =
    # 100 dB instead of +inf, so the loop's finiteness check passes.
    scene = synthetic_scene(num=4, size=16, num_train=2, num_test=1)
    cfg = train.resolve(TEST_CFG, scene)
    state = train.init_state(cfg, *gaussians.empty(8, 1))
    black = dataclasses.replace(
        scene.train, images=np.zeros_like(scene.train.images))
    step_fn, lanes, state, _ = step.for_scene(
        cfg, dataclasses.replace(scene, train=black), state)
    _, metrics = step_fn(state, lanes, None)
    values = {k: float(v) for k, v in jax.device_get(metrics).items()
              if k != "view"}
    self.assertAlmostEqual(values["psnr"], 100.0, places=3)
    self.assertEqual(values["l1"], 0.0)
    loop.check_finite(1, values)


class EndToEndTest(absltest.TestCase):

  def test_smoke_run(self):
    # Fresh jitted functions, so the compile count below does not depend on
    # which other test compiled the same config first in this process.
    step.make_train_step.cache_clear()
    densify.make_densify.cache_clear()
    scene = synthetic_scene()
    workdir = self.create_tempdir().full_path
    with CompileCounter() as compiles:
      result = train.fit(train.resolve(TEST_CFG, scene), scene, workdir,
                         progress=False)
    curve = result.curve
    self.assertEqual([p["step"] for p in curve], [0, 40, 80, 120])
    self.assertGreater(curve[-1]["test_psnr"], curve[0]["test_psnr"] + 3.0)
    self.assertTrue(all(b["seconds"] >= a["seconds"]
                        for a, b in zip(curve, curve[1:])))
    state = result.state
    self.assertEqual(int(state.step), 120)
    self.assertLessEqual(int(jnp.sum(state.alive)), state.capacity)
    self.assertEqual(state.capacity, 256)
    log = {int(x["step"]): x for x in result.log}
    self.assertEqual(sorted(log), [20, 40, 60, 80, 100, 120])
    grew = sum(log[s]["num_cloned"] + log[s]["num_split"]
               for s in (40, 60, 80))
    self.assertGreater(grew, 0)
    self.assertGreater(log[120]["num_alive"], log[20]["num_alive"])
    for entry in result.log:
      self.assertLessEqual(entry["num_alive"], 256)
      self.assertEqual(entry["num_overflow"], 0)
      for field in ("means", "sh_dc", "opacity_logits"):
        self.assertGreater(entry[f"grad_norm/{field}"], 0)
    self.assertEqual(log[120]["sh_degree"], 1)
    # Three densify/prune cycles and an opacity reset, one compilation of
    # the step and one of densify: nothing retraced.
    self.assertEqual(compiles.count("train_step"), 1, compiles.names)
    self.assertEqual(compiles.count("densify"), 1, compiles.names)
    self.assertTrue(os.path.exists(os.path.join(workdir,
                                                train.CHECKPOINT_NAME)))
    # The final evaluation matches a fresh one of the returned state.
    again = evaluation.evaluate(state.params, state.alive, scene.test, result.cfg)
    np.testing.assert_allclose(again["mean/psnr"], curve[-1]["test_psnr"],
                               rtol=1e-6)

  def test_step_benchmark_leaves_the_callers_state_usable(self):
    # bench.py --bench=step --checkpoint times one state once per count;
    # the donated train step must not delete the caller's arrays.
    scene = synthetic_scene()
    cfg = train.resolve(TEST_CFG, scene)
    state = train.initial_state(cfg, scene)
    means = np.asarray(state.params.means)
    out = timing.step_stages(cfg, scene, state.params, state.alive,
                             view=0, repeats=1)
    self.assertGreater(out["train_step"]["wall_ms"], 0)
    self.assertEqual(out["n"], int(np.sum(np.asarray(state.alive))))
    np.testing.assert_array_equal(np.asarray(state.params.means), means)

  def test_steps_after_the_first_compile_and_transfer_nothing(self):
    # The loop dispatches steps back to back: after the first, a step of
    # one view on one device, or of a guided run with the residual or the
    # learned map, compiles nothing and moves nothing between host and device.
    scene = synthetic_scene()
    residual = dataclasses.replace(
        TEST_CFG,
        semantic=guidance_config.SemanticConfig(scorer="residual",
                                                evidence="pixel",
                                                accumulate_start=0,
                                                reg_start=0),
        pixel=guidance_config.PixelConfig(loss_masking=True))
    # The learned map: its classifier's update is in the step too.
    learned = dataclasses.replace(
        residual, semantic=dataclasses.replace(residual.semantic,
                                               scorer="learned"))
    for cfg in (TEST_CFG, residual, learned):
      cfg = train.resolve(cfg, scene)
      step_fn, lanes, state, scorer = step.for_scene(
          cfg, scene, train.initial_state(cfg, scene),
          guidance.make_scorer(cfg, scene))
      state, _ = jax.block_until_ready(step_fn(state, lanes, scorer))
      with CompileCounter() as compiles, jax.transfer_guard("disallow"):
        for _ in range(3):
          state, metrics = step_fn(state, lanes, scorer)
        jax.block_until_ready((state, metrics))
      self.assertEqual(compiles.names, [], cfg.semantic.scorer)

  def test_runs_that_differ_on_the_host_share_one_step(self):
    # Another seed, split, curve and cadence: the same compiled functions
    # (a table's vanilla and clean rows compile their step once).
    host = dataclasses.replace(
        TEST_CFG, data=config.DataConfig(scene="elsewhere",
                                         train_split="clean"),
        eval=config.EvalConfig(curve_points=3),
        train=dataclasses.replace(TEST_CFG.train, seed=7, log_every=5,
                                  eval_every=0, checkpoint_every=9))
    mesh = sharding.make_mesh(1)
    make_step = lambda c: step.make_train_step(c, mesh)
    for make in (make_step, densify.make_densify,
                 densify.make_reset_opacity, densify.make_count_requests):
      self.assertIs(make(host), make(TEST_CFG), make.__name__)
    # The prune rule is not the step's: the step is shared, the prune not.
    oracle = guidance_config.SemanticConfig(scorer="oracle", evidence="pixel")
    strict = dataclasses.replace(TEST_CFG, semantic=oracle)
    lenient = dataclasses.replace(TEST_CFG,
                                  semantic=dataclasses.replace(
                                      oracle, max_prune_fraction=1.0),
                                  pixel=guidance_config.PixelConfig(tau_p=0.9))
    self.assertIs(make_step(strict), make_step(lenient))
    self.assertIsNot(guidance.make_prune(strict), guidance.make_prune(lenient))
    # What the step computes with is not shared.
    dssim = dataclasses.replace(
        TEST_CFG, train=dataclasses.replace(TEST_CFG.train, lambda_dssim=0.5))
    self.assertIsNot(make_step(dssim), make_step(TEST_CFG))
    # A dropped field fails loudly where compiled code would read it (the
    # fits in this file trace every function above with dropped fields).
    part = compiled.compiled_part(host)
    self.assertIs(part.data, compiled.HOST_ONLY)
    with self.assertRaisesRegex(TypeError, "host-only config field"):
      bool(part.train.seed)
    with self.assertRaises(TypeError):
      part.train.eval_every + 1  # pylint: disable=pointless-statement
    self.assertEqual(part.train.steps, TEST_CFG.train.steps)


if __name__ == "__main__":
  absltest.main()
