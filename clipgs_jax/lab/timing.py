"""Timings of the rasterizer, the train step and semantic guidance.

Each benchmark returns JSON-ready dicts (experiments/bench.py prints one
line each); BUILD_NOTES.md cites their fields. Wall and process-CPU times are
both reported: CPU time sums all threads and is not inflated by other
processes on a shared machine.
"""

import dataclasses
import os
import statistics
import time
from typing import Any, Callable, Iterator, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from clipgs_jax import camera
from clipgs_jax import checkpoint
from clipgs_jax import config as config_lib
from clipgs_jax import gaussians
from clipgs_jax import guidance
from clipgs_jax import losses
from clipgs_jax import optim
from clipgs_jax import step as step_lib
from clipgs_jax import train
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.render import blend
from clipgs_jax.render import project
from clipgs_jax.render import rasterize

# Stand-in of a densified model (and the frustum scene): opacity logit
# spread (mostly 0.05-0.95); the jitter of a resampled point, in units of
# its kNN scale.
STAND_IN_OPACITY_STD = 1.5
STAND_IN_JITTER = 0.5
# Frustum scene: focal length per image side (a ~64 degree field of view),
# depth range, spread of the log anisotropy and of the colours.
FRUSTUM_FOCAL = 0.8
FRUSTUM_DEPTH = (2.0, 8.0)
FRUSTUM_ANISOTROPY = 0.5
FRUSTUM_COLOR_STD = 0.5
# Step stages: the loss's D-SSIM weight (the paper's lambda = 0.2).
DSSIM_WEIGHT = 0.2
# Semantic overhead: every variant starts past the paper schedule's starts
# (accumulation, opacity loss), so the scorer and the loss run.
SEMANTIC_START_STEP = 5000


class Timing(NamedTuple):
  """What time_calls measured: the first call's output and seconds."""
  out: Any            # the first call's result
  first_s: float      # first call (compiles), seconds
  wall_s: list        # timed calls' wall seconds
  cpu_s: list         # timed calls' process CPU seconds

  def ms(self) -> dict[str, float]:
    """compile_s, median wall_ms and cpu_ms, rounded as reported."""
    return dict(compile_s=round(self.first_s, 2),
                wall_ms=round(1e3 * statistics.median(self.wall_s), 1),
                cpu_ms=round(1e3 * statistics.median(self.cpu_s), 1))


def time_calls(fn: Callable, *args, repeats: int, warmup: int = 0
               ) -> Timing:
  """Calls fn(*args) once (compiling), `warmup` times untimed, then
  `repeats` timed times, blocking on every result."""
  t0 = time.perf_counter()
  out = jax.block_until_ready(fn(*args))
  first = time.perf_counter() - t0
  for _ in range(warmup):
    jax.block_until_ready(fn(*args))
  wall, cpu = [], []
  for _ in range(repeats):
    t0, c0 = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn(*args))
    wall.append(time.perf_counter() - t0)
    cpu.append(time.process_time() - c0)
  return Timing(out, first, wall, cpu)


def time_steps(step: Callable, state, *args, repeats: int) -> Timing:
  """time_calls for step(state, *args) -> (state, out) that donates its
  state, as the training loop calls it: each call gets the state the
  previous one returned, so no call pays for fresh output buffers.
  Timing.out is the first call's `out`."""
  carry = [state]

  def call():
    carry[0], out = jax.block_until_ready(step(carry[0], *args))
    return out
  return time_calls(call, repeats=repeats)


def frustum_scene(n: int, width: int, height: int, r_lo: float, r_hi: float,
                  seed: int = 0):
  """N Gaussians in the view frustum with 3-sigma radii in [r_lo, r_hi] px.

  Returns:
    (GaussianParams, bool [N] alive, camera.Camera at the origin).
  """
  rng = np.random.default_rng(seed)
  focal = FRUSTUM_FOCAL * max(width, height)
  cam = camera.Camera.create(np.eye(3), np.zeros(3), focal, focal, width / 2,
                             height / 2, width, height)
  z = rng.uniform(*FRUSTUM_DEPTH, n)
  u = rng.uniform(0, width, n)
  v = rng.uniform(0, height, n)
  means = np.stack([(u - width / 2) * z / focal, (v - height / 2) * z / focal,
                    z], -1)
  radius = rng.uniform(r_lo, r_hi, n)
  sigma = radius / 3 * z / focal                      # world std dev
  aniso = np.exp(rng.uniform(-FRUSTUM_ANISOTROPY, FRUSTUM_ANISOTROPY,
                             (n, 3)))
  params = gaussians.GaussianParams(
      means=jnp.asarray(means, jnp.float32),
      log_scales=jnp.asarray(np.log(sigma[:, None] * aniso), jnp.float32),
      quats=jnp.asarray(rng.normal(size=(n, 4)), jnp.float32),
      opacity_logits=jnp.asarray(rng.normal(0.0, STAND_IN_OPACITY_STD, n),
                                 jnp.float32),
      sh_dc=jnp.asarray(rng.normal(0, FRUSTUM_COLOR_STD, (n, 3)),
                        jnp.float32),
      sh_rest=jnp.zeros((n, 0, 3), jnp.float32))
  return params, jnp.ones(n, bool), cam


