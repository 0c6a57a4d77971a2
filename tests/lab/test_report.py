"""clipgs_jax.report: metrics, colour and mask renders of a finished run."""

import dataclasses
import json
import os
import pathlib
import subprocess
import sys
import types

import jax.numpy as jnp
import numpy as np
import OpenImageIO as oiio
import pytest

from clipgs_jax import checkpoint
from clipgs_jax import config as config_lib
from clipgs_jax import config_file
from clipgs_jax import evaluation
from clipgs_jax import fileio
from clipgs_jax import guidance
from clipgs_jax.lab import loss_maps
from clipgs_jax.lab import report
from clipgs_jax import run as run_lib
from clipgs_jax import train
from clipgs_jax.data import default_scene
from clipgs_jax.data import scene as scene_lib

ROOT = pathlib.Path(__file__).resolve().parents[2]
DOWNSCALE = 4      # the embedded scene's 128x96 views become 32x24
HIGH, LOW = 0.02, 0.01   # s_j of the flagged / other Gaussians; tau 0.015


def _read_u8(path):
  """uint8 [H, W, channels] exactly as stored."""
  inp = oiio.ImageInput.open(str(path))
  assert inp is not None, path
  try:
    spec = inp.spec()
    pixels = inp.read_image(0, 0, 0, spec.nchannels, "uint8")
  finally:
    inp.close()
  return np.asarray(pixels).reshape(spec.height, spec.width, spec.nchannels)


def test_transient_selection():
  n = jnp.array([1.0, 1.0, 2.0, 0.0])
  stats = types.SimpleNamespace(acc=jnp.array([0.02, 0.01, 0.05, 0.0]),
                                weight=n, n=n)
  state = types.SimpleNamespace(
      semantic=stats, alive=jnp.array([True, True, False, True]),
      params=types.SimpleNamespace(opacity_logits=jnp.zeros(4)))
  # s = [0.02, 0.01, 0.025, 0 (n = 0)]; slot 2 is dead.
  np.testing.assert_array_equal(report.transient_selection(state, 0.015),
                                [True, False, False, False])
  # tau below 0 would take never-scored slots; 0 does not.
  np.testing.assert_array_equal(report.transient_selection(state, 0.0),
                                [True, True, False, False])


def test_mask_iou():
  alpha = np.array([[0.2, 0.6], [0.5, 0.9]], np.float32)
  mask = np.array([[False, True], [True, False]])
  # pred = alpha > 0.5 = [[F, T], [F, T]] (0.5 is not above): 1 / 3.
  assert evaluation.mask_iou(alpha, mask) == pytest.approx(1 / 3)
  assert evaluation.mask_iou(alpha, alpha > 0.5) == 1.0
  # Nothing predicted, something true: 0.
  assert evaluation.mask_iou(np.zeros((2, 2)), mask) == 0.0
  # Both empty: undefined.
  assert evaluation.mask_iou(np.zeros((2, 2)), np.zeros((2, 2), bool)) is None
  with pytest.raises(ValueError, match="mask_iou"):
    evaluation.mask_iou(np.zeros((2, 3)), mask)


def test_iou_summary_skips_empty_unions():
  alphas = np.array([[[0.9, 0.0]], [[0.0, 0.0]], [[0.9, 0.9]]])
  masks = np.array([[[True, True]], [[False, False]], [[True, False]]])
  out = evaluation.iou_summary(["a", "b", "c"], alphas, masks)
  # a: 1/2, b: empty union, c: 1/2 -> mean 0.5 over 2 views.
  assert out["per_view"] == {"a": 0.5, "b": None, "c": 0.5}
  assert out["mean"] == 0.5
  assert out["num_views_scored"] == 2
  assert out["alpha_threshold"] == 0.5
  assert evaluation.iou_summary(["b"], alphas[1:2], masks[1:2])["mean"] is None


