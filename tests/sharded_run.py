"""Runs of the multi-device tests (tests/test_sharding.py), each in its own
process, since a process's device count is fixed when JAX starts.

  python tests/sharded_run.py devices OUT
      (XLA_FLAGS=--xla_force_host_platform_device_count=2): into OUT/
      sharded/ a B = 2 run over both devices, into OUT/resumed/ the same
      run killed at KILL_AT and resumed, into OUT/unsharded/ the B = 2 run
      on one device, and OUT/memory.npz (`memory_step`).
  python tests/sharded_run.py process OUT ID PORT: process ID of a
      two-process run (one device each) into OUT/two_process/.

Each leaves its final state in checkpoint.npz.
"""

import dataclasses
import os
import sys

import numpy as np

# B = 2 views per step, 30 steps: densify at 10 and 20 (the first grows the
# capacity from 64), residual maps and their statistics, loss masking.
BATCH = 2
STEPS = 30
KILL_AT = 15
CAPACITY = 64


def canvas_scene():
  """The synthetic scene (test_train) with photos of three sizes (two
  training views and a test view cut to the top-left of the canvas) and
  transient masks on two training views."""
  import test_train  # pylint: disable=g-import-not-at-top
  from clipgs_jax.data import scene as scene_lib  # pylint: disable=g-import-not-at-top
  base = test_train.synthetic_scene()

  def cut(views, sizes, masks=None):
    sizes = np.asarray(sizes, np.int32)
    images = np.array(views.images)
    for im, (w, h) in zip(images, sizes):
      im[h:], im[:, w:] = 0, 0
    return scene_lib.Views(cameras=views.cameras, images=images,
                           names=views.names, masks=masks, sizes=sizes)
  num, size = base.train.images.shape[:2]
  train_sizes = [(size, size)] * num
  train_sizes[1], train_sizes[4] = (size, size - 8), (size - 6, size)
  masks = np.zeros((num, size, size), bool)
  masks[0, 4:12, 6:20] = True
  masks[4, 20:, 10:] = True
  masks[4, :, size - 6:] = False           # nothing outside the photo
  test_sizes = [(size, size)] * len(base.test.names)
  test_sizes[0] = (size - 4, size - 10)
  return scene_lib.Scene(
      train=cut(base.train, train_sizes, masks),
      test=cut(base.test, test_sizes),
      points=base.points, point_colors=base.point_colors,
      extent=base.extent, path="")


def config():
  """The runs' config: the smoke preset's densify, ORACLE-PIXEL evidence
  with loss masking and its prune."""
  from clipgs_jax import config_file  # pylint: disable=g-import-not-at-top
  cfg = config_file.named("smoke")
  return dataclasses.replace(
      cfg,
      gaussians=dataclasses.replace(cfg.gaussians, capacity=CAPACITY),
      train=dataclasses.replace(cfg.train, steps=STEPS, batch_size=BATCH,
                                eval_every=0, checkpoint_every=0),
      semantic=dataclasses.replace(
          cfg.semantic, scorer="oracle", evidence="pixel",
          accumulate_start=0, reg_start=5, prune_start=25, prune_every=10),
      pixel=dataclasses.replace(cfg.pixel, loss_masking=True))


def anisotropic_state(cfg, scene):
  """The initial state with anisotropic Gaussians. From isotropic ones the
  quaternions' exact gradient is 0 and their computed one rounding noise,
  which Adam (eps 1e-15) turns into a full learning-rate step of random
  sign: no two compiled programs would agree on it."""
  import jax  # pylint: disable=g-import-not-at-top
  from clipgs_jax import train  # pylint: disable=g-import-not-at-top
  state = train.initial_state(cfg, scene)
  rng = np.random.default_rng(0)
  log_scales = state.params.log_scales + rng.uniform(
      -0.4, 0.4, state.params.log_scales.shape).astype(np.float32)
  return state.replace(params=state.params.replace(
      log_scales=jax.numpy.asarray(log_scales)))


