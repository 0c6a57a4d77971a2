"""Times one training step on a real bird view, stage by stage.

Prints one JSON line per Gaussian count: wall and CPU ms of projection,
binning + sort, blend forward, blend backward, loss, Adam and the whole
jitted `train.train_step`; compile times; and the blend's lockstep
efficiency (needed / executed pixel evaluations) and the share of executed
pixel-entry pairs with a non-zero alpha (`rasterize.blend_stats`).

The state: the scene's SfM points (what step 0 trains), or, for a count
above that, the points resampled with jitter and shrunk scales, with
opacities sigmoid(N(0, 1.5)), as a stand-in for a densified model of that
size (`--checkpoint` loads a real one instead).

  python experiments/bench_step.py --num_gaussians=0,220000
"""

import json
import os
import time

from absl import app
from absl import flags
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import blend
from clipgs_jax import camera
from clipgs_jax import checkpoint
from clipgs_jax import config
from clipgs_jax import gaussians
from clipgs_jax import losses
from clipgs_jax import project
from clipgs_jax import rasterize
from clipgs_jax import train
from clipgs_jax.data import scene as scene_lib

_SCENE = flags.DEFINE_string("scene", "../shared/data/bird", "COLMAP scene.")
_DOWNSCALE = flags.DEFINE_integer("downscale", 4, "Image downscale factor.")
_VIEW = flags.DEFINE_integer("view", 0, "Training view index.")
_NUM = flags.DEFINE_list(
    "num_gaussians", ["0", "220000"],
    "Alive counts; 0 = the SfM points as loaded (the step-0 state). 220k is "
    "about where a bird ds4 7k-step run ends (BUILD_NOTES: 223k at 5950).")
_CHECKPOINT = flags.DEFINE_string("checkpoint", "", "Optional checkpoint.npz "
                                  "whose state replaces the stand-in.")
_TILE_BUDGET = flags.DEFINE_integer("tile_budget", 8192, "K.")
_CHUNK = flags.DEFINE_integer("chunk_size", 32, "B.")
_LANES = flags.DEFINE_integer("lanes", 0, "Blend lanes; 0 = automatic.")
_TILE_SIZE = flags.DEFINE_integer("tile_size", 16, "Tile side, pixels.")
_REPEATS = flags.DEFINE_integer("repeats", 3, "Timed runs (median).")
_OPACITY_STD = 1.5    # logit spread of the stand-in: mostly 0.05-0.95
_JITTER = 0.5         # resampled points move by this x their kNN scale


def _timed(fn, *args):
  """Compile seconds, and median wall / CPU ms over the repeats."""
  t0 = time.perf_counter()
  out = jax.block_until_ready(fn(*args))
  compile_s = time.perf_counter() - t0
  wall, cpu = [], []
  for _ in range(_REPEATS.value):
    w0, c0 = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn(*args))
    wall.append(time.perf_counter() - w0)
    cpu.append(time.process_time() - c0)
  return out, dict(compile_s=round(compile_s, 2),
                   wall_ms=round(1e3 * float(np.median(wall)), 1),
                   cpu_ms=round(1e3 * float(np.median(cpu)), 1))


def _stand_in(params, alive, n, seed=0):
  """`n` Gaussians resampled from the alive rows (see module docstring)."""
  rng = np.random.default_rng(seed)
  rows = np.flatnonzero(np.asarray(alive))
  pick = rng.choice(rows, n)
  grow = (n / len(rows)) ** (1 / 3)       # same volume coverage at n rows
  scale = np.exp(np.asarray(params.log_scales)[pick])
  means = (np.asarray(params.means)[pick]
           + _JITTER * scale * rng.normal(size=(n, 3)))
  take = lambda x: jnp.asarray(np.asarray(x)[pick])
  out = gaussians.GaussianParams(
      means=jnp.asarray(means, jnp.float32),
      log_scales=jnp.asarray(np.log(scale / grow), jnp.float32),
      quats=jnp.asarray(rng.normal(size=(n, 4)), jnp.float32),
      opacity_logits=jnp.asarray(rng.normal(0, _OPACITY_STD, n), jnp.float32),
      sh_dc=take(params.sh_dc), sh_rest=take(params.sh_rest))
  return out, jnp.ones(n, bool)


