"""clipgs_jax.evidence: ghost labels and pixel evidence of a finished run."""

import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from clipgs_jax import camera as camera_lib
from clipgs_jax import checkpoint
from clipgs_jax import config as config_lib
from clipgs_jax import config_file
from clipgs_jax import fileio
from clipgs_jax import train
from clipgs_jax.data import billboards
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.lab import ghost_evidence
from clipgs_jax.render import rasterize
from test_billboards import built  # pylint: disable=unused-import,g-bad-import-order

NUM_GHOSTS = 3          # Gaussians put on the first billboard


def test_on_billboard_geometry():
  # The unit square in z = 0 seen from distance 1: depth tolerance 0.1,
  # margin 0.05 of each side.
  corners = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
  points = np.array([
      [0.5, 0.5, 0.0], [0.5, 0.5, 0.09], [0.5, 0.5, -0.09],   # in
      [1.04, 0.5, 0.0], [-0.04, -0.04, 0.05],                 # in (margin)
      [0.5, 0.5, 0.11], [0.5, 0.5, -0.11],                    # too deep
      [1.06, 0.5, 0.0], [0.5, -0.06, 0.0]])                   # outside
  got = billboards.on_billboard(points, corners, viewing_distance=1.0)
  np.testing.assert_array_equal(got, [1, 1, 1, 1, 1, 0, 0, 0, 0])
  # The tolerance scales with the viewing distance.
  assert billboards.on_billboard(points[5:6], corners, 2.0)[0]


def test_summarize_counts_by_hand():
  scores = np.array([0.1, 0.6, 0.7, 0.2, 0.9, 0.95])
  weight = np.array([2.0, 2.0, 0.5, 2.0, 2.0, 2.0])  # row 2: below the floor
  ghost = np.array([True, True, True, False, False, False])
  alive = np.array([True, True, True, True, True, False])
  out = ghost_evidence.summarize(scores, weight, ghost, alive, tau=0.5, bins=2)
  assert out["edges"] == [0.0, 0.5, 1.0]
  assert out["ghost"] == {"num": 2, "counts": [1, 1], "median": 0.35,
                          "above_tau": 1}
  assert out["other"] == {"num": 2, "counts": [1, 1],
                          "median": pytest.approx(0.55), "above_tau": 1}
  assert out["precision"] == 0.5 and out["recall"] == 0.5
  # Only the last row alive: one false positive, no ghost to recall.
  last = ghost_evidence.summarize(scores, weight, ghost, ~alive, tau=0.5,
                                  bins=2)
  assert last["precision"] == 0.0 and last["recall"] is None
  assert last["ghost"]["median"] is None
  none = ghost_evidence.summarize(scores, weight, ghost, alive & False, 0.5, 2)
  assert none["precision"] is None and none["other"]["counts"] == [0, 0]


def test_needs_billboards():
  with pytest.raises(ValueError, match="--mode=persistent"):
    ghost_evidence.ghost_rows(np.zeros((1, 3)), {"mode": "independent"}, None)


@pytest.fixture(scope="module")
def saved_run(built, tmp_path_factory):  # pylint: disable=redefined-outer-name
  """A run folder on the f=1.0 billboard benchmark, without training: the
  SfM initialisation plus NUM_GHOSTS Gaussians around billboard 0."""
  root, _ = built
  path = str(root / "f1.0")
  with open(os.path.join(path, "transients.json")) as f:
    manifest = json.load(f)
  scene = scene_lib.load_scene(path)
  cfg = train.resolve(config_file.named("smoke"), scene)
  state = train.initial_state(cfg, scene)
  free = np.flatnonzero(~np.asarray(state.alive))[:NUM_GHOSTS]
  corners = np.asarray(manifest["billboards"][0]["corners"])
  on_board = corners[0] + np.array([[0.5, 0.5], [0.3, 0.6], [0.7, 0.4]]) @ (
      np.stack([corners[1] - corners[0], corners[3] - corners[0]]))
  p = state.params
  params = p.replace(
      means=p.means.at[free].set(on_board.astype(np.float32)),
      log_scales=p.log_scales.at[free].set(np.log(0.05)),
      quats=p.quats.at[free].set(jnp.array([1.0, 0, 0, 0])),
      opacity_logits=p.opacity_logits.at[free].set(3.0))
  state = state.replace(params=params, alive=state.alive.at[free].set(True))
  workdir = tmp_path_factory.mktemp("evidence_run")
  checkpoint.save(str(workdir / train.CHECKPOINT_NAME), state, cfg, extra={})
  fileio.write_json(str(workdir / "run.json"), {
      "scene": path, "embedded_scene": False, "downscale": 1,
      "train_split": "clutter"})
  fileio.write_json(str(workdir / "config.json"), config_lib.to_dict(cfg))
  return workdir, scene, cfg, state, free, manifest