def stand_in(params, alive, n: int, seed: int = 0):
  """`n` Gaussians resampled from the alive rows, as a densified model.

  The points are jittered by STAND_IN_JITTER x their scale and shrunk so
  that n rows cover the same volume; opacities are sigmoid(N(0,
  STAND_IN_OPACITY_STD)).
  """
  rng = np.random.default_rng(seed)
  rows = np.flatnonzero(np.asarray(alive))
  pick = rng.choice(rows, n)
  grow = (n / len(rows)) ** (1 / 3)       # same volume coverage at n rows
  scale = np.exp(np.asarray(params.log_scales)[pick])
  means = (np.asarray(params.means)[pick]
           + STAND_IN_JITTER * scale * rng.normal(size=(n, 3)))
  take = lambda x: jnp.asarray(np.asarray(x)[pick])
  out = gaussians.GaussianParams(
      means=jnp.asarray(means, jnp.float32),
      log_scales=jnp.asarray(np.log(scale / grow), jnp.float32),
      quats=jnp.asarray(rng.normal(size=(n, 4)), jnp.float32),
      opacity_logits=jnp.asarray(rng.normal(0, STAND_IN_OPACITY_STD, n),
                                 jnp.float32),
      sh_dc=take(params.sh_dc), sh_rest=take(params.sh_rest))
  return out, jnp.ones(n, bool)


def _peak_bytes(fn, *args):
  mem = fn.lower(*args).compile().memory_analysis()
  if mem is None:
    return None
  return int(mem.temp_size_in_bytes + mem.argument_size_in_bytes
             + mem.output_size_in_bytes)


def _budget(params, alive, cam, chunk_size: int, tile_size: int) -> int:
  """Smallest power of two >= the longest tile list of this scene."""
  probe = config_lib.RenderConfig(tile_budget=1 << 15, chunk_size=chunk_size,
                                  tile_size=tile_size)
  proj = project.project(params, alive, cam, near=probe.near, sh_degree=0)
  longest = int(rasterize.rasterize(proj, cam, jnp.zeros(3),
                                    probe).max_tile_count)
  return max(chunk_size, 1 << max(longest - 1, 1).bit_length())