def bench(cfg, scene, batch, params, alive):
  state = train.init_state(cfg, params, alive)
  cam = camera.camera_at(batch.cameras, _VIEW.value)
  target = batch.images[_VIEW.value]
  rcfg = cfg.render
  grid = blend.Grid(int(cam.width), int(cam.height), rcfg.tile_budget,
                    rcfg.chunk_size, rcfg.lanes, rcfg.tile_size)
  degree = 0
  result = dict(n=int(np.sum(np.asarray(alive))), capacity=int(alive.shape[0]),
                width=int(cam.width), height=int(cam.height),
                tile_budget=rcfg.tile_budget, chunk_size=rcfg.chunk_size)

  def proj_fn(p):
    return project.project(p, state.alive, cam, near=rcfg.near,
                           sh_degree=degree)

  proj, result["project_fwd"] = _timed(jax.jit(proj_fn), state.params)
  _, result["project_fwd_bwd"] = _timed(jax.jit(lambda p: jax.vjp(
      proj_fn, p)[1](proj)), state.params)
  # pylint: disable=protected-access
  binned, result["bin_sort"] = _timed(
      jax.jit(lambda q: rasterize._bin(q, grid)), proj)
  gauss, start, count, overflow, max_count = binned
  tables = (gauss, start, count)
  pix, inside = rasterize._pixel_centers(grid, jnp.float32)
  # pylint: enable=protected-access
  splats = (proj.means2d, proj.conics, proj.colors, proj.opacities,
            proj.depths)
  fwd = jax.jit(lambda s, tb: blend.forward(grid, s, tb, pix, inside, None))
  (color, depth, trans, n_contrib, _, _, _), result["blend_fwd"] = (
      _timed(fwd, splats, tables))
  rng = np.random.default_rng(0)
  cot = (jnp.asarray(rng.normal(size=color.shape), jnp.float32),
         jnp.asarray(rng.normal(size=depth.shape), jnp.float32),
         jnp.asarray(rng.normal(size=trans.shape), jnp.float32))
  bwd = jax.jit(lambda s, tb, *a: blend.backward(grid, s, tb, pix, *a))
  _, result["blend_bwd"] = _timed(
      bwd, splats, tables, color, depth, trans, n_contrib, *cot)
  image = jnp.zeros(target.shape)
  _, result["loss_fwd_bwd"] = _timed(jax.jit(jax.grad(
      lambda x: losses.photometric(x, target, 0.2)[0])), image)
  tx = train.make_optimizer(cfg)
  _, result["adam"] = _timed(jax.jit(lambda g, o, p: tx.update(g, o, p)),
                             state.params, state.opt_state, state.params)
  step = jax.jit(lambda s: train.train_step(s, batch, cfg=cfg))
  _, result["train_step"] = _timed(step, state)
  result.update(num_overflow=int(overflow), max_tile_count=int(max_count))
  result.update(rasterize.blend_stats(proj, cam, rcfg))
  return result


def main(argv):
  del argv
  scene = scene_lib.load_scene(_SCENE.value, downscale=_DOWNSCALE.value)
  cfg = config.Config(render=config.RenderConfig(
      tile_budget=_TILE_BUDGET.value, chunk_size=_CHUNK.value,
      lanes=_LANES.value, tile_size=_TILE_SIZE.value))
  cfg = train.resolve(cfg, scene)
  batch = train.make_batch(scene.train)
  base = train.initial_state(cfg, scene)
  if _CHECKPOINT.value:
    if not os.path.exists(_CHECKPOINT.value):
      raise FileNotFoundError(f"--checkpoint {_CHECKPOINT.value} not found.")
    base = checkpoint.restore(_CHECKPOINT.value, base)[0]
  for n in (int(float(x)) for x in _NUM.value):
    if n == 0 or _CHECKPOINT.value:
      params, alive = base.params, base.alive
    else:
      params, alive = _stand_in(base.params, base.alive, n)
    result = bench(cfg, scene, batch, params, alive)
    result.update(load_average=os.getloadavg()[0], scene=_SCENE.value,
                  downscale=_DOWNSCALE.value, view=_VIEW.value,
                  source="checkpoint" if _CHECKPOINT.value else
                  ("sfm_points" if n == 0 else "stand_in"))
    print(json.dumps(result), flush=True)


if __name__ == "__main__":
  app.run(main)
