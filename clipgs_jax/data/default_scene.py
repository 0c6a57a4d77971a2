"""The embedded default scene: a procedural RobustNeRF-style capture."""

import json
import os
import shutil
import uuid

import numpy as np
import pycolmap

from clipgs_jax import camera
from clipgs_jax.data import colmap
from clipgs_jax.data import images

# 2: persistent transients (each stays put for a run of views), every
# training view cluttered; caches of version 1 are rebuilt.
VERSION = 2
SEED = 20261122
WIDTH, HEIGHT = 128, 96
FOCAL = 110.0                 # pixels: about 60 degrees horizontal field
NUM_TRAIN, NUM_TEST = 24, 5
NUM_POINTS_PER_VIEW = 200     # sparse points sampled from each view
POINT_NOISE = 0.01            # scene units, mimics SfM triangulation error
SUPERSAMPLE = 2               # 2x2 samples per pixel, so edges are fittable
MIN_TRANSIENT_PIXELS = 30     # every view of a run sees its object this much
# Transient objects, as in RobustNeRF: each stays at one 3D position for a
# run of consecutive training views (about a quarter of the ring at most),
# so that vanilla 3DGS can fit it as a multi-view-consistent ghost. A new
# object enters every RUN_STRIDE views; with runs of RUN_LENGTHS views every
# training view is cluttered and some see two objects.
RUN_STRIDE = 3
RUN_LENGTHS = (3, 6)          # inclusive range of a run's length in views
# Objects stand between the camera ring (radius 3) and the static objects
# (within radius ~1.4 of the centre): this range of distances from the
# centre, so that fitted ghosts occlude static content in nearby views.
TRANSIENT_RADII = (1.75, 2.15)
MAX_PLACEMENT_TRIES = 50      # resample an object until all its views see it

_TARGET = np.array([0.0, 0.0, 0.3])
_UP = np.array([0.0, 0.0, 1.0])
_LIGHT = np.array([0.5, -0.3, 1.0]) / np.linalg.norm([0.5, -0.3, 1.0])
_AMBIENT = 0.35
_GROUND_HALF = 3.5            # the ground is the square |x|, |y| <= this
_BACKDROP_RADIUS = 7.0
_EPS = 1e-4                   # offset of shadow rays, avoids self-hits

# Object ids in the hit buffers; transients are >= _TRANSIENT.
_MISS, _GROUND, _BACKDROP = -1, 0, 1
_TRANSIENT = 100

# Static primitives. Spheres: (centre, radius, albedo); box: (centre,
# half sizes, rotation about z, albedo); cylinder: (base xy, radius, height,
# albedo), standing on the ground.
_SPHERES = [((0.6, -0.4, 0.45), 0.45, (0.85, 0.2, 0.15)),
            ((0.9, 0.75, 0.2), 0.2, (0.95, 0.8, 0.15))]
_BOX = ((-0.7, -0.45, 0.35), (0.35, 0.3, 0.35), np.deg2rad(30),
        (0.2, 0.35, 0.85))
_CYLINDER = ((-0.25, 0.8), 0.25, 0.9, (0.2, 0.7, 0.3))

_VIVID = [(1.0, 0.1, 0.8), (1.0, 0.5, 0.0), (0.0, 0.85, 1.0),
          (0.55, 1.0, 0.0), (1.0, 0.1, 0.1), (0.6, 0.2, 1.0)]
_SKIN = (0.95, 0.75, 0.6)


def _ray_sphere(o, d, centre, radius):
  """float [N] hit distance (inf on miss), nearest positive root."""
  oc = o - np.asarray(centre)
  b = np.einsum("ni,ni->n", oc, d)
  c = np.einsum("ni,ni->n", oc, oc) - radius ** 2
  disc = b * b - c
  root = np.sqrt(np.maximum(disc, 0.0))
  t1, t2 = -b - root, -b + root
  t = np.where(t1 > _EPS, t1, np.where(t2 > _EPS, t2, np.inf))
  return np.where(disc >= 0, t, np.inf)


def _ray_vertical_cylinder(o, d, xy, radius, z0, z1):
  """float [N] hit distance with the side of a vertical cylinder."""
  ox, oy = o[:, 0] - xy[0], o[:, 1] - xy[1]
  a = d[:, 0] ** 2 + d[:, 1] ** 2
  b = 2 * (ox * d[:, 0] + oy * d[:, 1])
  c = ox ** 2 + oy ** 2 - radius ** 2
  disc = b * b - 4 * a * c
  safe_a = np.where(a > 1e-12, a, 1.0)
  t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * safe_a)
  z = o[:, 2] + t * d[:, 2]
  ok = (disc >= 0) & (a > 1e-12) & (t > _EPS) & (z >= z0) & (z <= z1)
  return np.where(ok, t, np.inf)


