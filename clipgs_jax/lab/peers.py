"""Whole training runs of JAX 3DGS peers beside ours, scored by our metrics.

`experiments/bench.py --bench=peers --peers=DIR` trains vanilla 3DGS with
our code and with each peer whose sources a user has put under DIR, on the
same scene, training views, downscale, SfM points and step count, and
scores every run's test views with our metrics (clipgs_jax/metrics.py) at
the same steps, every CURVE_EVERY. The peers' code stays out of this
repository: it is loaded from DIR at run time, as
../shared/bench_peers/README.md lays it out (a peer's HEAD written into
DIR/<folder>).

Peers (PEERS):
  ghif: ghif/jax-gs (pure JAX), in DIR/ghif-jax-gs. Its trainer,
    `train.run_training`, runs in this process with its own defaults
    (initial log-scales -3, learning rates, densification every 500 steps
    to 15k, opacity reset every 3k, one more SH band every 1k while its
    tile buffers are healthy, 100 steps a compiled block) on a COLMAP
    folder written from our loaded scene (`write_colmap`): the training
    views only, our photos (downscaled, undistorted) as PNG, PINHOLE
    cameras with our intrinsics, our SfM points. Its trainer takes the
    first view's intrinsics for every view and the image centre as the
    principal point. Its snapshots (every 1,000 steps) are kept in memory
    and rendered after training by its renderer on our test cameras, on
    its black background. Seconds count from the end of its data loading
    (compilation included), as ours count the training loop.
"""

import contextlib
import functools
import importlib.util
import os
import random
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
from matplotlib import figure
import numpy as np

from clipgs_jax import config_file
from clipgs_jax import fileio
from clipgs_jax import metrics as metrics_lib
from clipgs_jax import plots
from clipgs_jax import run as run_lib
from clipgs_jax.data import images as images_lib
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.lab import table

PEERS = {"ghif": "ghif-jax-gs"}
# Files that must exist in a peer's folder for its run.
_NEEDS = {"ghif": ("train.py", "jax_gs/renderer/renderer.py")}
CURVE_EVERY = 1000          # the ghif trainer's snapshot cadence
PEERS_JSON = "peers.json"
PEERS_PNG = "peers.png"


def missing(peers_dir: str, names) -> list[str]:
  """One line for each peer in `names` whose sources are not in
  `peers_dir`, naming the folder and how to fill it."""
  out = []
  for name in names:
    if name not in PEERS:
      out.append(f"{name}: not a peer; choose from {', '.join(PEERS)}")
      continue
    folder = os.path.join(peers_dir, PEERS[name])
    for f in _NEEDS[name]:
      if not os.path.exists(os.path.join(folder, f)):
        out.append(f"{name}: {os.path.join(folder, f)} is missing; write "
                   f"the peer's HEAD into {folder} as ../shared/bench_peers/"
                   "README.md says")
        break
  return out


def write_colmap(views, points: np.ndarray, colours: np.ndarray,
                 folder: str) -> None:
  """A COLMAP folder of `views` (data.scene.Views, one canvas size):
  sparse/0 (binary, written by pycolmap: a PINHOLE camera per view, no 2D
  observations or tracks) and images/NNNNN.png, view i as i (names
  without RobustNeRF's split words)."""
  import pycolmap  # pylint: disable=import-outside-toplevel  # see colmap.py
  cams = views.cameras
  w, h = int(cams.width), int(cams.height)
  rec = pycolmap.Reconstruction()
  names = [f"{i:05d}.png" for i in range(len(views))]
  for i, name in enumerate(names):
    rec.add_camera_with_trivial_rig(pycolmap.Camera(
        camera_id=i + 1, model="PINHOLE", width=w, height=h,
        params=[cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]]))
    pose = pycolmap.Rigid3d(
        pycolmap.Rotation3d(np.asarray(cams.rotation[i], np.float64)),
        np.asarray(cams.translation[i], np.float64))
    rec.add_image_with_trivial_frame(
        pycolmap.Image(name=name, camera_id=i + 1, image_id=i + 1), pose)
  rgb = np.clip(np.round(np.asarray(colours) * 255), 0, 255).astype(np.uint8)
  for p, c in zip(np.asarray(points, np.float64), rgb):
    rec.add_point3D(p, pycolmap.Track(), c)
  sparse = os.path.join(folder, "sparse", "0")
  os.makedirs(sparse, exist_ok=True)
  rec.write_binary(sparse)
  os.makedirs(os.path.join(folder, "images"), exist_ok=True)
  for name, photo in zip(names, views.images):
    images_lib.write_png(os.path.join(folder, "images", name), photo)


