"""The embedded default scene: a procedural RobustNeRF-style capture."""

import json
import os
import shutil
import uuid

import numpy as np

from clipgs_jax import camera
from clipgs_jax.data import colmap
from clipgs_jax.data import images
from clipgs_jax.data import raycast

# 2: persistent transients (each stays put for a run of views), every
# training view cluttered, SfM points on them. A cache written by another
# version lives in another folder and is never read.
VERSION = 2
SEED = 20261122
# Training steps for this scene in the README main job and in train.py
# when --config.train.steps is not set: clean upper bound 19.94 dB against
# vanilla 15.20 dB at 700 steps (BUILD_NOTES.md, "Embedded default
# scene"), and a vanilla and a guided run fit the README's 10 minutes on 2
# cores.
TRAIN_STEPS = 700
WIDTH, HEIGHT = 128, 96
FOCAL = 110.0                 # pixels: about 60 degrees horizontal field
NUM_TRAIN, NUM_TEST = 24, 5
NUM_POINTS_PER_VIEW = 200     # sparse points sampled from each view
POINT_NOISE = 0.01            # scene units, mimics SfM triangulation error
SUPERSAMPLE = 2               # 2x2 samples per pixel, so edges are fittable
MIN_TRANSIENT_PIXELS = 30     # every view of a run sees its object this much
# Transient objects, as in RobustNeRF: each stays at one 3D position for a
# run of consecutive training views (at most 75 degrees of the ring),
# so that vanilla 3DGS can fit it as a multi-view-consistent ghost. A new
# object enters every RUN_STRIDE views; with runs of RUN_LENGTHS views every
# training view is cluttered and some see two objects.
RUN_STRIDE = 3
RUN_LENGTHS = (3, 6)          # inclusive range of a run's length in views
# Objects stand between the camera ring (radius 3) and the static objects
# (within radius ~1.4 of the centre): this range of distances from the
# centre, so that fitted ghosts occlude static content in nearby views.
TRANSIENT_RADII = (1.75, 2.15)
TRANSIENT_AZIMUTH_JITTER = 0.15  # radians around the run's middle camera
MAX_PLACEMENT_TRIES = 50      # resample an object until all its views see it

_TARGET = np.array([0.0, 0.0, 0.3])
_UP = np.array([0.0, 0.0, 1.0])
_VIVID = [(1.0, 0.1, 0.8), (1.0, 0.5, 0.0), (0.0, 0.85, 1.0),
          (0.55, 1.0, 0.0), (1.0, 0.1, 0.1), (0.6, 0.2, 1.0)]


def _rays(cam: camera.Camera, samples: int):
  """World rays through a samples x samples grid in each pixel."""
  off = (np.arange(samples) + 0.5) / samples
  v = (np.arange(cam.height)[:, None] + off[None]).reshape(-1)
  u = (np.arange(cam.width)[:, None] + off[None]).reshape(-1)
  vv, uu = np.meshgrid(v, u, indexing="ij")        # [H s, W s]
  dirs = np.stack([(uu - cam.cx) / cam.fx, (vv - cam.cy) / cam.fy,
                   np.ones_like(uu)], -1).reshape(-1, 3)
  rot = np.asarray(cam.rotation, np.float64)
  d = dirs @ rot                                    # R^T d, row vectors
  d /= np.linalg.norm(d, axis=1, keepdims=True)
  o = np.broadcast_to(camera.camera_center(cam), d.shape)
  return np.ascontiguousarray(o, np.float64), d


def _downsample(x, cam, samples):
  """Mean over each pixel's samples: [H s * W s, C] -> [H, W, C]."""
  x = x.reshape(cam.height, samples, cam.width, samples, -1)
  return x.mean(axis=(1, 3))