@pytest.fixture(scope="module")
def saved_run(tmp_path_factory):
  """A run folder as experiments/train.py writes it, without training.

  The first half of the slots get s_j = HIGH > tau, the rest LOW.
  """
  workdir = tmp_path_factory.mktemp("run")
  scene_path = default_scene.ensure_default_scene()
  scene = scene_lib.load_scene(scene_path, downscale=DOWNSCALE)
  cfg = train.resolve(config_file.named("smoke"), scene)
  state = train.initial_state(cfg, scene)
  c = state.capacity
  high = jnp.arange(c) < c // 2
  state = state.replace(semantic=state.semantic.replace(
      acc=jnp.where(high, HIGH, LOW).astype(jnp.float32),
      weight=jnp.ones((c,), jnp.float32), n=jnp.ones((c,), jnp.float32)))
  checkpoint.save(str(workdir / train.CHECKPOINT_NAME), state, cfg, extra={})
  fileio.write_json(str(workdir / "run.json"), {
      "scene": os.path.abspath(scene_path), "embedded_scene": True,
      "downscale": DOWNSCALE, "train_split": "clutter", "preset": "smoke"})
  fileio.write_json(str(workdir / "config.json"), config_lib.to_dict(cfg))
  fileio.write_json(str(workdir / "metrics.json"),
                    {"test": {"psnr": 12.5}})
  expected = int(np.sum(np.asarray(state.alive & high)))
  return workdir, scene, expected


def _check_pngs(folder, scene, channels):
  names = sorted(os.listdir(folder))
  stems = sorted(os.path.splitext(n)[0] + ".png" for n in scene.train.names)
  assert names == stems
  h, w = scene.train.images.shape[1:3]
  pngs = [_read_u8(folder / n) for n in names]
  for p in pngs:
    assert p.shape == (h, w, channels) and p.dtype == np.uint8
  return dict(zip(names, pngs))


def test_render_masks_writes_pngs_and_iou(saved_run):
  workdir, scene, expected = saved_run
  assert expected > 0
  out = report.render_masks(str(workdir))
  block = out["mask_iou"]
  assert out["num_views"] == len(scene.train.names)
  pngs = _check_pngs(workdir / "renders" / "masks", scene, 1)
  assert max(int(p.max()) for p in pngs.values()) > 0
  with open(workdir / "metrics.json") as f:
    metrics = json.load(f)
  assert metrics["test"] == {"psnr": 12.5}      # kept
  assert metrics["mask_iou"] == block
  assert block["tau"] == 0.015
  assert block["num_gaussians_above_tau"] == expected
  assert set(block["per_view"]) == set(scene.train.names)
  assert 0 < block["num_views_scored"] <= len(scene.train.names)
  assert 0.0 <= block["mean"] <= 1.0
  scored = [v for v in block["per_view"].values() if v is not None]
  assert len(scored) == block["num_views_scored"]
  assert all(np.isfinite(scored))


def test_render_masks_nothing_above_tau(saved_run):
  workdir, scene, _ = saved_run
  block = report.render_masks(str(workdir), tau=1.0)["mask_iou"]
  pngs = _check_pngs(workdir / "renders" / "masks", scene, 1)
  assert all(int(p.max()) == 0 for p in pngs.values())
  has_transient = scene.train.masks.any(axis=(1, 2))
  # Empty prediction: IoU 0 where the mask has transients, else undefined.
  for name, has in zip(scene.train.names, has_transient):
    assert block["per_view"][name] == (0.0 if has else None)
  assert block["num_views_scored"] == int(has_transient.sum())
  assert block["mean"] == 0.0
  assert block["num_gaussians_above_tau"] == 0
  assert block["tau"] == 1.0


def test_render_rgb(saved_run):
  workdir, scene, _ = saved_run
  assert report.render_colour(str(workdir)).endswith("renders/train")
  pngs = _check_pngs(workdir / "renders" / "train", scene, 3)
  assert max(int(p.max()) for p in pngs.values()) > 0


def test_bad_workdir(tmp_path):
  missing = tmp_path / "nope"
  with pytest.raises(FileNotFoundError, match="not a folder"):
    report.render_masks(str(missing))
  with pytest.raises(FileNotFoundError, match="run.json is missing"):
    report.render_masks(str(tmp_path))
  fileio.write_json(str(tmp_path / "run.json"), {})
  fileio.write_json(str(tmp_path / "config.json"), {})
  with pytest.raises(FileNotFoundError, match="checkpoint.npz is missing"):
    report.render_colour(str(tmp_path))
  with pytest.raises(ValueError, match="source='pl'"):
    report.recompute_metrics(str(tmp_path), source="pl")


def test_render_masks_without_ground_truth(saved_run, monkeypatch):
  workdir, scene, _ = saved_run
  load_run = run_lib.load_run

  def without_masks(path):
    run, cfg, loaded = load_run(path)
    train_views = dataclasses.replace(loaded.train, masks=None)
    return run, cfg, dataclasses.replace(loaded, train=train_views)

  monkeypatch.setattr(run_lib, "load_run", without_masks)
  before = (workdir / "metrics.json").read_text()
  assert report.render_masks(str(workdir), tau=1.0)["mask_iou"] is None
  _check_pngs(workdir / "renders" / "masks", scene, 1)
  assert (workdir / "metrics.json").read_text() == before