def _load_ghif(peers_dir: str):
  """The ghif trainer module and its renderer's (Gaussians, Camera,
  render), imported from the peer's folder."""
  folder = os.path.join(peers_dir, PEERS["ghif"])
  if folder not in sys.path:
    sys.path.insert(0, folder)
  spec = importlib.util.spec_from_file_location(
      "ghif_train", os.path.join(folder, "train.py"))
  trainer = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(trainer)
  from jax_gs.core import camera  # pylint: disable=g-import-not-at-top
  from jax_gs.core import gaussians  # pylint: disable=g-import-not-at-top
  from jax_gs.renderer import renderer  # pylint: disable=g-import-not-at-top
  return trainer, gaussians.Gaussians, camera.Camera, renderer.render


def train_ghif(scene, peers_dir: str, steps: int, seed: int, log: str):
  """Runs the ghif trainer for `steps` on `scene`'s training views.

  Returns:
    [(step, seconds, {name: numpy array} of its active Gaussians,
    SH degree)] at every CURVE_EVERY steps, the last at `steps`.
  """
  trainer, _, _, _ = _load_ghif(peers_dir)
  snaps, clock = [], {}

  def loaded(*args, **kwargs):
    out = load(*args, **kwargs)
    clock["start"] = time.perf_counter()
    return out

  def snapshot(gaussians, iteration, *unused_args):
    snaps.append((iteration, time.perf_counter() - clock["start"],
                  gaussians, unused_args[-1]))

  load = trainer.load_colmap_dataset
  trainer.load_colmap_dataset = loaded
  trainer.save_artifacts_task = snapshot
  trainer.save_ply = lambda *unused: None
  with tempfile.TemporaryDirectory() as tmp:
    write_colmap(scene.train, scene.points, scene.point_colors,
                 os.path.join(tmp, "scene"))
    random.seed(seed)
    with open(log, "w") as f, contextlib.redirect_stdout(f), \
        contextlib.redirect_stderr(f):
      trainer.run_training(num_iterations=steps,
                           data_path=os.path.join(tmp, "scene"),
                           output_base=os.path.join(tmp, "out"),
                           images_subdir="images")
  return snaps


def score_ghif(peers_dir: str, snaps, views, lpips_net: str) -> list[dict]:
  """[{step, seconds, test_psnr, test_ssim, test_lpips}] of the snapshots
  rendered by the peer on `views` (one canvas size)."""
  _, gaussians_cls, camera_cls, render = _load_ghif(peers_dir)
  w, h = int(views.cameras.width), int(views.cameras.height)
  cams = jax.tree.map(jnp.asarray, views.cameras)

  @functools.partial(jax.jit, static_argnums=(2,))
  def draw(g, i, degree):
    w2c = jnp.eye(4).at[:3, :3].set(cams.rotation[i]).at[:3, 3].set(
        cams.translation[i])
    cam = camera_cls(W=w, H=h, fx=cams.fx[i], fy=cams.fy[i], cx=cams.cx[i],
                     cy=cams.cy[i], W2C=w2c, full_proj=jnp.eye(4))
    return jnp.clip(render(g, cam, sh_degree=degree)[0], 0.0, 1.0)

  curve = []
  for step, seconds, arrays, degree in snaps:
    g = gaussians_cls(**{k: jnp.asarray(v) for k, v in arrays.items()})
    scores = [metrics_lib.image_metrics(
        draw(g, i, int(degree))[None], jnp.asarray(views.images[i])[None],
        lpips_net) for i in range(len(views))]
    curve.append({"step": int(step), "seconds": float(seconds),
                  **{f"test_{k}": float(np.mean([np.asarray(s[k])
                                                  for s in scores]))
                     for k in ("psnr", "ssim", "lpips")}})
  return curve


