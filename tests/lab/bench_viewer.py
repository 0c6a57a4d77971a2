"""Viewer start time and headless-Chromium frame rate on a large run.

  python tests/lab/bench_viewer.py --like=RUN --out=DIR [--gaussians=200000]

Writes DIR, a run folder with --gaussians random Gaussians (checkpoint.npz
with guided statistics, point_cloud.ply, pruned.ply) and RUN's run.json and
config.json (so its scene and cameras), then times experiments/view.py from
its start to its ready line (three times; wall and the CPU time of the
process, stopped at that line) and counts the frames the
headless browser draws per second while it orbits. Prints one JSON line.
Not a test: a measurement for BUILD_NOTES ("Viewer and logs").
"""

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time

import numpy as np

import browser
from clipgs_jax import checkpoint
from clipgs_jax import config_file
from clipgs_jax import gaussians
from clipgs_jax import ply
from clipgs_jax import run as run_lib
from clipgs_jax import sh
from clipgs_jax import state as state_lib
from clipgs_jax import train

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__))))


def fake_run(like: str, out: str, num: int, seed: int = 0) -> None:
  """A run folder like `like`'s with `num` random Gaussians around its
  own, random guided statistics and num // 50 pruned rows."""
  os.makedirs(out, exist_ok=True)
  for name in (run_lib.RUN_JSON, run_lib.CONFIG_JSON):
    shutil.copy(os.path.join(like, name), out)
  with open(os.path.join(out, run_lib.CONFIG_JSON)) as f:
    cfg = config_file.from_dict(json.load(f))
  like_means = np.asarray(ply.read_ply(
      os.path.join(like, run_lib.POINT_CLOUD_PLY))[0].means)
  rng = np.random.default_rng(seed)
  spread = np.std(like_means, axis=0)

  def params(n):
    f = lambda *s: rng.normal(size=s).astype(np.float32)
    means = (like_means[rng.integers(len(like_means), size=n)]
             + 0.05 * spread * f(n, 3))
    return gaussians.GaussianParams(
        means=means.astype(np.float32),
        log_scales=np.log(0.01 * cfg.scene_extent) + 0.5 * f(n, 3),
        quats=f(n, 4), opacity_logits=1.5 * f(n),
        sh_dc=sh.rgb_to_dc(rng.uniform(size=(n, 3))).astype(np.float32),
        sh_rest=np.zeros((n, sh.num_rest_coeffs(cfg.gaussians.sh_degree),
                          3), np.float32))

  p = params(num)
  state = train.init_state(cfg, p, np.ones(num, bool))
  weight = rng.uniform(0, 10, num).astype(np.float32)
  state = state.replace(semantic=state_lib.SemanticStats(
      acc=weight * rng.beta(0.5, 3, num).astype(np.float32), weight=weight,
      n=weight))
  checkpoint.save(os.path.join(out, train.CHECKPOINT_NAME), state, cfg)
  ply.write_ply(os.path.join(out, run_lib.POINT_CLOUD_PLY), p,
                np.ones(num, bool))
  ply.write_ply(os.path.join(out, run_lib.PRUNED_PLY), params(num // 50),
                np.ones(num // 50, bool))


def start_viewer(run: str, port: int):
  """(process, seconds from start to its ready line)."""
  tic = time.monotonic()
  proc = subprocess.Popen(
      [sys.executable, "experiments/view.py", f"--run={run}",
       f"--port={port}"], cwd=ROOT, stdout=subprocess.PIPE,
      stderr=subprocess.DEVNULL, text=True,
      env=dict(os.environ, PYTHONPATH=ROOT))
  line = proc.stdout.readline()
  if "viewer: serving" not in line:
    raise RuntimeError(f"the viewer did not start: {line!r}")
  return proc, time.monotonic() - tic


def main():
  parser = argparse.ArgumentParser()
  parser.add_argument("--like", required=True)
  parser.add_argument("--out", required=True)
  parser.add_argument("--gaussians", type=int, default=200_000)
  parser.add_argument("--port", type=int, default=8097)
  parser.add_argument("--seconds", type=float, default=10.0)
  parser.add_argument("--shares", default="1.0",
                      help="comma-separated shares drawn (the panel's "
                      "slider) to count frames at")
  args = parser.parse_args()
  if not os.path.exists(os.path.join(args.out, train.CHECKPOINT_NAME)):
    fake_run(args.like, args.out, args.gaussians)
  starts, cpu = [], []
  for _ in range(3):
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc, seconds = start_viewer(args.out, args.port)
    starts.append(seconds)
    proc.send_signal(2)              # Ctrl-C at once: CPU to its ready line
    proc.wait(timeout=60)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu.append(after.ru_utime + after.ru_stime - before.ru_utime
               - before.ru_stime)
  proc, _ = start_viewer(args.out, args.port)
  page = browser.Browser()
  try:
    tic = time.monotonic()
    page.open(f"http://127.0.0.1:{args.port}/?fixedDpr=1")
    page.wait_for_text("test (green)", 120)
    while page.drawn_frames() == 0:
      time.sleep(0.1)
    first = time.monotonic() - tic
    fps = {}
    for share in (float(x) for x in args.shares.split(",")):
      page.set_number("share drawn (most opaque)", share)
      time.sleep(5.0)
      fps[share] = page.frames_per_second(args.seconds)
    size = page.viewport()
  finally:
    page.close()
    proc.send_signal(2)
    proc.wait(timeout=60)
  print(json.dumps({"gaussians": args.gaussians, "start_seconds": starts,
                    "start_cpu_seconds": cpu,
                    "page_ready_seconds": first,
                    "orbit_fps": fps, "viewport": size,
                    "load_average": os.getloadavg()}))


if __name__ == "__main__":
  main()