def test_recompute_metrics(saved_run):
  workdir, scene, _ = saved_run
  with open(workdir / "metrics.json") as f:
    stored = json.load(f)
  fileio.write_json(str(workdir / "metrics.json"), stored | {"mark": 1})
  before = (workdir / "metrics.json").read_text()
  new, old, source = report.recompute_metrics(str(workdir), dry_run=True)
  assert (workdir / "metrics.json").read_text() == before
  assert source == "checkpoint" and old == {"psnr": 12.5}
  assert new["num_views"] == len(scene.test.names)
  assert new["lpips_net"] == "alex" and np.isfinite(new["psnr"])
  with pytest.raises(FileNotFoundError, match="point_cloud.ply is missing"):
    report.recompute_metrics(str(workdir), source="ply")
  again, _, _ = report.recompute_metrics(str(workdir))
  with open(workdir / "metrics.json") as f:
    metrics = json.load(f)
  assert metrics["test_source"] == "checkpoint"
  # As JSON text: LPIPS may be NaN here (no LPIPS weights under tests).
  drop = lambda d: json.dumps({k: v for k, v in d.items() if k != "seconds"},
                             sort_keys=True)
  assert drop(metrics["test"]) == drop(again)
  # The same Gaussians, rendered twice: the same numbers.
  assert again["psnr"] == new["psnr"] and again["ssim"] == new["ssim"]
  assert metrics["mark"] == 1     # the other blocks are kept


def _report_cli(*flags):
  env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
  return subprocess.run(
      [sys.executable, str(ROOT / "experiments" / "report.py"), *flags],
      capture_output=True, text=True, env=env, check=False, timeout=300)


def test_cli_curve(tmp_path):
  runs = []
  for name, offset in (("a", 15.0), ("b", 18.0)):
    folder = tmp_path / name
    folder.mkdir()
    fileio.write_json(str(folder / run_lib.CURVE_JSON), [
        {"step": s, "seconds": s / 10, "test_psnr": offset + s / 100}
        for s in (0, 100, 200)])
    runs.append(str(folder))
  png = tmp_path / "curve.png"
  proc = _report_cli("--report=curve", f"--runs={','.join(runs)}",
                     f"--curve_png={png}")
  assert proc.returncode == 0, proc.stderr
  assert png.stat().st_size > 1000
  # Several runs where one is needed: a usage error in one line.
  proc = _report_cli("--report=masks", f"--runs={','.join(runs)}")
  assert proc.returncode == 2
  assert proc.stderr.strip().splitlines()[-1].startswith(
      "error: --runs=")


def test_loss_map_scores_and_worst_views():
  pred = np.array([[True, True], [False, False]])
  truth = np.array([[True, False], [True, False]])
  s = loss_maps.view_scores(pred, truth)
  assert s == {"masked_fraction": 0.5, "transient_fraction": 0.5,
               "precision": 0.5, "recall": 0.5, "iou": 1 / 3}
  assert loss_maps.view_scores(pred, None) == {"masked_fraction": 0.5}
  picture = loss_maps.error_picture(pred, truth)
  np.testing.assert_array_equal(picture[0, 0], [0, 1, 0])   # hit
  np.testing.assert_array_equal(picture[0, 1], [1, 0, 0])   # false
  np.testing.assert_array_equal(picture[1, 0], [0, 0, 1])   # missed
  scores = {
      "good": {"masked_fraction": 0.1, "transient_fraction": 0.1,
               "iou": 0.9},
      "bad": {"masked_fraction": 0.3, "transient_fraction": 0.1, "iou": 0.2},
      "empty": {"masked_fraction": 0.0, "transient_fraction": 0.1,
                "iou": 0.0},
      "clean_fp": {"masked_fraction": 0.2, "transient_fraction": 0.0,
                   "iou": 0.0},
      "clean_ok": {"masked_fraction": 0.0, "transient_fraction": 0.0,
                   "iou": None}}
  assert loss_maps.worst_views(scores, 2) == {
      "lowest_iou": ["empty", "bad"], "clean_most_masked": ["clean_fp"]}


