"""Views per second of a batch of views per step, on one or more devices.

experiments/bench.py --bench=views: the train step at batch sizes B on
mesh sizes D, all in one process on the same state (the scene's step-0
state, or a stand-in of a densified model) and the same views. Every
variant is compiled and warmed up first, then the variants are timed
round-robin (a turn each, so a change in the machine's load shifts them
all alike), two ways: each step waited for before the next is dispatched,
and `chunk` steps dispatched back to back with one wait at the end, as
the training loop (loop.py) runs them, so that the host's dispatch of a
step overlaps the devices' work on the one before. Wall and process-CPU
times are both reported: CPU time sums every thread, so on a shared
machine it shows what the step costs when wall time only shows what it
got.
"""

import dataclasses
import os
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import config as config_lib
from clipgs_jax import sharding
from clipgs_jax import step as step_lib
from clipgs_jax import train
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.lab import timing


def views_per_second(scene_path: str, downscale: int, *,
                     variants: list[tuple[int, int]], steps: int,
                     render: config_lib.RenderConfig,
                     num_gaussians: int = 0, warmup: int = 2,
                     chunk: int = 10,
                     vmap_lanes: bool | None = None) -> list[dict]:
  """Times the train step of each (B, D) variant.

  Each is the train step (step.py) on the first D devices.

  Args:
    scene_path, downscale: the scene (a folder or pack).
    variants: (batch size B, devices D) pairs, D dividing B.
    steps: timed steps per variant and way (rounded up to chunks).
    render: the rasterizer settings.
    num_gaussians: 0 for the scene's step-0 state, else a stand-in with
      this many Gaussians (timing.stand_in).
    warmup: untimed steps after the compiling one.
    chunk: steps dispatched back to back in the second way.
    vmap_lanes: how a device renders its lanes (step.make_train_step;
      None: step.lanes_vmapped).
  Returns:
    One dict per variant: lanes (how its step runs: one lane a device,
    vmap or scan); compile_s (the first step); mean wall
    and CPU ms per step, views per second of wall time and per CPU
    second, each step waited for; the same "..._pipelined", steps back
    to back; the load average before and after.
  """
  load_before = os.getloadavg()[0]
  scene = scene_lib.load_scene(scene_path, downscale=downscale)
  base = train.resolve(config_lib.Config(render=render), scene)
  state0 = train.initial_state(base, scene)
  if num_gaussians:
    params, alive = timing.stand_in(state0.params, state0.alive,
                                    num_gaussians)
    state0 = train.init_state(base, params, alive)
  fns, data, states, compile_s, how = {}, {}, {}, {}, {}
  for size, count in variants:
    name = f"B={size} D={count}"
    cfg = dataclasses.replace(base, train=dataclasses.replace(
        base.train, batch_size=size))
    state = jax.tree.map(jnp.copy, state0)
    mesh = sharding.make_mesh(size, jax.devices()[:count])
    vmap = (step_lib.lanes_vmapped(mesh) if vmap_lanes is None
            else vmap_lanes)
    fn = step_lib.make_train_step(cfg, mesh, vmap)
    views, _ = sharding.lanes_of(scene, size, mesh)
    how[name] = ("one lane" if size == count
                 else "vmap" if vmap else "scan")
    state = sharding.replicate(state, mesh)
    tic = time.perf_counter()
    state, _ = jax.block_until_ready(fn(state, views, None))
    compile_s[name] = time.perf_counter() - tic
    for _ in range(warmup):
      state, _ = fn(state, views, None)
    fns[name], data[name], states[name] = fn, views, jax.block_until_ready(
        state)
  ways = {"": 1, "_pipelined": chunk}  # steps dispatched before a wait
  wall = {(n, way): [] for n in fns for way in ways}
  cpu = {(n, way): [] for n in fns for way in ways}
  for _ in range(-(-steps // chunk)):
    for name, fn in fns.items():
      for way, run in ways.items():
        for _ in range(chunk // run):
          tic, cpu_tic = time.perf_counter(), time.process_time()
          state = states[name]
          for _ in range(run):
            state, metrics = fn(state, data[name], None)
          states[name] = jax.block_until_ready((state, metrics))[0]
          wall[name, way].append((time.perf_counter() - tic) / run)
          cpu[name, way].append((time.process_time() - cpu_tic) / run)
  load_after = os.getloadavg()[0]
  h, w = scene.train.images.shape[1:3]
  ref = None
  out = []
  for (size, count), name in zip(variants, fns):
    row = {
        "variant": name, "batch_size": size, "devices": count,
        "lanes": how[name],
        "scene": scene_path, "downscale": downscale, "image": [w, h],
        "num_gaussians": int(np.sum(np.asarray(state0.alive))),
        "steps": len(wall[name, ""]), "chunk": chunk,
        "compile_s": round(compile_s[name], 1),
        "load_before": load_before, "load_after": load_after,
        "device": jax.devices()[0].device_kind,
        "host_cores": os.cpu_count()}
    for way in ways:
      mw = statistics.fmean(wall[name, way])
      mc = statistics.fmean(cpu[name, way])
      row.update({f"mean_wall_ms{way}": round(1e3 * mw, 1),
                  f"mean_cpu_ms{way}": round(1e3 * mc, 1),
                  f"views_per_s{way}": round(size / mw, 3),
                  f"views_per_cpu_s{way}": round(size / mc, 3)})
    ref = ref or row
    for way in ways:
      row[f"speedup_wall{way}"] = round(
          row[f"views_per_s{way}"] / ref[f"views_per_s{way}"], 3)
      row[f"speedup_cpu{way}"] = round(
          row[f"views_per_cpu_s{way}"] / ref[f"views_per_cpu_s{way}"], 3)
    out.append(row)
  return out