def _random_object(rng, cams):
  """A person, crate or balloon standing in front of a run of cameras.

  It stands at TRANSIENT_RADII from the scene centre, near the azimuth of
  the run's middle camera: between those cameras and the static objects.
  """
  centres = np.stack([camera.camera_center(c) for c in cams])
  mid = centres[:, :2].mean(axis=0)
  az = np.arctan2(mid[1], mid[0]) + rng.uniform(-TRANSIENT_AZIMUTH_JITTER,
                                                TRANSIENT_AZIMUTH_JITTER)
  radius = rng.uniform(*TRANSIENT_RADII)
  x, y = radius * np.cos(az), radius * np.sin(az)
  pick = rng.permutation(len(_VIVID))
  color, color2 = tuple(_VIVID[pick[0]]), tuple(_VIVID[pick[1]])
  kind = rng.choice(["person", "person", "crate", "balloon"])
  if kind == "person":
    return {"kind": "person", "position": [x, y, 0.0],
            "height": rng.uniform(1.2, 1.6), "radius": rng.uniform(0.16, 0.24),
            "head": rng.uniform(0.11, 0.14), "color": color,
            "color2": tuple(0.6 * np.asarray(color2))}
  if kind == "crate":
    return {"kind": "crate", "position": [x, y, 0.0],
            "half": [rng.uniform(0.2, 0.32), rng.uniform(0.2, 0.32),
                     rng.uniform(0.25, 0.45)],
            "angle": rng.uniform(0, np.pi / 2), "color": color}
  return {"kind": "balloon", "radius": rng.uniform(0.22, 0.32),
          "position": [x, y, rng.uniform(0.8, 1.3)], "color": color}


def _schedule(rng):
  """[(first view, run length)]: a new object every RUN_STRIDE views."""
  runs = []
  for first in range(0, NUM_TRAIN, RUN_STRIDE):
    length = int(rng.integers(RUN_LENGTHS[0], RUN_LENGTHS[1] + 1))
    runs.append((first, min(length, NUM_TRAIN - first)))
  return runs


def _look_at(eye) -> camera.Camera:
  """Camera at `eye` looking at _TARGET, image up = world up (+z).

  Rows of R are the camera axes in world coordinates: x right, y down (so
  -up projected), z forward.
  """
  eye = np.asarray(eye, np.float64)
  z = _TARGET - eye
  z /= np.linalg.norm(z)
  x = np.cross(z, _UP)
  x /= np.linalg.norm(x)
  y = np.cross(z, x)
  rotation = np.stack([x, y, z])
  return camera.Camera.create(rotation, -rotation @ eye, FOCAL, FOCAL,
                              WIDTH / 2, HEIGHT / 2, WIDTH, HEIGHT,
                              dtype=np.float64)


def _cameras():
  """(train, test) lists of cameras on a ring looking at the centre."""
  def ring(n, phase, radius, height, wobble):
    cams = []
    for k in range(n):
      az = 2 * np.pi * k / n + phase
      cams.append(_look_at((radius * np.cos(az), radius * np.sin(az),
                            height + wobble * np.sin(2 * az))))
    return cams
  return (ring(NUM_TRAIN, 0.0, 3.0, 1.3, 0.25),
          ring(NUM_TEST, 0.3, 3.1, 1.5, 0.2))


def _render_static(cam):
  """Static render: (colour [H, W, 3], per-sample buffers for compositing)."""
  o, d = _rays(cam, SUPERSAMPLE)
  t, col = raycast.static(o, d)
  return (_downsample(col, cam, SUPERSAMPLE),
          {"o": o, "d": d, "t": t, "col": col})


def _render_cluttered(cam, buffers, transients):
  """(colour [H, W, 3], mask bool [H, W], per-sample buffers) of a view.

  The transients are composited over the static render; the buffers are
  those of the cluttered view (what structure from motion would see).
  """
  o, d = buffers["o"], buffers["d"]
  t, colour = raycast.transients(o, d, transients, buffers["t"])
  front = np.isfinite(t)
  col = np.where(front[:, None], colour, buffers["col"])
  mask = _downsample(front.astype(np.float64)[:, None], cam, SUPERSAMPLE)
  # A pixel is transient if any of its samples sees a transient: every
  # contaminated pixel is marked.
  cluttered = {"o": o, "d": d, "t": np.where(front, t, buffers["t"]),
               "col": col, "transient": front}
  return _downsample(col, cam, SUPERSAMPLE), mask[..., 0] > 0, cluttered


