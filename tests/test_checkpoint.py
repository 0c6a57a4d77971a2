"""Tests for checkpoint: flat .npz round trip, atomicity, bit-identical resume."""

import dataclasses
import json
import os

import chex
import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

from clipgs_jax import checkpoint
from clipgs_jax import config_file
from clipgs_jax import fileio
from clipgs_jax import gaussians
from clipgs_jax import state as state_lib
from clipgs_jax import train
from test_train import synthetic_scene, TEST_CFG  # pylint: disable=g-bad-import-order

CFG = dataclasses.replace(TEST_CFG, scene_extent=2.0)


def _state(capacity=16, seed=0):
  rng = np.random.default_rng(seed)
  params, alive = gaussians.empty(capacity, 1)
  params = jax.tree.map(
      lambda x: jnp.asarray(rng.normal(size=x.shape), jnp.float32), params)
  state = train.init_state(CFG, params, alive.at[:capacity // 2].set(True))
  state = state.replace(
      opt_state=state_lib.map_rows(
          state.opt_state, capacity,
          lambda x: jnp.asarray(rng.normal(size=x.shape), x.dtype)),
      semantic=state_lib.SemanticStats(
          acc=jnp.asarray(rng.random(capacity), jnp.float32),
          weight=jnp.asarray(rng.random(capacity), jnp.float32),
          n=jnp.arange(capacity, dtype=jnp.float32)),
      step=jnp.int32(1234))
  return state


def _assert_states_equal(a, b):
  a, b = jax.device_get(a), jax.device_get(b)
  np.testing.assert_array_equal(jax.random.key_data(a.key),
                                jax.random.key_data(b.key))
  strip = lambda s: s.replace(key=jnp.zeros(()))
  chex.assert_trees_all_equal(strip(a), strip(b))
  chex.assert_trees_all_equal_dtypes(strip(a), strip(b))


class RoundTripTest(absltest.TestCase):

  def test_save_restore(self):
    state = _state()
    path = os.path.join(self.create_tempdir().full_path, "ckpt.npz")
    checkpoint.save(path, state, CFG, extra={"curve": [{"step": 1}]})
    self.assertEqual(os.listdir(os.path.dirname(path)), ["ckpt.npz"])
    template = _state(seed=1).replace(step=jnp.int32(0))
    restored, meta = checkpoint.restore(path, template)
    _assert_states_equal(restored, state)
    self.assertEqual(config_file.from_dict(meta["config"]), CFG)
    self.assertEqual(meta["extra"], {"curve": [{"step": 1}]})
    # Flat '/'-keyed names, loadable without pickle.
    with np.load(path, allow_pickle=False) as data:
      self.assertIn("state/params/means", data)
      self.assertIn("state/opt_state/inner_states/means/inner_state/0/mu/"
                    "means", data)
      self.assertIn("state/semantic/acc", data)
      json.loads(str(data["meta/config"]))

  def test_restore_into_other_capacity(self):
    state = state_lib.resize(_state(capacity=16), 32)
    path = os.path.join(self.create_tempdir().full_path, "ckpt.npz")
    checkpoint.save(path, state, CFG)
    restored, _ = checkpoint.restore(path, _state(capacity=16, seed=2))
    self.assertEqual(restored.capacity, 32)
    _assert_states_equal(restored, state)

  def test_overwrite_is_atomic(self):
    directory = self.create_tempdir().full_path
    path = os.path.join(directory, "ckpt.npz")
    checkpoint.save(path, _state(seed=0), CFG)

    def failing_write(tmp):
      with open(tmp, "wb") as f:
        f.write(b"partial")
      raise RuntimeError("disk full")
    with self.assertRaisesRegex(RuntimeError, "disk full"):
      fileio.atomic_write(path, failing_write, ".npz")
    # The old file is intact and no temporary file is left behind.
    self.assertEqual(os.listdir(directory), ["ckpt.npz"])
    restored, _ = checkpoint.restore(path, _state(seed=3))
    _assert_states_equal(restored, _state(seed=0))

  def test_errors(self):
    directory = self.create_tempdir().full_path
    with self.assertRaisesRegex(FileNotFoundError, "does not exist"):
      checkpoint.restore(os.path.join(directory, "none.npz"), _state())
    other = os.path.join(directory, "other.npz")
    np.savez(other, x=np.zeros(3))
    with self.assertRaisesRegex(ValueError, "not a clipgs_jax checkpoint"):
      checkpoint.restore(other, _state())
    path = os.path.join(directory, "ckpt.npz")
    checkpoint.save(path, _state(), CFG)
    degree2 = train.init_state(CFG, *gaussians.empty(16, 2))
    with self.assertRaisesRegex(ValueError, "sh_rest is float32"):
      checkpoint.restore(path, degree2)
    # A checkpoint of an older format (version 1 had no semantic weight).
    with np.load(path) as data:
      old = {k: data[k] for k in data.files
             if k != "state/semantic/weight"}
    old["meta/version"] = np.asarray(1, np.int32)
    np.savez(path, **old)
    with self.assertRaisesRegex(ValueError, "format version 1, this code "
                                f"reads {checkpoint.VERSION}"):
      checkpoint.restore(path, _state())


class ResumeTest(absltest.TestCase):

  def test_resume_is_bit_identical(self):
    scene = synthetic_scene()
    cfg = train.resolve(TEST_CFG, scene)
    straight_dir = self.create_tempdir().full_path
    resumed_dir = self.create_tempdir().full_path
    straight = train.fit(cfg, scene, straight_dir, progress=False)
    half = train.fit(cfg, scene, resumed_dir, progress=False,
                     stop_after=50)
    self.assertEqual(int(half.state.step), 50)
    resumed = train.fit(cfg, scene, resumed_dir, progress=False,
                        resume=True)
    self.assertEqual(int(resumed.state.step), TEST_CFG.train.steps)
    _assert_states_equal(resumed.state, straight.state)
    self.assertEqual(resumed.curve, [
        dict(p, seconds=q["seconds"])
        for p, q in zip(straight.curve, resumed.curve)])
    # The halves really differ from the end state (the test can fail).
    self.assertFalse(np.array_equal(half.state.params.means,
                                    straight.state.params.means))
    # A different config cannot resume this run.
    other = dataclasses.replace(
        cfg, train=dataclasses.replace(cfg.train, seed=1))
    with self.assertRaisesRegex(ValueError, "different config"):
      train.fit(other, scene, resumed_dir, progress=False, resume=True)


if __name__ == "__main__":
  absltest.main()