def test_ghost_rows_are_the_billboard_rows(saved_run):  # pylint: disable=redefined-outer-name
  _, scene, _, state, free, manifest = saved_run
  ghost = ghost_evidence.ghost_rows(state.params.means, manifest, scene.train)
  assert ghost[free].all()
  # The rest of the cloud (radius <= 0.87 about the origin) stands behind
  # every billboard.
  assert int(ghost[np.asarray(state.alive)].sum()) == NUM_GHOSTS


def test_pixel_evidence_bounds_and_limits(saved_run):  # pylint: disable=redefined-outer-name
  _, scene, cfg, state, free, _ = saved_run
  sums = ghost_evidence.pixel_evidence(state.params, state.alive,
                                       scene.train, cfg)
  w, raw, rep = sums["weight"], sums["raw"], sums["reproduced"]
  assert (w > 0).sum() > NUM_GHOSTS
  assert np.all(raw <= w + 1e-4) and np.all(rep <= raw + 1e-4)
  assert np.all(rep >= 0)
  # The ghosts lie on masked pixels in the billboard's views, and are seen
  # unmasked from the others: a share strictly between 0 and 1.
  share = raw[free] / w[free]
  assert np.all(share > 0.05) and np.all(share < 0.95), share
  # Every pixel masked: raw evidence is the whole weight.
  views = scene.train
  ones = dataclasses.replace(views, masks=np.ones_like(views.masks))
  full = ghost_evidence.pixel_evidence(state.params, state.alive, ones, cfg)
  np.testing.assert_allclose(full["raw"], full["weight"], rtol=1e-6,
                             atol=1e-6)
  h, w = views.masks.shape[1:]
  assert full["pixels"][1] == len(views) * h * w and full["pixels"][3] == 0
  # Photos equal to the renders: agreement is 1, reproduced equals raw.
  bg = jnp.asarray(cfg.train.background, jnp.float32)
  render = jax.jit(lambda cam: rasterize.render(
      state.params, state.alive, cam, bg, cfg.render).image)
  cams = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), views.cameras)
  renders = np.stack([np.asarray(render(camera_lib.camera_at(cams, i)))
                      for i in range(len(views))])
  same = dataclasses.replace(views, images=renders)
  agreed = ghost_evidence.pixel_evidence(state.params, state.alive, same, cfg)
  np.testing.assert_allclose(agreed["reproduced"], agreed["raw"],
                             rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(agreed["pixels"][[0, 2]],
                             agreed["pixels"][[1, 3]], rtol=1e-6)
  assert agreed["pixels"][1] == views.masks.sum()


def test_report_writes_json_and_png(saved_run):  # pylint: disable=redefined-outer-name
  workdir, scene, _, _, _, _ = saved_run
  out = ghost_evidence.evidence_report(str(workdir), bins=5)
  with open(workdir / ghost_evidence.EVIDENCE_JSON) as f:
    assert json.load(f) == json.loads(json.dumps(out))
  assert os.path.getsize(workdir / ghost_evidence.EVIDENCE_PNG) > 0
  assert out["num_ghost"] == NUM_GHOSTS
  assert out["num_views"] == len(scene.train)
  assert 0 < out["ghost_weight_share"] < out["ghost_masked_share"] < 1
  assert 0 <= out["masked_agreement"] <= 1
  for value in out["pixel_agreement"].values():
    assert 0 <= value <= 1
  assert out["run_scores"] is None      # the smoke config runs no guidance
  for block in out["rules"].values():
    assert len(block["edges"]) == 6 and block["tau"] == 0.5
    for name in ("ghost", "other"):
      assert sum(block[name]["counts"]) == block[name]["num"]