def _ray_disc_top(o, d, xy, radius, z):
  """float [N] hit distance with a horizontal disc (cylinder cap)."""
  safe = np.where(np.abs(d[:, 2]) > 1e-12, d[:, 2], 1.0)
  t = (z - o[:, 2]) / safe
  p = o + t[:, None] * d
  ok = ((np.abs(d[:, 2]) > 1e-12) & (t > _EPS) &
        ((p[:, 0] - xy[0]) ** 2 + (p[:, 1] - xy[1]) ** 2 <= radius ** 2))
  return np.where(ok, t, np.inf)


def _ray_box(o, d, centre, half, angle):
  """(t [N], normal [N, 3]) for a box rotated by `angle` about z."""
  c, s = np.cos(angle), np.sin(angle)
  rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])     # box to world
  ol, dl = (o - centre) @ rot, d @ rot                    # world to box
  safe = np.where(np.abs(dl) > 1e-12, dl, 1e-12)
  ta, tb = (-np.asarray(half) - ol) / safe, (np.asarray(half) - ol) / safe
  tmin, tmax = np.minimum(ta, tb), np.maximum(ta, tb)
  # Column-wise reductions: much faster than .max(axis=1) on [N, 3].
  near = np.maximum(np.maximum(tmin[:, 0], tmin[:, 1]), tmin[:, 2])
  far = np.minimum(np.minimum(tmax[:, 0], tmax[:, 1]), tmax[:, 2])
  hit = (near <= far) & (near > _EPS)
  # The entry face is the slab whose entry distance is `near`.
  normal = np.where(tmin == near[:, None], -np.sign(dl), 0.0)
  return np.where(hit, near, np.inf), normal @ rot.T


def _static_hits(o, d, occluders_only=False):
  """Nearest static hit: (t [N], id [N], normal [N, 3]).

  With `occluders_only`, only the primitives that cast shadows are tested
  (not the ground or the backdrop), for shadow rays.
  """
  n = len(o)
  t = np.full(n, np.inf)
  ids = np.full(n, _MISS)
  normal = np.zeros((n, 3))

  def take(ti, oid, ni):
    closer = ti < t
    t[closer], ids[closer] = ti[closer], oid
    normal[closer] = ni[closer] if ni.ndim == 2 else ni

  def point(ti):
    return o + np.where(np.isfinite(ti), ti, 0)[:, None] * d

  if not occluders_only:
    safe = np.where(d[:, 2] < -1e-12, d[:, 2], -1.0)
    tg = np.where(d[:, 2] < -1e-12, -o[:, 2] / safe, np.inf)
    inside = (np.abs(point(tg)[:, :2]) <= _GROUND_HALF).all(axis=1)
    take(np.where(inside & (tg > _EPS), tg, np.inf), _GROUND,
         np.array([0.0, 0.0, 1.0]))
  for k, (centre, radius, _) in enumerate(_SPHERES):
    ts = _ray_sphere(o, d, centre, radius)
    take(ts, 2 + k, (point(ts) - np.asarray(centre)) / radius)
  tb, nb = _ray_box(o, d, np.asarray(_BOX[0]), _BOX[1], _BOX[2])
  take(tb, 2 + len(_SPHERES), nb)
  xy, radius, height, _ = _CYLINDER
  tc = _ray_vertical_cylinder(o, d, xy, radius, 0.0, height)
  p = point(tc)
  side = np.stack([p[:, 0] - xy[0], p[:, 1] - xy[1], np.zeros(n)], 1) / radius
  take(tc, 3 + len(_SPHERES), side)
  take(_ray_disc_top(o, d, xy, radius, height), 3 + len(_SPHERES),
       np.array([0.0, 0.0, 1.0]))
  if not occluders_only:
    # The backdrop is seen from inside, so its far root is the hit.
    take(_ray_sphere(o, d, (0, 0, 0), _BACKDROP_RADIUS), _BACKDROP,
         np.array([0.0, 0.0, 0.0]))
  return t, ids, normal


def _shadowed(p):
  """bool [N], True where the light is blocked by a static primitive."""
  d = np.ascontiguousarray(np.broadcast_to(_LIGHT, p.shape))
  return np.isfinite(_static_hits(p, d, occluders_only=True)[0])