def train_ours(scene_path: str, downscale: int, steps: int, seed: int,
               workdir: str, lpips_net: str) -> list[dict]:
  """[{step, seconds, test_psnr}] of our vanilla 3DGS (configs/default.py's
  3DGS values) every CURVE_EVERY steps; the last point also has the final
  test_ssim and test_lpips."""
  cfg = config_file.check({
      "data": {"scene": scene_path, "downscale": downscale},
      "train": {"steps": steps, "seed": seed, "eval_every": CURVE_EVERY},
      "eval": {"curve_points": 0, "lpips_net": lpips_net}})
  out = run_lib.train_and_evaluate(cfg, workdir, progress=False)
  curve = [dict(p) for p in run_lib.read_json(
      os.path.join(workdir, run_lib.CURVE_JSON), "the run's curve")
           if p["step"] > 0]
  curve[-1].update(test_ssim=out["test"]["ssim"],
                   test_lpips=out["test"]["lpips"])
  return curve


def plot(runs: dict, path: str) -> None:
  """Test error against training seconds and against steps, a line a
  system (plots.draw_curves)."""
  fig = figure.Figure(figsize=(10, 4), dpi=120)
  for ax, x in zip(fig.subplots(1, 2), ("seconds", "step")):
    plots.draw_curves(ax, runs, x)
  plots.save_figure(fig, path)


def bench(peers_dir: str, names, scene_path: str, downscale: int,
          steps: int, seed: int, workdir: str,
          lpips_net: str = "alex") -> dict:
  """Ours and each peer in `names` on one scene: writes PEERS_JSON
  ({"settings", "runs": {system: curve}}) and PEERS_PNG into `workdir`
  and returns the dict; our run's folder is workdir/ours.

  Raises:
    ValueError: a peer's sources are missing (every missing one named),
      `steps` is not a multiple of CURVE_EVERY, or the photos differ in
      size; all before the scene is read.
  """
  problems = missing(peers_dir, names)
  if steps <= 0 or steps % CURVE_EVERY:
    problems.append(f"steps={steps} must be a positive multiple of "
                    f"{CURVE_EVERY} (the peers' snapshot cadence)")
  if problems:
    raise ValueError("; ".join(problems))
  scene = scene_lib.load_scene(scene_path, downscale=downscale)
  if scene.train.sizes is not None or scene.test.sizes is not None:
    raise ValueError(f"{scene_path}: photos of different sizes; the peers "
                     "train one image size")
  runs = {"ours": train_ours(scene_path, downscale, steps, seed,
                             os.path.join(workdir, "ours"), lpips_net)}
  for name in names:
    snaps = train_ghif(scene, peers_dir, steps, seed,
                       os.path.join(workdir, f"{name}.log"))
    runs[name] = score_ghif(peers_dir, snaps, scene.test, lpips_net)
  out = {"settings": {"scene": scene_path, "downscale": downscale,
                      "steps": steps, "seed": seed, "lpips_net": lpips_net,
                      "train_views": len(scene.train),
                      "test_views": len(scene.test),
                      **table.machine_and_date()},
         "runs": runs}
  fileio.write_json(os.path.join(workdir, PEERS_JSON), out)
  plot(runs, os.path.join(workdir, PEERS_PNG))
  return out
