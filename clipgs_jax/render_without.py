"""What eq. 13's semantic clause would cost the views that see its rows.

A row can have most of its blending weight on pixels a residual map marked
(s_j > tau_p) and still be static scene that the other views need: a window
whose bright edge the map marks in the few views that see it, not yet fit
where it is overexposed. Ghosts of transients draw what most views do not
show. The test renders each training view where some candidate is on screen
with every alive row and again without the candidates, and calls a pixel
harmed where the residual |render - photo| (mean over channels) without them
is larger by more than HARM_TOLERANCE, marked or not. A candidate with at
least `semantic.prune_harm` of its blending weight over the training views
on harmed pixels is spared.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import camera as camera_lib
from clipgs_jax import config as config_lib
from clipgs_jax.maps import residual
from clipgs_jax.render import project as project_lib
from clipgs_jax.render import rasterize

# A pixel is harmed by removing rows when its mean absolute colour error
# rises by more than this (13/255): above a fitted render's L1 error on the
# benchmarks, below the contrast of a pasted object against what it hides.
HARM_TOLERANCE = 0.05


@functools.lru_cache(maxsize=None)
def _view_fn(render_cfg: config_lib.RenderConfig):
  def fn(params, alive, candidates, cam, photo, valid_size, background,
         degree, threshold):
    def draw(rows):
      proj = project_lib.project(params, rows, cam, near=render_cfg.near,
                                 sh_degree=degree)
      return proj, rasterize.rasterize(proj, cam, background, render_cfg,
                                       valid_size=valid_size)
    proj, kept = draw(alive)
    _, without = draw(alive & ~candidates)
    harmed = (residual.residual(without.image, photo)
              - residual.residual(kept.image, photo)) > threshold
    out = rasterize.rasterize(proj, cam, background, render_cfg,
                              evidence_map=harmed.astype(photo.dtype),
                              valid_size=valid_size)
    return (jnp.where(candidates, out.contribution, 0.0),
            jnp.where(candidates, out.evidence, 0.0), jnp.sum(harmed))
  return jax.jit(fn)


@functools.lru_cache(maxsize=None)
def _on_screen_fn(near: float):
  def fn(params, candidates, cam, valid_size, degree):
    proj = project_lib.project(params, candidates, cam, near=near,
                               sh_degree=degree)
    lo = proj.means2d - proj.extents
    hi = proj.means2d + proj.extents
    inside = ((hi[:, 0] >= 0) & (hi[:, 1] >= 0)
              & (lo[:, 0] < valid_size[0]) & (lo[:, 1] < valid_size[1]))
    return jnp.any(proj.valid & inside)
  return jax.jit(fn)


def harmed_share(params, alive, candidates, views, threshold, degree,
                 cfg: config_lib.Config) -> tuple[np.ndarray, int, int]:
  """Per row, the share of its blending weight over `views` that falls on
  pixels whose residual the candidates lower by more than `threshold` (0
  off `candidates`).

  Args:
    params, alive: the model now.
    candidates: bool [C], the rows the test would remove together.
    views: data.scene.Views, the training views.
    threshold: float, a mean absolute colour error in [0, 1].
    degree: int32 [], the SH degree the steps use now.
    cfg: the run's config (render settings and background).
  Returns:
    (float64 [C] share, int number of harmed pixels over the views, int
    number of views rendered: those where some candidate is on screen).
  """
  fn = _view_fn(cfg.render)
  on_screen = _on_screen_fn(cfg.render.near)
  background = jnp.asarray(cfg.train.background, jnp.float32)
  cams = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), views.cameras)
  candidates = jnp.asarray(candidates)
  weight = np.zeros(params.capacity)
  harmed = np.zeros(params.capacity)
  pixels = tested = 0
  for i in range(len(views)):
    cam = camera_lib.camera_at(cams, i)
    size = None if views.sizes is None else jnp.asarray(views.sizes[i])
    canvas = jnp.asarray([cam.width, cam.height], jnp.float32)
    if not on_screen(params, candidates, cam,
                     canvas if size is None else size, degree):
      continue
    tested += 1
    w, h, count = fn(params, alive, candidates, cam,
                     jnp.asarray(views.images[i], jnp.float32), size,
                     background, degree, jnp.float32(threshold))
    weight += np.asarray(w, np.float64)
    harmed += np.asarray(h, np.float64)
    pixels += int(count)
  share = np.where(weight > 0, harmed / np.maximum(weight, 1e-12), 0.0)
  return share, pixels, tested
