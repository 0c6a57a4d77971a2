"""clipgs_jax.table and sweep: rows, Markdown, and a table end to end."""

import dataclasses
import json
import os
import pathlib
from unittest import mock

from absl import app
from absl.testing import absltest
import numpy as np

from clipgs_jax import config
from clipgs_jax import config_file
from clipgs_jax import fileio
from clipgs_jax import guidance_config
from clipgs_jax import run as run_lib
from clipgs_jax.lab import sweep
from clipgs_jax.lab import table
from clipgs_jax.data import default_scene


def _metrics(psnr, *, fraction_pruned=None, label=None, num=1000):
  """A hand-made metrics.json dict."""
  m = {"test": {"psnr": psnr, "ssim": 0.5, "lpips": 0.25,
                "lpips_net": "alex"},
       "train_seconds": 12.0, "steps": 30, "num_gaussians": num}
  if fraction_pruned is not None:
    m["semantic"] = {"label": label, "fraction_pruned": fraction_pruned}
  return m


def _table_cd():
  return config_file.load_file(os.path.join(config_file.CONFIGS_DIR, "table.py"))


def _row_cfg(row: str) -> config.Config:
  return sweep.row_config(_table_cd(), row)


class FormatTest(absltest.TestCase):

  def _rows(self):
    oracle_label = ("CLIP-GS machinery, ORACLE scorer (ground-truth masks, "
                    "not CLIP)")
    return table.add_deltas([
        table.collect_row("s", "vanilla", _row_cfg("vanilla"),
                          _metrics(20.0)),
        table.collect_row("s", "oracle", _row_cfg("oracle"), _metrics(
            21.5, fraction_pruned=0.125, label=oracle_label, num=900)),
        table.collect_row("s", "clip", _row_cfg("clip"), None,
                          "error: no weights"),
        table.collect_row("s", "clean", _row_cfg("clean"), _metrics(24.0)),
    ])

  def test_collect_and_deltas(self):
    rows = {r["row"]: r for r in self._rows()}
    self.assertIn("ORACLE", rows["oracle"]["method"])
    # Oracle: 21.5 - 20.0 = +1.5 over vanilla, 24.0 - 21.5 = 2.5 below clean.
    self.assertAlmostEqual(rows["oracle"]["delta_psnr"], 1.5)
    self.assertAlmostEqual(rows["oracle"]["gap_to_clean"], 2.5)
    self.assertAlmostEqual(rows["oracle"]["fraction_pruned"], 0.125)
    self.assertIsNone(rows["vanilla"]["delta_psnr"])
    self.assertAlmostEqual(rows["vanilla"]["gap_to_clean"], 4.0)
    self.assertIsNone(rows["vanilla"]["fraction_pruned"])
    self.assertEqual(rows["clip"]["status"], "failed")
    self.assertIn("CLIP-GS (ViT-B/32", rows["clip"]["method"])
    self.assertIsNone(rows["clip"]["delta_psnr"])
    self.assertEqual(rows["clean"]["status"], "ok")
    self.assertEqual(rows["clean"]["method"],
                     "3DGS on clean views (upper bound)")

  def test_oracle_label_forced_and_nan(self):
    m = _metrics(float("nan"), fraction_pruned=1.0, label="something")
    r = table.collect_row("s", "oracle", _row_cfg("oracle"), m)
    self.assertIn("ORACLE", r["method"])
    self.assertIsNone(r["psnr"])  # Non-finite: None, so JSON stays valid.
    json.dumps(r, allow_nan=False)

  def test_mask_iou_only_where_something_was_pruned(self):
    label = "CLIP-GS machinery, ORACLE scorer (ground-truth masks, not CLIP)"
    iou = lambda n, mean: {"num_gaussians": n, "mean": mean}
    m = _metrics(21.0, fraction_pruned=0.0, label=label)
    m["semantic"]["pruned_mask_iou"] = iou(0, 0.0)  # every prune refused
    self.assertIsNone(
        table.collect_row("s", "oracle", _row_cfg("oracle"), m)["mask_iou"])
    m["semantic"]["pruned_mask_iou"] = iou(65, 0.25)
    self.assertAlmostEqual(
        table.collect_row("s", "oracle", _row_cfg("oracle"), m)["mask_iou"],
        0.25)

  def test_map_quality_and_the_control_against_clean(self):
    label = "residual map (sls, no weights, no oracle), loss masking"
    residual = _metrics(23.0, fraction_pruned=0.1, label=label)
    residual["semantic"]["mask_quality"] = {
        "precision": 0.8, "recall": 0.7, "iou": 0.6}
    control = _metrics(23.5, fraction_pruned=0.0, label=label)
    rows = table.add_deltas([
        table.collect_row("s", "vanilla", _row_cfg("vanilla"),
                          _metrics(20.0)),
        table.collect_row("s", "clean", _row_cfg("clean"), _metrics(24.0)),
        table.collect_row("s", "residual", _row_cfg("residual"), residual),
        table.collect_row("s", "residual_clean", _row_cfg("residual_clean"),
                          control)])
    by_row = {r["row"]: r for r in rows}
    self.assertAlmostEqual(by_row["residual"]["delta_psnr"], 3.0)
    self.assertEqual(by_row["residual"]["map_recall"], 0.7)
    # The control trains on the clean views: measured against clean.
    self.assertAlmostEqual(by_row["residual_clean"]["delta_psnr"], -0.5)
    text = table.format_markdown(rows, {"lpips_net": "alex"})
    self.assertIn("| 0.80 / 0.70 / 0.60 | +3.00 |", text)

  def test_markdown(self):
    text = table.format_markdown(self._rows(), {"steps": 30,
                                                "lpips_net": "alex"})
    self.assertIn("- steps: 30", text)
    self.assertIn("LPIPS (alex)", text)
    body = [l for l in text.splitlines() if l.startswith("| s |")]
    self.assertLen(body, 4)
    vanilla, oracle, clip, clean = body
    self.assertIn("ORACLE", oracle)
    self.assertIn("| 21.50 |", oracle)
    self.assertIn("| 0.125 | n/a | — | +1.50 | +2.50 |", oracle)
    self.assertIn("| — | — | — | +4.00 |", vanilla)
    self.assertIn("FAILED (error: no weights)", clip)
    self.assertIn("| 24.00 |", clean)
    self.assertTrue(clean.endswith("| — | — | — | — |"), clean)

  def test_a_flag_a_row_overrides_is_refused(self):
    keys = sweep.command_line_keys(
        ["train.py", "--config=configs/table.py",
         "--config.pixel.loss_masking=False", "--scene=X"])
    self.assertEqual(keys, {"pixel.loss_masking"})
    cd = _table_cd()
    cd.pixel.loss_masking = False   # as the flag leaves it
    sweep.check_row_overrides(cd, ["vanilla", "clean"], keys)
    with self.assertRaisesRegex(app.UsageError,
                                "does not reach row 'residual'"):
      sweep.check_row_overrides(cd, ["vanilla", "residual"], keys)
    cd.pixel.loss_masking = True    # the row's own value: no conflict
    sweep.check_row_overrides(cd, ["residual"], keys)

  def test_row_configs(self):
    # The rows of configs/table.py: the old table.py flags, as overrides.
    cfgs = {row: _row_cfg(row) for row in _table_cd().sweep.rows.split(",")}
    self.assertEqual(list(cfgs), [
        "vanilla", "oracle", "oracle_pixel", "oracle_pixel_masked", "clip",
        "clip_pixel", "residual", "residual_features",
        "residual_features_remember", "learned", "oracle_patch_residual",
        "clip_residual", "clean", "residual_clean", "residual_features_clean",
        "residual_features_remember_clean", "learned_clean"])
    bench = config_file.named("benchmark")
    sem = bench.semantic      # scaled to the steps
    self.assertEqual(cfgs["vanilla"].semantic.scorer, "off")
    self.assertEqual(cfgs["clean"].data.train_split, "clean")
    self.assertEqual(
        cfgs["oracle"].semantic,
        guidance_config.SemanticConfig(scorer="oracle").scaled_to(
            bench.train.steps))
    self.assertEqual(cfgs["oracle_pixel_masked"].semantic.evidence, "pixel")
    self.assertTrue(cfgs["oracle_pixel_masked"].pixel.loss_masking)
    self.assertEqual(cfgs["clip_pixel"].semantic.scorer, "clip")
    # The residual rows: the residual map (with feature regions, or gated
    # by a semantic map) and loss masking, with the benchmark's loss (L1 +
    # D-SSIM, as the ORACLE rows); their controls train on the clean twins.
    residual_rows = ("residual", "residual_features", "oracle_patch_residual",
                     "clip_residual", "residual_clean",
                     "residual_features_clean")
    for row in residual_rows:
      self.assertTrue(cfgs[row].uses_residual, row)
      self.assertTrue(cfgs[row].pixel.loss_masking, row)
    self.assertEqual(cfgs["residual_features"].residual.features, "alex")
    self.assertEqual(cfgs["oracle_patch_residual"].semantic.scorer,
                     "oracle_patch")
    self.assertEqual(cfgs["residual_features_clean"].data.train_split,
                     "clean")
    self.assertTrue(cfgs["residual_features_remember"].residual.remember)
    self.assertEqual(
        cfgs["residual_features_remember"].residual,
        dataclasses.replace(cfgs["residual_features"].residual,
                            remember=True))
    for row, control in (("residual_features", "residual_features_clean"),
                         ("residual_features_remember",
                          "residual_features_remember_clean"),
                         ("learned", "learned_clean")):
      for section in ("semantic", "pixel", "residual", "learned"):
        self.assertEqual(getattr(cfgs[control], section),
                         getattr(cfgs[row], section), control)
    self.assertEqual(cfgs["learned"].semantic.scorer, "learned")
    self.assertTrue(cfgs["learned"].pixel.loss_masking)
    for row, cfg in cfgs.items():   # everything else is the benchmark's
      self.assertEqual(cfg.render, bench.render)
      self.assertEqual(cfg.train, bench.train)
      self.assertEqual(cfg.semantic.prune_start, sem.prune_start)

  def test_residual_labels_name_the_regions(self):
    # A map voted over feature regions says so, alone or gated by a
    # semantic map (the demo's row with --clip_weights); one without
    # regions does not.
    demo = config_file.load_file(
        os.path.join(config_file.CONFIGS_DIR, "demo.py"))
    gated = sweep.row_config(
        demo, "residual", None,
        **demo.sweep.clip_overrides.residual.to_dict())
    self.assertIn("gating the residual map (sls, alex feature regions)",
                  run_lib.semantic_label(gated))
    self.assertIn("residual map (sls, alex feature regions, no weights",
                  run_lib.semantic_label(_row_cfg("residual_features")))
    self.assertNotIn("regions", run_lib.semantic_label(_row_cfg("residual")))
    self.assertNotIn("regions", run_lib.semantic_label(
        _row_cfg("oracle_patch_residual")))
    # A vote share other than SLS-agg's majority is a different row.
    features = _row_cfg("residual_features")
    self.assertNotIn("masked at", run_lib.semantic_label(features))

    def with_residual(**fields):
      return dataclasses.replace(features, residual=dataclasses.replace(
          features.residual, **fields))
    strict = with_residual(vote=0.7)
    self.assertIn("alex feature regions masked at 0.7 failing",
                  run_lib.semantic_label(strict))
    # So is an early uniformity gate other than the default's 0.35.
    self.assertNotIn("even", run_lib.semantic_label(strict))
    self.assertIn("failing, early only where even (std / mean < 0.5)",
                  run_lib.semantic_label(with_residual(vote=0.7,
                                                       uniformity=0.5)))
    self.assertIn("failing, no early uniformity gate", run_lib.semantic_label(
        with_residual(vote=0.7, uniformity=0.0)))