def rasterizer(n: int, width: int, height: int, variant: str, *,
               radius_px: tuple[float, float], tile_budget: int = 0,
               chunk_size: int = 32, lanes: int = 0,
               tile_size: int = config_lib.RenderConfig.tile_size,
               repeats: int = 5, max_gib: float = 12.0) -> dict:
  """The tile rasterizer's forward and forward + backward on frustum_scene.

  Args:
    variant: "custom_vjp" or "autodiff" (plain autodiff of the forward).
    radius_px: (lo, hi), range of projected 3-sigma radii, pixels.
    tile_budget: K; 0 = the smallest power of two >= the scene's longest
      tile list, the same for both variants.
    max_gib: a variant whose compiled forward + backward needs more memory
      is not run (its estimate is still returned, with "skipped").
  Returns:
    forward / forward+backward median wall and CPU ms, compile seconds,
    backward / forward, XLA's peak buffer estimate, tile overflow, the
    longest tile list and (custom VJP) rasterize.blend_stats.
  """
  params, alive, cam = frustum_scene(n, width, height, *radius_px)
  budget = tile_budget or _budget(params, alive, cam, chunk_size, tile_size)
  cfg = config_lib.RenderConfig(tile_budget=budget, chunk_size=chunk_size,
                                lanes=lanes, tile_size=tile_size)
  bg = jnp.zeros(3)
  custom = variant == "custom_vjp"

  def forward(p):
    proj = project.project(p, alive, cam, near=cfg.near, sh_degree=0)
    return rasterize.rasterize(proj, cam, bg, cfg, custom_vjp=custom)

  fwd = jax.jit(lambda p: forward(p).image)
  grad = jax.jit(jax.grad(lambda p: jnp.mean(forward(p).image)))
  result = dict(n=n, width=width, height=height, variant=variant,
                tile_budget=budget, chunk_size=cfg.chunk_size,
                backend=jax.default_backend())
  t0 = time.perf_counter()
  peak = _peak_bytes(grad, params)        # compiles forward + backward
  fb_compile = time.perf_counter() - t0
  result["peak_bytes_fwd_bwd"] = peak
  if peak is not None and peak > max_gib * 2**30:
    result["skipped"] = f"needs {peak / 2**30:.1f} GiB > --max_gib"
    return result
  out = jax.jit(forward)(params)
  f = time_calls(fwd, params, repeats=repeats)
  fb = time_calls(grad, params, repeats=repeats)
  fwd_ms, fb_ms = (1e3 * statistics.median(t.wall_s) for t in (f, fb))
  result.update(
      forward_ms=round(fwd_ms, 1), forward_backward_ms=round(fb_ms, 1),
      forward_cpu_ms=f.ms()["cpu_ms"], forward_backward_cpu_ms=fb.ms()[
          "cpu_ms"],
      compile_forward_s=f.ms()["compile_s"],
      compile_forward_backward_s=round(fb_compile, 2),
      backward_over_forward=round((fb_ms - fwd_ms) / fwd_ms, 2),
      num_overflow=int(out.num_overflow),
      max_tile_count=int(out.max_tile_count),
      load_average=os.getloadavg()[0])
  if custom:
    proj = project.project(params, alive, cam, near=cfg.near, sh_degree=0)
    result.update(rasterize.blend_stats(proj, cam, cfg))
  return result


def step_stages(cfg: config_lib.Config, scene, params, alive, view: int,
                repeats: int) -> dict:
  """One training step on training view `view` of `scene`, stage by stage
  (the jitted train step draws its own views).

  Returns:
    {stage: {compile_s, wall_ms, cpu_ms}} for project_fwd,
    project_fwd_bwd, bin_sort, blend_fwd, blend_bwd, loss_fwd_bwd, adam
    and the jitted train_step; plus the image size, overflow, the longest
    tile list and rasterize.blend_stats.
  """
  state = train.init_state(cfg, params, alive)
  cam = camera.camera_at(scene.train.cameras, view)
  target = jnp.asarray(scene.train.images[view], jnp.float32)
  rcfg = cfg.render
  grid = blend.Grid(int(cam.width), int(cam.height), rcfg.tile_budget,
                    rcfg.chunk_size, rcfg.lanes, rcfg.tile_size)
  result = dict(n=int(np.sum(np.asarray(alive))), capacity=int(alive.shape[0]),
                width=int(cam.width), height=int(cam.height),
                tile_budget=rcfg.tile_budget, chunk_size=rcfg.chunk_size)

  def timed(name, fn, *args, timer=time_calls):
    t = timer(fn, *args, repeats=repeats)
    result[name] = t.ms()
    return t.out

  def proj_fn(p):
    return project.project(p, state.alive, cam, near=rcfg.near, sh_degree=0)

  proj = timed("project_fwd", jax.jit(proj_fn), state.params)
  timed("project_fwd_bwd", jax.jit(lambda p: jax.vjp(proj_fn, p)[1](proj)),
        state.params)
  # pylint: disable=protected-access
  gauss, start, count, overflow, max_count = timed(
      "bin_sort", jax.jit(lambda q: rasterize._bin(q, grid)), proj)
  tables = (gauss, start, count)
  pix, inside = rasterize._pixel_centers(grid, jnp.float32)
  # pylint: enable=protected-access
  splats = (proj.means2d, proj.conics, proj.colors, proj.opacities,
            proj.depths)
  fwd = jax.jit(lambda s, tb: blend.forward(grid, s, tb, pix, inside, None))
  color, depth, trans, n_contrib, _, _, _ = timed("blend_fwd", fwd, splats,
                                                  tables)
  rng = np.random.default_rng(0)
  cot = (jnp.asarray(rng.normal(size=color.shape), jnp.float32),
         jnp.asarray(rng.normal(size=depth.shape), jnp.float32),
         jnp.asarray(rng.normal(size=trans.shape), jnp.float32))
  bwd = jax.jit(lambda s, tb, *a: blend.backward(grid, s, tb, pix, *a))
  timed("blend_bwd", bwd, splats, tables, color, depth, trans, n_contrib,
        *cot)
  timed("loss_fwd_bwd", jax.jit(jax.grad(
      lambda x: losses.photometric(x, target, DSSIM_WEIGHT)[0])),
        jnp.zeros(target.shape))
  # Adam and the train step donate their state as the training loop does;
  # without donation each call also faults in fresh output pages (Adam at
  # 262k rows: 194 ms against 30 ms on the 2-core box; BUILD_NOTES.md,
  # "Training").
  tx = optim.for_run(cfg)

  def adam(carry, grads):
    updates, opt_state = tx.update(grads, carry[1], carry[0])
    return (optax.apply_updates(carry[0], updates), opt_state), None
  copy = lambda tree: jax.tree.map(jnp.copy, tree)
  timed("adam", jax.jit(adam, donate_argnums=(0,)),
        copy((state.params, state.opt_state)), state.params,
        timer=time_steps)
  # A copy: `state` shares its arrays with the caller's, which may time the
  # same state again (one sample per count with --checkpoint).
  step_fn, lanes, step_state, _ = step_lib.for_scene(cfg, scene,
                                                     copy(state))
  timed("train_step", step_fn, step_state, lanes, None, timer=time_steps)
  result.update(num_overflow=int(overflow), max_tile_count=int(max_count))
  result.update(rasterize.blend_stats(proj, cam, rcfg))
  return result