@pytest.fixture(scope="module")
def residual_run(tmp_path_factory):
  """A residual-map run folder with its threshold set, without training."""
  workdir = tmp_path_factory.mktemp("residual_run")
  scene_path = default_scene.ensure_default_scene()
  scene = scene_lib.load_scene(scene_path, downscale=DOWNSCALE)
  smoke = config_file.named("smoke")
  cfg = train.resolve(dataclasses.replace(
      smoke,
      semantic=dataclasses.replace(smoke.semantic, scorer="residual",
                                   evidence="pixel"),
      pixel=dataclasses.replace(smoke.pixel, loss_masking=True),
      residual=dataclasses.replace(smoke.residual, warmup=0.0)), scene)
  state = train.initial_state(cfg, scene)
  state = state.replace(maps=state.maps.replace(threshold=jnp.float32(0.1)))
  checkpoint.save(str(workdir / train.CHECKPOINT_NAME), state, cfg, extra={})
  fileio.write_json(str(workdir / "run.json"), {
      "scene": os.path.abspath(scene_path), "embedded_scene": True,
      "downscale": DOWNSCALE, "train_split": "clutter"})
  fileio.write_json(str(workdir / "config.json"), config_lib.to_dict(cfg))
  return workdir, scene, cfg, state


def test_loss_map_report(residual_run):
  workdir, scene, cfg, state = residual_run
  proc = _report_cli("--report=loss_maps", f"--runs={workdir}", "--views=2")
  assert proc.returncode == 0, proc.stderr
  assert "precision" in proc.stdout, proc.stdout
  with open(workdir / loss_maps.LOSS_MAPS_JSON) as f:
    out = json.load(f)
  assert sorted(out["per_view"]) == sorted(scene.train.names)
  # The pooled numbers are the run's own mask quality (what metrics.json
  # and the curve report), from the same maps.
  degree = np.int32(state.params.sh_degree)
  quality = evaluation.mask_quality(
      state.params, state.alive, state.maps,
      guidance.make_scorer(cfg, scene), scene.train, cfg, degree)
  for key in ("precision", "recall", "iou"):
    assert out["pooled"][key] == pytest.approx(quality[key])
  # The 3x3 rule and the gates only take pixels away, and the last
  # (the share floor, after the smoke config's alpha gate) is the map the
  # loss uses.
  stages = out["pooled"]["stages"]
  names = ("threshold", "rule", "alpha", "share")
  assert set(stages) == set(names)
  recalls = [stages[k]["recall"] for k in names]
  assert recalls == sorted(recalls, reverse=True)
  assert stages["share"]["recall"] == pytest.approx(quality["recall"])
  for key in ("precision", "iou"):
    assert stages["share"][key] == pytest.approx(quality[key])
  assert "recall after each step" in proc.stdout
  for name in out["worst"]["clean_most_masked"]:
    assert out["per_view"][name]["transient_fraction"] == 0.0
  assert len(out["worst"]["lowest_iou"]) == 2
  assert (workdir / loss_maps.LOSS_MAPS_PNG).stat().st_size > 1000


def test_loss_map_report_needs_pixel_evidence(saved_run):
  workdir, _, _ = saved_run
  with pytest.raises(ValueError, match="no per-pixel map"):
    loss_maps.loss_map_report(str(workdir))


def test_contrast_counts():
  truth = np.array([[True, True, True, False]])
  photo = np.zeros((1, 4, 3), np.float32)
  behind = np.full((1, 4, 3), 0.5, np.float32)   # 0.5 from the photo
  behind[0, 0] = 0.05                             # under the threshold
  render = np.full((1, 4, 3), 0.5, np.float32)
  render[0, 1] = 0.0                              # the transient fitted
  np.testing.assert_array_equal(
      loss_maps.contrast_counts(photo, render, behind, truth, 0.15),
      [3, 2, 1])


def test_loss_map_contrast_against_a_clean_run(residual_run):
  workdir, scene, _, _ = residual_run
  # The run as its own clean twin: what lies behind is its own render, so
  # nothing is baked and every reachable pixel passes the threshold.
  out = loss_maps.loss_map_report(str(workdir), 1, clean_run=str(workdir))
  c = out["pooled"]["contrast"]
  assert c["threshold"] == pytest.approx(0.1)
  assert c["baked"] == 0.0
  assert c["reachable"] == pytest.approx(
      out["pooled"]["stages"]["threshold"]["recall"], abs=0.02)
  assert 0.0 < c["reachable"] <= 1.0
  cams = scene.train.cameras
  assert loss_maps.same_cameras(cams, cams)
  assert not loss_maps.same_cameras(cams, dataclasses.replace(
      cams, translation=np.asarray(cams.translation) + 0.1))