class ConfigChangesTest(absltest.TestCase):

  def test_names_what_differs(self):
    folder = self.create_tempdir().full_path
    cfg = config_file.named("smoke")
    stored = config.to_dict(dataclasses.replace(cfg, scene_extent=2.5))
    path = os.path.join(folder, "config.json")
    fileio.write_json(path, stored)
    # The run resolved scene_extent from its scene: not a difference.
    self.assertEqual(sweep.config_changes(folder, cfg), [])
    self.assertEqual(sweep.config_changes(folder, dataclasses.replace(
        cfg, train=dataclasses.replace(cfg.train, seed=7))),
                     [f"train.seed: {cfg.train.seed} -> 7"])
    # A field the run's config lacks: the run did not have it.
    del stored["residual"]["min_alpha"]
    fileio.write_json(path, stored)
    self.assertEqual(sweep.config_changes(folder, cfg), [
        f"residual.min_alpha: None -> {cfg.residual.min_alpha}"])
    # A run written with the old names (config.RENAMED) is the same run.
    stored = config.to_dict(cfg)
    stored["semantic"]["residual_min_alpha"] = stored["residual"].pop(
        "min_alpha")
    fileio.write_json(path, stored)
    self.assertEqual(sweep.config_changes(folder, cfg), [])
    with open(path, "w") as f:
      f.write("[1, 2]")
    self.assertIn("is not a config", sweep.config_changes(folder, cfg)[0])


