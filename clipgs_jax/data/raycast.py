"""Numpy ray caster of the default scene: static objects and transients."""

import numpy as np

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


def static(o, d):
  """Shaded static scene along rays.

  Args:
    o: float64 [N, 3], ray origins (world).
    d: float64 [N, 3], unit ray directions.

  Returns:
    (t float64 [N], colour float64 [N, 3]): hit distance (finite: every ray
    ends on the backdrop at the latest) and linear colour.
  """
  t, ids, normal = _static_hits(o, d)
  p = o + np.where(np.isfinite(t), t, 0)[:, None] * d
  return t, _shade(o, d, t, ids, normal, _albedo(ids, p))


def transients(o, d, objects, t_max):
  """Shaded transient objects along rays, where they are nearer than t_max.

  Transients receive the static objects' shadows but cast none, so pixels
  they do not cover keep their static colour exactly.

  Args:
    o: float64 [N, 3], ray origins (world).
    d: float64 [N, 3], unit ray directions.
    objects: list of dicts, as made by default_scene (kind, position, ...).
    t_max: float64 [N], distance of the static hit (occlusion).

  Returns:
    (t float64 [N], colour float64 [N, 3]): t is inf where no transient is
    in front of t_max; colour is 0 there.
  """
  t, albedo, normal = _transient_hits(o, d, objects)
  front = t < t_max
  col = np.zeros((len(o), 3))
  col[front] = _shade(o[front], d[front], t[front],
                      np.full(int(front.sum()), _TRANSIENT), normal[front],
                      albedo[front])
  return np.where(front, t, np.inf), col
