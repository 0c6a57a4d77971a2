"""clipgs_jax.benchmark: the timer and the stand-in scenes."""

import jax.numpy as jnp
import numpy as np

from clipgs_jax import camera
from clipgs_jax.lab import timing
from clipgs_jax.render import project


def test_time_calls_counts_and_rounds():
  calls = []

  def fn(x):
    calls.append(x)
    return x + 1

  t = timing.time_calls(fn, jnp.float32(1), repeats=3, warmup=2)
  assert len(calls) == 1 + 2 + 3       # first (compiling), warm-up, timed
  assert float(t.out) == 2.0
  assert len(t.wall_s) == len(t.cpu_s) == 3
  fixed = timing.Timing(None, 1.23456, [0.001, 0.003, 0.002],
                        [0.0005, 0.0005, 0.004])
  # Medians: 2 ms wall, 0.5 ms CPU; compile seconds to 2 places.
  assert fixed.ms() == {"compile_s": 1.23, "wall_ms": 2.0, "cpu_ms": 0.5}


def test_time_steps_threads_the_state():
  seen = []

  def step(state, inc):
    seen.append(int(state))
    return state + inc, state * 10

  t = timing.time_steps(step, jnp.int32(0), jnp.int32(1), repeats=3)
  assert seen == [0, 1, 2, 3]          # each call gets the previous state
  assert int(t.out) == 0               # the first call's second output
  assert len(t.wall_s) == len(t.cpu_s) == 3


def test_frustum_scene_projects_inside_the_image():
  params, alive, cam = timing.frustum_scene(200, 64, 48, 2.0, 20.0)
  assert params.means.shape == (200, 3) and bool(alive.all())
  proj = project.project(params, alive, cam, near=0.2, sh_degree=0)
  xy = np.asarray(proj.means2d)
  assert (xy[:, 0] >= 0).all() and (xy[:, 0] <= 64).all()
  assert (xy[:, 1] >= 0).all() and (xy[:, 1] <= 48).all()
  np.testing.assert_allclose(camera.camera_center(cam), 0.0, atol=1e-6)


def test_stand_in_resamples_alive_rows():
  params, alive, _ = timing.frustum_scene(50, 64, 48, 2.0, 20.0)
  alive = alive.at[:25].set(False)
  # Dead rows far away: a point resampled from one would be far from all
  # live ones.
  params = params.replace(means=params.means.at[:25].add(1000.0))
  out, out_alive = timing.stand_in(params, alive, 400)
  assert out.means.shape == (400, 3) and out_alive.shape == (400,)
  # 8x the alive rows: scales shrink by 8^(1/3) = 2.
  source = np.exp(np.asarray(params.log_scales)[25:])
  assert np.exp(np.asarray(out.log_scales)).max() <= source.max() / 2 + 1e-6
  # Every new point lies near a live source point, none near a dead one.
  live = np.asarray(params.means)[25:]
  dist = np.linalg.norm(np.asarray(out.means)[:, None] - live[None], axis=-1)
  # Jitter is 0.5 x scale x N(0, 1) per axis; 6 sigma in 3D bounds it.
  assert (dist.min(axis=1) <= 0.5 * 6 * source.max()).all()
  assert out.sh_rest.shape == (400, 0, 3)