def _sample_points(rng, buffers):
  """Sparse points from one view's samples.

  Returns:
    (xyz float64 [n, 3], rgb uint8 [n, 3], on_transient bool [n]).
  """
  pick = rng.choice(len(buffers["t"]), NUM_POINTS_PER_VIEW, replace=False)
  # Every ray ends on the backdrop at the latest, so t is finite.
  xyz = buffers["o"][pick] + buffers["t"][pick, None] * buffers["d"][pick]
  xyz += rng.normal(0, POINT_NOISE, xyz.shape)
  rgb = np.round(np.clip(buffers["col"][pick], 0, 1) * 255)
  return xyz, rgb.astype(np.uint8), buffers["transient"][pick]


def _write_model(folder, named_cams, points, colors):
  import pycolmap  # pylint: disable=import-outside-toplevel  # see colmap.py
  rec = pycolmap.Reconstruction()
  rec.add_camera_with_trivial_rig(pycolmap.Camera(
      camera_id=1, model="PINHOLE", width=WIDTH, height=HEIGHT,
      params=[FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2]))
  for image_id, (name, cam) in enumerate(sorted(named_cams.items()), 1):
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(cam.rotation)),
                            np.asarray(cam.translation, np.float64))
    rec.add_image_with_trivial_frame(
        pycolmap.Image(name=name, camera_id=1, image_id=image_id), pose)
  for xyz, rgb in zip(points, colors):
    rec.add_point3D(xyz.astype(np.float64), pycolmap.Track(), rgb)
  os.makedirs(folder)
  rec.write_binary(folder)


_README = """\
clipgs_jax default scene, version {version}

A procedural scene generated by clipgs_jax (clipgs_jax/data/default_scene.py,
seed {seed}): a textured ground, four primitives and a sky backdrop, ray cast
with 2x2 supersampling. RobustNeRF layout: images/0cleanNNN.png (clean twins
of the training views), images/1extraNNN.png (clean test views),
images/2clutterNNN.png (training views; every one contains transient people,
crates or balloons, each of which stays at one place for a run of 3-6
consecutive views, as RobustNeRF's distractors do), masks/2clutterNNN.png
(white = transient pixel), sparse/0 (COLMAP PINHOLE model; points sampled
from the surfaces the training views see, transients included, as structure
from motion triangulates objects that stay put), transients.json (the
objects, their runs of views, and each view's objects).

License: CC0 1.0 (public domain dedication). Generated data, no third-party
content.
"""


def _describe(transient) -> dict:
  """JSON-ready transient with rounded numbers (stable text across runs)."""
  out = {}
  for key, value in transient.items():
    if isinstance(value, str):
      out[key] = value
    elif np.ndim(value):
      out[key] = [round(float(v), 6) for v in value]
    else:
      out[key] = round(float(value), 6)
  return out


def _object_pixels(cam, buffers, tr) -> int:
  """Pixels of `cam` in which the object alone is in front of the scene."""
  return int(_render_cluttered(cam, buffers, [tr])[1].sum())


def _place_objects(rng, train, buffers):
  """[(object, views)]: one object per run, seen by every view of it."""
  placed = []
  for first, length in _schedule(rng):
    views = list(range(first, first + length))
    for _ in range(MAX_PLACEMENT_TRIES):
      tr = _random_object(rng, [train[k] for k in views])
      if all(_object_pixels(train[k], buffers[k], tr) >= MIN_TRANSIENT_PIXELS
             for k in views):
        break
    else:
      raise RuntimeError(f"default scene: no placement of the object for "
                         f"views {views} is visible in all of them; "
                         f"TRANSIENT_RADII or RUN_LENGTHS are inconsistent")
    placed.append((tr, views))
  return placed


