"""Times the tile rasterizer: custom VJP against plain autodiff of its forward.

Prints one JSON line per (N, image size, variant): forward ms, forward +
backward ms (wall and CPU), compile seconds, backward / forward, XLA's peak
buffer estimate for forward + backward, tile overflow, the longest tile list
and (custom VJP) the blend's lockstep efficiency and non-zero-alpha share
from `rasterize.blend_stats`.

  python experiments/bench_rasterizer.py
  python experiments/bench_rasterizer.py --num_gaussians=10000 --sizes=256x256
"""

import json
import os
import time

from absl import flags
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import camera
from clipgs_jax import cli
from clipgs_jax import config
from clipgs_jax import gaussians
from clipgs_jax import project
from clipgs_jax import rasterize

_NUM = flags.DEFINE_list("num_gaussians", ["1000", "10000", "100000"],
                         "Scene sizes N.")
_SIZES = flags.DEFINE_list("sizes", ["256x256", "512x384"],
                           "Image sizes WxH.")
_VARIANTS = flags.DEFINE_list("variants", ["custom_vjp", "autodiff"],
                              "custom_vjp and/or autodiff.")
_RADIUS = flags.DEFINE_list("radius_px", ["2", "20"],
                            "Range of projected 3-sigma radii, pixels.")
_TILE_BUDGET = flags.DEFINE_integer(
    "tile_budget", 0, "K; 0 = the smallest power of two >= the scene's "
    "longest tile list (what BUILD_NOTES recommends), same for both variants.")
_CHUNK = flags.DEFINE_integer("chunk_size", 32, "B.")
_LANES = flags.DEFINE_integer("lanes", 0, "Blend lanes; 0 = automatic.")
_TILE_SIZE = flags.DEFINE_integer("tile_size", 16, "Tile side, pixels.")
_REPEATS = flags.DEFINE_integer("repeats", 5, "Timed runs (median).")
_MAX_BYTES = flags.DEFINE_float(
    "max_gib", 12.0, "Do not run a variant whose compiled forward+backward "
    "needs more memory than this (GiB); its estimate is still printed.")


def make_scene(n, width, height, r_lo, r_hi, seed=0):
  """N Gaussians in the view frustum with 3-sigma radii in [r_lo, r_hi] px."""
  rng = np.random.default_rng(seed)
  focal = 0.8 * max(width, height)
  cam = camera.Camera.create(np.eye(3), np.zeros(3), focal, focal, width / 2,
                             height / 2, width, height)
  z = rng.uniform(2.0, 8.0, n)
  u = rng.uniform(0, width, n)
  v = rng.uniform(0, height, n)
  means = np.stack([(u - width / 2) * z / focal, (v - height / 2) * z / focal,
                    z], -1)
  radius = rng.uniform(r_lo, r_hi, n)
  sigma = radius / 3 * z / focal                      # world std dev
  aniso = np.exp(rng.uniform(-0.5, 0.5, (n, 3)))
  params = gaussians.GaussianParams(
      means=jnp.asarray(means, jnp.float32),
      log_scales=jnp.asarray(np.log(sigma[:, None] * aniso), jnp.float32),
      quats=jnp.asarray(rng.normal(size=(n, 4)), jnp.float32),
      opacity_logits=jnp.asarray(rng.normal(0.0, 1.5, n), jnp.float32),
      sh_dc=jnp.asarray(rng.normal(0, 0.5, (n, 3)), jnp.float32),
      sh_rest=jnp.zeros((n, 0, 3), jnp.float32))
  return params, jnp.ones(n, bool), cam


def _time(fn, *args):
  """Compile s (first call), median wall ms and median CPU ms."""
  t0 = time.perf_counter()
  jax.block_until_ready(fn(*args))
  compile_s = time.perf_counter() - t0
  wall, cpu = [], []
  for _ in range(_REPEATS.value):
    t0, c0 = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn(*args))
    wall.append(time.perf_counter() - t0)
    cpu.append(time.process_time() - c0)
  return (compile_s, 1e3 * float(np.median(wall)),
          1e3 * float(np.median(cpu)))


def _peak_bytes(fn, *args):
  mem = fn.lower(*args).compile().memory_analysis()
  if mem is None:
    return None
  return int(mem.temp_size_in_bytes + mem.argument_size_in_bytes
             + mem.output_size_in_bytes)


def _budget(params, alive, cam):
  """Smallest power of two >= the longest tile list of this scene."""
  probe = config.RenderConfig(tile_budget=1 << 15, chunk_size=_CHUNK.value,
                              tile_size=_TILE_SIZE.value)
  proj = project.project(params, alive, cam, near=probe.near, sh_degree=0)
  longest = int(rasterize.rasterize(proj, cam, jnp.zeros(3),
                                    probe).max_tile_count)
  return max(_CHUNK.value, 1 << max(longest - 1, 1).bit_length())


def bench(n, width, height, variant):
  r_lo, r_hi = (float(r) for r in _RADIUS.value)
  params, alive, cam = make_scene(n, width, height, r_lo, r_hi)
  budget = _TILE_BUDGET.value or _budget(params, alive, cam)
  cfg = config.RenderConfig(tile_budget=budget, chunk_size=_CHUNK.value,
                            lanes=_LANES.value, tile_size=_TILE_SIZE.value)
  bg = jnp.zeros(3)
  custom = variant == "custom_vjp"

  def forward(p):
    proj = project.project(p, alive, cam, near=cfg.near, sh_degree=0)
    return rasterize.rasterize(proj, cam, bg, cfg, custom_vjp=custom)

  def loss(p):
    return jnp.mean(forward(p).image)

  fwd = jax.jit(lambda p: forward(p).image)
  grad = jax.jit(jax.grad(loss))
  result = dict(n=n, width=width, height=height, variant=variant,
                tile_budget=budget, chunk_size=cfg.chunk_size,
                backend=jax.default_backend())
  t0 = time.perf_counter()
  peak = _peak_bytes(grad, params)        # compiles forward + backward
  fb_compile = time.perf_counter() - t0
  result["peak_bytes_fwd_bwd"] = peak
  if peak is not None and peak > _MAX_BYTES.value * 2**30:
    result["skipped"] = f"needs {peak / 2**30:.1f} GiB > --max_gib"
    return result
  out = jax.jit(forward)(params)
  fwd_compile, fwd_ms, fwd_cpu = _time(fwd, params)
  _, fb_ms, fb_cpu = _time(grad, params)
  result.update(
      forward_ms=round(fwd_ms, 1), forward_backward_ms=round(fb_ms, 1),
      forward_cpu_ms=round(fwd_cpu, 1),
      forward_backward_cpu_ms=round(fb_cpu, 1),
      compile_forward_s=round(fwd_compile, 2),
      compile_forward_backward_s=round(fb_compile, 2),
      backward_over_forward=round((fb_ms - fwd_ms) / fwd_ms, 2),
      num_overflow=int(out.num_overflow),
      max_tile_count=int(out.max_tile_count),
      load_average=os.getloadavg()[0])
  if custom:
    proj = project.project(params, alive, cam, near=cfg.near, sh_degree=0)
    result.update(rasterize.blend_stats(proj, cam, cfg))
  return result


def main(argv):
  del argv
  for size in _SIZES.value:
    width, height = (int(s) for s in size.split("x"))
    for n in (int(float(x)) for x in _NUM.value):
      for variant in _VARIANTS.value:
        print(json.dumps(bench(n, width, height, variant)), flush=True)


if __name__ == "__main__":
  cli.run(main)
