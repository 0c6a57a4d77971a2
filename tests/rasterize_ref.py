"""Slow dense reference renderer: every pixel against every sorted Gaussian.

Written plainly and independently of clipgs_jax.render.project/rasterize (only the
SH basis is shared, and it has its own closed-form tests), so that the tiled
rasterizer and its custom VJP can be checked against autodiff of this.
"""

import functools

import jax
import jax.numpy as jnp

from clipgs_jax import sh


def _rotmat(q):
  norm = jnp.sqrt(jnp.sum(q * q, -1, keepdims=True))
  zero = norm == 0
  q = jnp.where(zero, jnp.array([1.0, 0, 0, 0], q.dtype),
                q / jnp.where(zero, 1.0, norm))
  w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
  return jnp.stack([
      jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z),
                 2 * (x * z + w * y)], -1),
      jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z),
                 2 * (y * z - w * x)], -1),
      jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x),
                 1 - 2 * (x * x + y * y)], -1)], -2)


# One jitted program per shape, shared by every test that renders that shape
# (the camera's values are traced). Run eagerly, it compiled each of its
# ~100 primitives (and their gradients) at every new shape: 400 small
# compiles and 10 s of CPU for one gradient test (BUILD_NOTES.md, "Test
# and compile time").
@functools.partial(jax.jit, static_argnames=("near", "sh_degree"))
def render_ref(params, alive, cam, background, near=0.2, sh_degree=None,
               evidence_map=None):
  """Returns dict(image [H,W,3], alpha [H,W], depth [H,W], contribution [C]).

  With evidence_map (float [H, W]) the dict also holds evidence [C], the
  blending weights of each Gaussian summed against the map.
  """
  dtype = params.means.dtype
  rot = jnp.asarray(cam.rotation, dtype)
  p = params.means @ rot.T + jnp.asarray(cam.translation, dtype)
  z = p[:, 2]
  valid = alive & (z > near)
  zs = jnp.where(valid, z, 1.0)
  xs, ys = jnp.where(valid, p[:, 0], 0.0), jnp.where(valid, p[:, 1], 0.0)
  fx, fy = jnp.asarray(cam.fx, dtype), jnp.asarray(cam.fy, dtype)
  limx = 1.3 * 0.5 * cam.width / fx
  limy = 1.3 * 0.5 * cam.height / fy
  tx = jnp.clip(xs / zs, -limx, limx) * zs
  ty = jnp.clip(ys / zs, -limy, limy) * zs
  o = jnp.zeros_like(zs)
  jac = jnp.stack([jnp.stack([fx / zs, o, -fx * tx / zs**2], -1),
                   jnp.stack([o, fy / zs, -fy * ty / zs**2], -1)], -2)
  rg = _rotmat(params.quats)
  s2 = jnp.exp(2 * params.log_scales)
  cov3 = jnp.einsum("nij,nj,nkj->nik", rg, s2, rg)
  t = jnp.einsum("nij,jk->nik", jac, rot)
  cov2 = jnp.einsum("nij,njk,nlk->nil", t, cov3, t) + 0.3 * jnp.eye(2, dtype=dtype)
  a, b, c = cov2[:, 0, 0], cov2[:, 0, 1], cov2[:, 1, 1]
  det = a * c - b * b
  opac = jax.nn.sigmoid(params.opacity_logits)
  valid = valid & (det > 0) & (opac >= 1 / 255)
  det = jnp.where(valid, det, 1.0)
  ca, cb, cc = c / det, -b / det, a / det
  u = fx * xs / zs + jnp.asarray(cam.cx, dtype)
  v = fy * ys / zs + jnp.asarray(cam.cy, dtype)

  center = -rot.T @ jnp.asarray(cam.translation, dtype)
  d = params.means - center
  dn = jnp.sqrt(jnp.sum(d * d, -1, keepdims=True))
  d = d / jnp.where(dn > 0, dn, 1.0)   # a Gaussian at the camera centre
  degree = params.sh_rest.shape[1] and sh.degree_of(params.sh_rest.shape[1])
  colors = sh.to_color(params.sh_dc, params.sh_rest, d,
                       degree if sh_degree is None else sh_degree)

  order = jnp.argsort(jnp.where(valid, z, jnp.inf), stable=True)
  h, w = cam.height, cam.width
  py, px = jnp.meshgrid(jnp.arange(h, dtype=dtype) + 0.5,
                        jnp.arange(w, dtype=dtype) + 0.5, indexing="ij")
  px, py = px.reshape(-1, 1), py.reshape(-1, 1)                  # [P, 1]
  dx, dy = px - u[order], py - v[order]                          # [P, N]
  power = 0.5 * (ca[order] * dx**2 + cc[order] * dy**2) + cb[order] * dx * dy
  raw = opac[order] * jnp.exp(-power)
  keep = valid[order] & (power >= 0) & (raw >= 1 / 255)
  alpha = jnp.where(keep, jnp.minimum(raw, 0.99), 0.0)
  # associative_scan: jnp.cumprod is O(N^2) on the CPU backend.
  t_after = jax.lax.associative_scan(jnp.multiply, 1 - alpha, axis=1)
  include = t_after >= 1e-4
  t_before = jnp.concatenate([jnp.ones_like(t_after[:, :1]),
                              t_after[:, :-1]], 1)
  wts = jnp.where(include, alpha * t_before, 0.0)
  t_final = jnp.prod(jnp.where(include, 1 - alpha, 1.0), axis=1)
  image = wts @ colors[order] + t_final[:, None] * background
  acc = 1 - t_final
  depth = wts @ z[order]
  depth = jnp.where(acc > 0, depth / jnp.where(acc > 0, acc, 1.0), 0.0)
  contrib = jnp.zeros_like(z).at[order].set(jnp.sum(wts, 0))
  out = dict(image=image.reshape(h, w, 3), alpha=acc.reshape(h, w),
             depth=depth.reshape(h, w), contribution=contrib)
  if evidence_map is not None:
    m = jax.lax.stop_gradient(jnp.asarray(evidence_map, dtype)).reshape(-1)
    out["evidence"] = jnp.zeros_like(z).at[order].set(
        jnp.sum(wts * m[:, None], 0))
  return out