def generate(folder: str) -> None:
  """Writes the default scene into `folder` (which must not exist)."""
  rng = np.random.default_rng(SEED)
  train, test = _cameras()
  img_dir = os.path.join(folder, "images")
  named = {}
  points, colors, labels, views = [], [], [], []
  renders = [_render_static(cam) for cam in train]
  placed = _place_objects(rng, train, [b for _, b in renders])
  for k, (cam, (clean, buffers)) in enumerate(zip(train, renders)):
    here = [(i, tr) for i, (tr, run) in enumerate(placed) if k in run]
    image, mask, seen = _render_cluttered(cam, buffers,
                                          [tr for _, tr in here])
    # Structure from motion triangulates what the training views show: an
    # object that stays put for several views gets points too.
    xyz, rgb, on_transient = _sample_points(rng, seen)
    points.append(xyz)
    colors.append(rgb)
    labels.append(on_transient)
    names = (f"0clean{k:03d}.png", f"2clutter{k:03d}.png")
    images.write_png(os.path.join(img_dir, names[0]), clean)
    images.write_png(os.path.join(img_dir, names[1]), image)
    images.write_png(os.path.join(folder, "masks", names[1]), mask)
    named.update({names[0]: cam, names[1]: cam})
    views.append({
        "name": names[1], "clean": names[0], "mask": f"masks/{names[1]}",
        "transient_pixels": int(mask.sum()),
        "transients": [{"id": i, **_describe(tr)} for i, tr in here]})
  for k, cam in enumerate(test):
    name = f"1extra{k:03d}.png"
    images.write_png(os.path.join(img_dir, name), _render_static(cam)[0])
    named[name] = cam
  _write_model(os.path.join(folder, "sparse", "0"), named,
               np.concatenate(points), np.concatenate(colors))
  files = sorted([f"images/{n}" for n in named] + [v["mask"] for v in views] +
                 [f"sparse/0/{f}" for f in os.listdir(
                     os.path.join(folder, "sparse", "0"))] + ["README.txt"])
  objects = [{"id": i, "views": [views[k]["name"] for k in run],
              **_describe(tr)} for i, (tr, run) in enumerate(placed)]
  manifest = {"generator": "clipgs_jax.data.default_scene",
              "version": VERSION, "seed": SEED, "width": WIDTH,
              "height": HEIGHT, "views": views, "objects": objects,
              "num_points": sum(len(p) for p in points),
              # Rows of the sparse model (in point3D id order, as
              # scene.load_scene returns them) that lie on a transient.
              "transient_points": np.flatnonzero(
                  np.concatenate(labels)).tolist(),
              "files": files}
  with open(os.path.join(folder, "README.txt"), "w") as f:
    f.write(_README.format(version=VERSION, seed=SEED))
  with open(os.path.join(folder, "transients.json"), "w") as f:
    json.dump(manifest, f, indent=1, sort_keys=True)


def _is_complete(folder: str) -> bool:
  try:
    with open(os.path.join(folder, "transients.json")) as f:
      manifest = json.load(f)
  except (OSError, ValueError):
    return False
  return manifest.get("version") == VERSION and all(
      os.path.isfile(os.path.join(folder, p)) and
      os.path.getsize(os.path.join(folder, p)) > 0
      for p in manifest.get("files", [None]))


def ensure_default_scene(cache_dir: str | None = None) -> str:
  """Path of the default scene, generating it first if missing or incomplete.

  Args:
    cache_dir: str or None, parent folder; default `colmap.cache_root()`
      (~/.cache/clipgs_jax). The scene is `<cache_dir>/default_scene_vN`,
      N = VERSION; a scene written by another version is rebuilt.

  Returns:
    str, the scene folder, ready for `scene.load_scene`.
  """
  root = cache_dir or colmap.cache_root()
  final = os.path.join(root, f"default_scene_v{VERSION}")
  if _is_complete(final):
    return final
  os.makedirs(root, exist_ok=True)
  tmp = os.path.join(root, f".tmp-default-scene-{os.getpid()}-"
                     f"{uuid.uuid4().hex[:8]}")
  try:
    generate(tmp)
    if os.path.exists(final):         # incomplete leftover: move it away
      stale = tmp + "-stale"
      os.rename(final, stale)
      shutil.rmtree(stale, ignore_errors=True)
    os.rename(tmp, final)
  except OSError:
    # Another process may have renamed its complete copy into place first.
    if not _is_complete(final):
      raise
  finally:
    shutil.rmtree(tmp, ignore_errors=True)
  return final