def train_step(scene_path: str, downscale: int, counts: list[int], *,
               render: config_lib.RenderConfig, view: int = 0,
               checkpoint_path: str | None = None, repeats: int = 3
               ) -> Iterator[dict]:
  """step_stages at each alive count on a real scene; one dict per count.

  A count of 0 is the SfM points as loaded (the step-0 state); a larger
  one is a stand_in of that size; with checkpoint_path its trained state
  replaces both.
  """
  scene = scene_lib.load_scene(scene_path, downscale=downscale)
  cfg = train.resolve(config_lib.Config(render=render), scene)
  base = train.initial_state(cfg, scene)
  if checkpoint_path:
    if not os.path.exists(checkpoint_path):
      raise FileNotFoundError(f"--checkpoint {checkpoint_path} not found.")
    base = checkpoint.restore(checkpoint_path, base)[0]
  for n in counts:
    if n == 0 or checkpoint_path:
      params, alive = base.params, base.alive
    else:
      params, alive = stand_in(base.params, base.alive, n)
    result = step_stages(cfg, scene, params, alive, view, repeats)
    result.update(load_average=os.getloadavg()[0], scene=scene_path,
                  downscale=downscale, view=view,
                  source="checkpoint" if checkpoint_path else
                  ("sfm_points" if n == 0 else "stand_in"))
    yield result


