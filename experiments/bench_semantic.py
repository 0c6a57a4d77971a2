"""Step-time overhead of semantic guidance over the vanilla 3DGS step.

  python experiments/bench_semantic.py [--scene=DIR --downscale=K]
      [--checkpoint=RUN/checkpoint.npz] [--score_every=1,10,20]
      [--steps=20] [--clip_variant=ViT-B/32]

Times, in one process on the same state and views, the jitted train step
  vanilla       guidance off (the step experiments/train.py runs by default)
  off           --semantic=clip with no distractor prompts: disabled
  oracle        oracle scorer, scoring every step, opacity loss on
  clip/k=K      CLIP scorer (random weights: timing only), scoring every
                K-th step, opacity loss on
and prints one JSON line per variant with the mean wall and process-CPU
milliseconds per step over --steps steps (the mean, so that every k-th
step's scoring is amortised; --steps should be a multiple of every k), after
compilation and a warm-up of one full scoring cycle, and the overhead over
vanilla. The variants are
timed round-robin, one step each in turn, so a change in machine load
shifts them all alike. The state is the scene's initial one, or a trained
one from --checkpoint (the Gaussian count sets the step time).
"""

import dataclasses
import json
import statistics
import time

from absl import flags
import jax
import jax.numpy as jnp

from clipgs_jax import checkpoint
from clipgs_jax import cli
from clipgs_jax import config as config_lib
from clipgs_jax import guidance
from clipgs_jax import train
from clipgs_jax.data import default_scene
from clipgs_jax.data import scene as scene_lib

_SCENE = flags.DEFINE_string("scene", None, "Scene folder; default: the "
                             "embedded scene.")
_DOWNSCALE = flags.DEFINE_integer("downscale", 1, "Image downscale factor.")
_CHECKPOINT = flags.DEFINE_string(
    "checkpoint", None, "A train.py checkpoint.npz of this scene to time "
    "the step at its Gaussian count (default: the initial state).")
_SCORE_EVERY = flags.DEFINE_list("score_every", ["1", "10", "20"],
                                 "CLIP scoring cadences to time.")
_STEPS = flags.DEFINE_integer("steps", 40, "Timed steps per variant.")
_CLIP_VARIANT = flags.DEFINE_string("clip_variant", "ViT-B/32",
                                    "CLIP tower (random weights).")
_TILE_BUDGET = flags.DEFINE_integer("tile_budget", 8192,
                                    "RenderConfig.tile_budget.")


def main(argv):
  del argv
  path = _SCENE.value or default_scene.ensure_default_scene()
  scene = scene_lib.load_scene(path, downscale=_DOWNSCALE.value)
  base = config_lib.Config()
  base = dataclasses.replace(base, render=dataclasses.replace(
      base.render, tile_budget=_TILE_BUDGET.value))
  base = train.resolve(base, scene)
  state0 = train.initial_state(base, scene)
  if _CHECKPOINT.value:
    state0, _ = checkpoint.restore(_CHECKPOINT.value, state0)
  # Every variant starts past the semantic schedule's starts, so the
  # scorer and the opacity loss run.
  state0 = state0.replace(step=jnp.int32(5000))
  batch = train.make_batch(scene.train)

  from clipgs_jax.clip import model  # pylint: disable=g-import-not-at-top
  clip_config = model.get_config(_CLIP_VARIANT.value)
  clip_params = (clip_config,
                 model.init_params(clip_config, jax.random.key(0)))
  # "off": guidance configured but disabled (no distractor prompts); the
  # same program as vanilla, timed to show it costs the same.
  off = dataclasses.replace(base, semantic=dataclasses.replace(
      base.semantic, scorer="clip", distractor_prompts=()))
  variants = {"vanilla": (base, None), "off": (off, None)}
  sem = dataclasses.replace(base.semantic, scorer="oracle",
                            accumulate_start=0, reg_start=0)
  if scene.train.masks is not None:
    cfg = dataclasses.replace(base, semantic=sem)
    variants["oracle"] = (cfg, guidance.make_scorer(cfg.semantic, scene))
  for k in (int(x) for x in _SCORE_EVERY.value):
    cfg = dataclasses.replace(base, semantic=dataclasses.replace(
        sem, scorer="clip", clip_variant=_CLIP_VARIANT.value, score_every=k))
    variants[f"clip/k={k}"] = (cfg, guidance.make_scorer(
        cfg.semantic, scene, clip_params=clip_params))

  steps, states = {}, {}
  warmup = max(int(x) for x in _SCORE_EVERY.value)
  for name, (cfg, scorer) in variants.items():
    fn = jax.jit(lambda s, b, sc, cfg=cfg: train.train_step(s, b, sc,
                                                            cfg=cfg))
    state = jax.tree.map(jnp.copy, state0)
    tic = time.perf_counter()
    state, _ = jax.block_until_ready(fn(state, batch, scorer))
    compile_s = time.perf_counter() - tic
    for _ in range(warmup):
      state, _ = fn(state, batch, scorer)
    steps[name] = (fn, scorer, compile_s)
    states[name] = jax.block_until_ready(state)

  wall = {n: [] for n in variants}
  cpu = {n: [] for n in variants}
  for _ in range(_STEPS.value):
    for name, (fn, scorer, _) in steps.items():
      tic, cpu_tic = time.perf_counter(), time.process_time()
      states[name], _ = jax.block_until_ready(
          fn(states[name], batch, scorer))
      wall[name].append((time.perf_counter() - tic) * 1e3)
      cpu[name].append((time.process_time() - cpu_tic) * 1e3)

  h, w = scene.train.images.shape[1:3]
  ref_wall = statistics.fmean(wall["vanilla"])
  ref_cpu = statistics.fmean(cpu["vanilla"])
  for name in variants:
    mw, mc = statistics.fmean(wall[name]), statistics.fmean(cpu[name])
    print(json.dumps({
        "variant": name, "scene": path, "image": [w, h],
        "num_gaussians": int(state0.alive.sum()),
        "capacity": state0.capacity, "steps": _STEPS.value,
        "mean_wall_ms": round(mw, 1), "mean_cpu_ms": round(mc, 1),
        "overhead_wall": round(mw / ref_wall - 1, 4),
        "overhead_cpu": round(mc / ref_cpu - 1, 4),
        "compile_s": round(steps[name][2], 1),
        "clip": _CLIP_VARIANT.value if name.startswith("clip") else None,
        "device": jax.devices()[0].device_kind}))


if __name__ == "__main__":
  cli.run(main)