def _albedo(ids, p):
  """float [N, 3] surface colour of static objects (textured)."""
  col = np.zeros(p.shape)
  g = ids == _GROUND
  x, y = p[g, 0], p[g, 1]
  # Soft checker (sin product through tanh) with a slow colour drift.
  chk = (0.5 + 0.5 * np.tanh(3 * np.sin(2 * np.pi * x) *
                             np.sin(2 * np.pi * y)))[:, None]
  a, b = np.array([0.85, 0.8, 0.7]), np.array([0.45, 0.4, 0.38])
  drift = 0.12 * np.stack([np.sin(0.9 * x), np.cos(0.7 * y),
                           np.sin(0.5 * (x + y))], 1)
  col[g] = a * chk + b * (1 - chk) + drift
  for k, (centre, _, albedo) in enumerate(_SPHERES):
    m = ids == 2 + k
    band = 0.8 + 0.2 * np.cos(14 * (p[m, 2] - centre[2]))
    col[m] = np.asarray(albedo) * band[:, None]
  m = ids == 2 + len(_SPHERES)
  col[m] = np.asarray(_BOX[3]) * (0.85 + 0.15 * np.sin(9 * p[m, 2]))[:, None]
  m = ids == 3 + len(_SPHERES)
  ang = np.arctan2(p[m, 1] - _CYLINDER[0][1], p[m, 0] - _CYLINDER[0][0])
  col[m] = np.asarray(_CYLINDER[3]) * (0.8 + 0.2 * np.cos(6 * ang))[:, None]
  return col


def _backdrop(d):
  """float [N, 3] unlit backdrop colour by direction: sky gradient + bands."""
  elev = d[:, 2]
  az = np.arctan2(d[:, 1], d[:, 0])
  horizon, zenith = np.array([0.92, 0.88, 0.8]), np.array([0.35, 0.55, 0.9])
  w = np.clip(elev, 0, 1)[:, None] ** 0.6
  sky = horizon * (1 - w) + zenith * w
  sky += 0.08 * np.stack([np.sin(3 * az), np.sin(3 * az + 2), np.sin(5 * az)],
                         1) * (1 - w)
  # Below the horizon, a wall with soft vertical stripes gives the
  # background some texture to fit.
  below = (np.array([0.3, 0.28, 0.27]) + 0.05 * np.sin(4 * az)[:, None] +
           0.06 * np.sin(40 * az)[:, None])
  return np.where(elev[:, None] >= 0, sky, below)


def _shade(o, d, t, ids, normal, albedo):
  """float [N, 3] Lambertian colour; backdrop pixels are unlit."""
  p = o + np.where(np.isfinite(t), t, 0)[:, None] * d
  diffuse = np.clip(normal @ _LIGHT, 0, None)
  # Shadow rays only where they can change the colour.
  test = (diffuse > 0) & (ids != _BACKDROP)
  diffuse[test] *= ~_shadowed(p[test] + _EPS * 10 * normal[test])
  col = albedo * (_AMBIENT + (1 - _AMBIENT) * diffuse)[:, None]
  sky = ids == _BACKDROP
  col[sky] = _backdrop(d[sky])
  return col


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


def _sphere_part(o, d, centre, radius):
  """(t [N], normal [N, 3]) of a sphere seen from outside."""
  t = _ray_sphere(o, d, centre, radius)
  p = o + np.where(np.isfinite(t), t, 0)[:, None] * d
  return t, (p - np.asarray(centre)) / radius


def _side_part(o, d, xy, radius, z0, z1):
  """(t [N], normal [N, 3]) of the side of a vertical cylinder."""
  t = _ray_vertical_cylinder(o, d, xy, radius, z0, z1)
  p = o + np.where(np.isfinite(t), t, 0)[:, None] * d
  n = np.stack([p[:, 0] - xy[0], p[:, 1] - xy[1], np.zeros(len(t))], 1)
  return t, n / radius


def _object_parts(o, d, tr):
  """[(t [N], normal [N, 3], colour [3] or callable of hit points)]."""
  x, y, z = tr["position"]
  if tr["kind"] == "person":
    # A capsule body (shirt over trousers) with a head, standing on the
    # ground at (x, y).
    r, top = tr["radius"], tr["height"] - 2.2 * tr["head"]
    hip = 0.45 * tr["height"]
    shirt, trousers = np.asarray(tr["color"]), np.asarray(tr["color2"])

    def body(p):
      return np.where((p[:, 2] < hip)[:, None], trousers, shirt)
    head = (x, y, tr["height"] - tr["head"])
    return [_sphere_part(o, d, (x, y, r), r) + (body,),
            _sphere_part(o, d, (x, y, top), r) + (body,),
            _side_part(o, d, (x, y), r, r, top) + (body,),
            _sphere_part(o, d, head, tr["head"]) + (_SKIN,)]
  if tr["kind"] == "crate":
    half = np.asarray(tr["half"])
    t, n = _ray_box(o, d, np.array([x, y, half[2]]), half, tr["angle"])
    colour = np.asarray(tr["color"])

    def slats(p):                     # horizontal bands: texture to fit
      band = 0.75 + 0.25 * (np.sin(25 * p[:, 2]) > 0)
      return colour * band[:, None]
    return [(t, n, slats)]
  # A balloon on a string tied to the ground.
  return [_sphere_part(o, d, (x, y, z), tr["radius"]) + (tr["color"],),
          _side_part(o, d, (x, y), 0.01, 0.0, z - tr["radius"]) +
          ((0.95, 0.95, 0.95),)]