def semantic_overhead(scene_path: str, downscale: int, *,
                      score_every: list[int], steps: int, clip_variant: str,
                      tile_budget: int, checkpoint_path: str | None = None
                      ) -> list[dict]:
  """Step time of semantic guidance against the vanilla step.

  Times, in one process on the same state and views, the jitted train step
  of: vanilla (guidance off); oracle and oracle_pixel (the ground-truth
  masks as the paper's image-level score, and as a per-pixel map with loss
  masking; scenes with masks only); residual and residual+features (the
  residual map with loss masking, per pixel and voted over the photos'
  feature regions; the regions are computed before timing, once per
  photo); learned (the learned map, its features computed before timing); clip/k=K (CLIP scorer with random weights, scoring every K-th
  step). Every guided variant scores every step with the opacity loss on.
  Each is compiled and warmed up over one full scoring cycle, then timed
  round-robin (one step each in turn, so a change in load shifts them all
  alike) for `steps` steps.

  Returns:
    One dict per variant: mean wall / CPU ms per step and the overhead
    over vanilla.
  """
  scene = scene_lib.load_scene(scene_path, downscale=downscale)
  base = config_lib.Config()
  base = dataclasses.replace(base, render=dataclasses.replace(
      base.render, tile_budget=tile_budget))
  base = train.resolve(base, scene)
  state0 = train.initial_state(base, scene)
  if checkpoint_path:
    state0, _ = checkpoint.restore(checkpoint_path, state0)
  state0 = state0.replace(step=jnp.int32(SEMANTIC_START_STEP))

  from clipgs_jax.clip import model  # pylint: disable=g-import-not-at-top
  clip_config = model.get_config(clip_variant)
  clip_params = (clip_config,
                 model.init_params(clip_config, jax.random.key(0)))
  variants = {"vanilla": (base, None)}
  sem = dataclasses.replace(base.semantic, scorer="oracle",
                            accumulate_start=0, reg_start=0)
  if scene.train.masks is not None:
    cfg = dataclasses.replace(base, semantic=sem)
    variants["oracle"] = (cfg, guidance.make_scorer(cfg, scene))
    cfg = dataclasses.replace(
        base, semantic=dataclasses.replace(sem, evidence="pixel"),
        pixel=dataclasses.replace(base.pixel, loss_masking=True))
    variants["oracle_pixel"] = (cfg, guidance.make_scorer(cfg, scene))
  scorer_s = {}
  for name, kind, net in (("residual", "residual", ""),
                          ("residual+features", "residual", "alex"),
                          ("learned", "learned", "")):
    cfg = dataclasses.replace(
        base, semantic=dataclasses.replace(sem, scorer=kind,
                                           evidence="pixel"),
        pixel=dataclasses.replace(base.pixel, loss_masking=True),
        residual=dataclasses.replace(base.residual, features=net))
    tic = time.perf_counter()
    variants[name] = (cfg, guidance.make_scorer(cfg, scene))
    scorer_s[name] = time.perf_counter() - tic
  for k in score_every:
    cfg = dataclasses.replace(base, semantic=dataclasses.replace(
        sem, scorer="clip", clip_variant=clip_variant, score_every=k))
    variants[f"clip/k={k}"] = (cfg, guidance.make_scorer(
        cfg, scene, clip_params=clip_params))

  fns, states, compile_s = {}, {}, {}
  for name, (cfg, scorer) in variants.items():
    state = jax.tree.map(jnp.copy, state0)
    if cfg.uses_residual:
      state = state.replace(maps=train.initial_state(cfg, scene).maps)
    fn, lanes, state, scorer = step_lib.for_scene(cfg, scene, state, scorer)
    tic = time.perf_counter()
    state, _ = jax.block_until_ready(fn(state, lanes, scorer))
    compile_s[name] = time.perf_counter() - tic
    for _ in range(max(score_every)):
      state, _ = fn(state, lanes, scorer)
    fns[name] = lambda s, fn=fn, lanes=lanes, scorer=scorer: fn(s, lanes,
                                                               scorer)
    states[name] = jax.block_until_ready(state)

  wall = {n: [] for n in variants}
  cpu = {n: [] for n in variants}
  for _ in range(steps):
    for name, fn in fns.items():
      tic, cpu_tic = time.perf_counter(), time.process_time()
      states[name], _ = jax.block_until_ready(fn(states[name]))
      wall[name].append((time.perf_counter() - tic) * 1e3)
      cpu[name].append((time.process_time() - cpu_tic) * 1e3)

  h, w = scene.train.images.shape[1:3]
  ref_wall = statistics.fmean(wall["vanilla"])
  ref_cpu = statistics.fmean(cpu["vanilla"])
  out = []
  for name in variants:
    mw, mc = statistics.fmean(wall[name]), statistics.fmean(cpu[name])
    out.append({
        "variant": name, "scene": scene_path, "image": [w, h],
        "num_gaussians": int(state0.alive.sum()),
        "capacity": state0.capacity, "steps": steps,
        "mean_wall_ms": round(mw, 1), "mean_cpu_ms": round(mc, 1),
        "overhead_wall": round(mw / ref_wall - 1, 4),
        "overhead_cpu": round(mc / ref_cpu - 1, 4),
        "compile_s": round(compile_s[name], 1),
        # Building the scorer (regions, the learned map's features), per
        # training photo, compile included.
        "scorer_s_per_photo": (round(scorer_s[name] / len(scene.train.images),
                                     3) if name in scorer_s else None),
        "clip": clip_variant if name.startswith("clip") else None,
        "device": jax.devices()[0].device_kind})
  return out