def start(cfg, scene, workdir: str) -> None:
  """Writes the step-0 checkpoint a run resumes from
  (`anisotropic_state`)."""
  from clipgs_jax import checkpoint  # pylint: disable=g-import-not-at-top
  from clipgs_jax import train  # pylint: disable=g-import-not-at-top
  checkpoint.save(os.path.join(workdir, train.CHECKPOINT_NAME),
                  anisotropic_state(cfg, scene), cfg, extra={})


def main(mode: str, out: str, *args):
  if mode == "process":
    from clipgs_jax import sharding  # pylint: disable=g-import-not-at-top
    process_id, port = (int(a) for a in args)
    sharding.join(f"localhost:{port}", 2, process_id)
  import jax  # pylint: disable=g-import-not-at-top
  jax.config.update("jax_disable_most_optimizations", True)
  from clipgs_jax import guidance  # pylint: disable=g-import-not-at-top
  from clipgs_jax import sharding  # pylint: disable=g-import-not-at-top
  from clipgs_jax import train  # pylint: disable=g-import-not-at-top
  from clipgs_jax.data import scene as scene_lib  # pylint: disable=g-import-not-at-top
  scene = canvas_scene()
  cfg = train.resolve(config(), scene)
  full = scene
  if mode == "process":
    # This process reads only its lane's views.
    lanes = sharding.held_lanes(sharding.make_mesh(BATCH), BATCH)
    held = [v for v in range(len(scene.train))
            if sharding.holds(v, BATCH, lanes)]
    scene = dataclasses.replace(
        scene, train=scene_lib.subset(scene.train, held),
        train_cameras=scene.train.cameras)

  def fit(folder, **kw):
    # Every process starts from its own step-0 checkpoint; process 0 writes
    # the run's.
    workdir = os.path.join(out, folder + (
        "" if sharding.is_writer() else f"_{jax.process_index()}"))
    if not kw.get("resume"):
      os.makedirs(workdir, exist_ok=True)
      start(cfg, full, workdir)
    return train.fit(cfg, scene, workdir, progress=False, resume=True,
                     scorer=guidance.make_scorer(cfg, scene),
                     **{k: v for k, v in kw.items() if k != "resume"})
  if mode == "process":
    fit("two_process")
    return
  fit("sharded")
  fit("resumed", stop_after=KILL_AT)
  fit("resumed", resume=True)
  fit("unsharded", devices=jax.devices()[:1])
  memory_step(cfg, full, out)


def memory_step(cfg, scene, out: str) -> None:
  """One B = 2 step over both devices of the residual map with its memory
  and threshold 0 (every photo pixel transient); writes the memory and
  the step's views to OUT/memory.npz."""
  import jax  # pylint: disable=g-import-not-at-top
  from clipgs_jax import guidance  # pylint: disable=g-import-not-at-top
  from clipgs_jax import step  # pylint: disable=g-import-not-at-top
  from clipgs_jax import train  # pylint: disable=g-import-not-at-top
  cfg = dataclasses.replace(
      cfg, semantic=dataclasses.replace(cfg.semantic, scorer="residual"),
      residual=dataclasses.replace(cfg.residual, min_threshold=0.0,
                                   min_alpha=0.0, min_share=0.0,
                                   uniform_until=0, remember=True))
  state = train.initial_state(cfg, scene)
  state = state.replace(maps=state.maps.replace(
      threshold=jax.numpy.float32(0)))
  fn, lanes, state, scorer = step.for_scene(
      cfg, scene, state, guidance.make_scorer(cfg, scene))
  state, metrics = fn(state, lanes, scorer)
  np.savez(os.path.join(out, "memory.npz"),
           memory=np.asarray(state.maps.memory),
           views=np.asarray(metrics["view"]))


if __name__ == "__main__":
  main(*sys.argv[1:])