def _transient_hits(o, d, transients):
  """Nearest transient hit: (t [N], albedo [N, 3], normal [N, 3])."""
  t = np.full(len(o), np.inf)
  col = np.zeros((len(o), 3))
  normal = np.zeros((len(o), 3))
  for tr in transients:
    for tp, n, colour in _object_parts(o, d, tr):
      closer = tp < t
      t[closer] = tp[closer]
      normal[closer] = n[closer]
      if callable(colour):
        col[closer] = colour(o[closer] + tp[closer, None] * d[closer])
      else:
        col[closer] = colour
  return t, col, normal


def _random_object(rng, cams):
  """A person, crate or balloon standing in front of a run of cameras.

  It stands at TRANSIENT_RADII from the scene centre, near the azimuth of
  the run's middle camera: between those cameras and the static objects.
  """
  centres = np.stack([camera.camera_center(c) for c in cams])
  mid = centres[:, :2].mean(axis=0)
  az = np.arctan2(mid[1], mid[0]) + rng.uniform(-0.15, 0.15)
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
  t, ids, normal = _static_hits(o, d)
  p = o + np.where(np.isfinite(t), t, 0)[:, None] * d
  col = _shade(o, d, t, ids, normal, _albedo(ids, p))
  return (_downsample(col, cam, SUPERSAMPLE),
          {"o": o, "d": d, "t": t, "col": col})


def _render_cluttered(cam, buffers, transients):
  """(colour [H, W, 3], mask bool [H, W], per-sample buffers) of a view.

  The transients are composited over the static render; the buffers are
  those of the cluttered view (what structure from motion would see).
  """
  o, d = buffers["o"], buffers["d"]
  t, albedo, normal = _transient_hits(o, d, transients)
  front = t < buffers["t"]
  col = buffers["col"].copy()
  col[front] = _shade(o[front], d[front], t[front],
                      np.full(int(front.sum()), _TRANSIENT), normal[front],
                      albedo[front])
  mask = _downsample(front.astype(np.float64)[:, None], cam, SUPERSAMPLE)
  # A pixel is transient if any of its samples sees a transient: every
  # contaminated pixel is marked.
  cluttered = {"o": o, "d": d, "t": np.where(front, t, buffers["t"]),
               "col": col}
  return _downsample(col, cam, SUPERSAMPLE), mask[..., 0] > 0, cluttered


def _sample_points(rng, buffers):
  """Sparse points from one view: (xyz [n, 3], rgb uint8 [n, 3])."""
  pick = rng.choice(len(buffers["t"]), NUM_POINTS_PER_VIEW, replace=False)
  # Every ray ends on the backdrop at the latest, so t is finite.
  xyz = buffers["o"][pick] + buffers["t"][pick, None] * buffers["d"][pick]
  xyz += rng.normal(0, POINT_NOISE, xyz.shape)
  rgb = np.round(np.clip(buffers["col"][pick], 0, 1) * 255)
  return xyz, rgb.astype(np.uint8)


def _write_model(folder, named_cams, points, colors):
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
from motion triangulates objects that stay put), transients.json (the objects, their runs of views,
and each view's objects).

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
  points, colors, views = [], [], []
  renders = [_render_static(cam) for cam in train]
  placed = _place_objects(rng, train, [b for _, b in renders])
  for k, (cam, (clean, buffers)) in enumerate(zip(train, renders)):
    here = [(i, tr) for i, (tr, run) in enumerate(placed) if k in run]
    image, mask, seen = _render_cluttered(cam, buffers,
                                          [tr for _, tr in here])
    # Structure from motion triangulates what the training views show: an
    # object that stays put for several views gets points too.
    xyz, rgb = _sample_points(rng, seen)
    points.append(xyz)
    colors.append(rgb)
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
      (~/.cache/clipgs_jax). The scene is `<cache_dir>/default_scene_v1`.

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