class EndToEndTest(absltest.TestCase):

  def _cd(self, scene):
    cd = _table_cd()
    smoke = config_file.load_file(os.path.join(config_file.CONFIGS_DIR, "smoke.py"))
    for section in ("gaussians", "densify", "train"):
      cd[section].update(smoke[section])
    cd.train.steps = 10
    cd.data.downscale = 4
    cd.eval.curve_points = 1
    cd.sweep.rows = "vanilla,oracle_pixel,clean"
    cd.sweep.benchmarks = scene
    return cd

  def test_three_rows_then_all_skipped(self):
    scene = default_scene.ensure_default_scene()
    root = self.create_tempdir().full_path
    sweep.run(self._cd(scene), root)
    with open(os.path.join(root, "table.json")) as f:
      out = json.load(f)
    rows = out["rows"]
    self.assertEqual([r["row"] for r in rows],
                     ["vanilla", "oracle_pixel", "clean"])
    for r in rows:
      self.assertEqual(r["status"], "ok", r)
      self.assertEqual(r["steps"], 10)
      self.assertIsInstance(r["psnr"], float)
      self.assertGreater(r["train_seconds"], 0.0)
    self.assertIsNotNone(rows[1]["fraction_pruned"])
    self.assertIsNotNone(rows[1]["delta_psnr"])
    self.assertEqual(out["settings"]["steps"], 10)
    text = pathlib.Path(root, "table.md").read_text()
    self.assertIn("ORACLE", text)
    self.assertLen([l for l in text.splitlines()
                    if l.startswith(f"| {os.path.basename(scene)} |")], 3)
    # Again: every row is finished, nothing trains.
    with mock.patch.object(run_lib, "train_and_evaluate") as train:
      again = sweep.run(self._cd(scene), root)
    train.assert_not_called()
    self.assertEqual([r["psnr"] for r in again["rows"]],
                     [r["psnr"] for r in rows])
    # Another seed into the same folders: the finished runs are not
    # reported as its rows (they used to be, silently), nor overwritten.
    cd = self._cd(scene)
    cd.train.seed = 1
    with mock.patch.object(run_lib, "train_and_evaluate") as train, \
        self.assertRaisesRegex(ValueError, "failed"):
      sweep.run(cd, root)
    train.assert_not_called()
    with open(os.path.join(root, "table.json")) as f:
      other = json.load(f)
    for r in other["rows"]:
      self.assertNotEqual(r["status"], "ok", r)
      self.assertIn("holds a finished run of another config (train.seed: "
                    "0 -> 1)", r["error"])

  def test_demo_writes_the_comparison(self):
    cd = config_file.load_file(os.path.join(config_file.CONFIGS_DIR, "demo.py"))
    smoke = config_file.load_file(os.path.join(config_file.CONFIGS_DIR, "smoke.py"))
    cd.gaussians.update(smoke.gaussians)
    cd.train.steps = 10
    # demo.py asks for 10 curve points, i.e. a test evaluation at every one
    # of these 10 steps in every row: most of this test's time, and not
    # what it checks.
    cd.eval.curve_points = 1
    root = self.create_tempdir().full_path
    summary = sweep.run(cd, root)
    self.assertEqual(sorted(os.listdir(root)),
                     ["comparison.json", "comparison.png",
                      "oracle_pixel_masked", "residual", "vanilla"])
    self.assertEqual(summary["vanilla"]["label"], "vanilla 3DGS")
    # The row the demo shows needs nothing but the photos; the reference
    # says it reads the ground truth.
    self.assertIn("residual map (sls, alex feature regions",
                  summary["residual"]["label"])
    self.assertNotIn("ORACLE", summary["residual"]["label"])
    self.assertIn("ORACLE-PIXEL", summary["oracle_pixel_masked"]["label"])
    scorers, cfg_of = {}, {}
    for row in ("residual", "oracle_pixel_masked"):
      with open(os.path.join(root, row, "config.json")) as f:
        cfg = cfg_of[row] = json.load(f)
      self.assertEqual(cfg["train"]["checkpoint_every"], 10)
      self.assertTrue(cfg["pixel"]["loss_masking"])
      scorers[row] = cfg["semantic"]["scorer"]
    self.assertEqual(scorers, {"residual": "residual",
                               "oracle_pixel_masked": "oracle"})
    # The table's best row that needs only the photos: regions voted.
    self.assertEqual(cfg_of["residual"]["residual"]["features"], "alex")
    # One row (it used to stop with an IndexError after training): its
    # finished run is not trained again, and the comparison shows it alone.
    cd.sweep.rows = "residual"
    with mock.patch.object(run_lib, "train_and_evaluate") as train:
      one = sweep.run(cd, root)
    train.assert_not_called()
    self.assertEqual(sorted(one), ["residual", "view"])

  def test_demo_view_is_where_the_oracle_gains_most(self):
    psnr = {"vanilla": np.array([20.0, 18.0, 25.0]),
            "residual": np.array([26.0, 19.0, 25.0]),
            "oracle_pixel_masked": np.array([21.0, 24.0, 25.0])}
    oracle = {"vanilla": False, "residual": False,
              "oracle_pixel_masked": True}
    # The transients cost vanilla most in view 1, not where the shown row
    # changes most (view 0).
    self.assertEqual(sweep.demo_view(psnr, oracle), 1)
    del psnr["oracle_pixel_masked"]
    self.assertEqual(sweep.demo_view(psnr, oracle), 0)
    self.assertEqual(sweep.demo_view({"vanilla": psnr["vanilla"]}, oracle),
                     1)


if __name__ == "__main__":
  absltest.main()
