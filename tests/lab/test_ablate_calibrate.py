"""configs/ablate.py and tau_sweep.py: rows, Otsu, Markdown, the plot."""

import os
from unittest import mock

from absl.testing import absltest
import numpy as np

from clipgs_jax import config_file
from clipgs_jax import run as run_lib
from clipgs_jax.lab import sweep
from clipgs_jax.lab import table
from clipgs_jax.lab import tau_sweep


def _metrics(psnr, *, alive=700, by_score=200, by_rule=100):
  return {"test": {"psnr": psnr, "ssim": 0.5, "lpips": 0.2,
                   "lpips_net": "alex"},
          "train_seconds": 10.0, "steps": 30, "num_gaussians": alive,
          "semantic": {"label": "CLIP-GS machinery, ORACLE scorer",
                       "fraction_pruned": (by_score + by_rule)
                       / (by_score + by_rule + alive),
                       "num_pruned_semantic": by_score,
                       "num_pruned_visibility": by_rule}}


def _cd(name):
  return config_file.load_file(os.path.join(config_file.CONFIGS_DIR, name + ".py"))


class CalibrateTest(absltest.TestCase):

  def test_otsu_splits_two_modes(self):
    edges = np.linspace(0.0, 0.05, 51)
    hist = np.zeros(50)
    hist[8:12] = 100.0          # static mode around 0.01
    hist[40:44] = 20.0          # transient mode around 0.042
    tau = tau_sweep.otsu_threshold(hist, edges)
    # Any edge in the empty gap [0.012, 0.040] separates; the middle one.
    self.assertAlmostEqual(tau, 0.026, delta=0.0015)

  def test_otsu_degenerate(self):
    edges = np.linspace(0.0, 1.0, 5)
    self.assertIsNone(tau_sweep.otsu_threshold(np.zeros(4), edges))
    self.assertIsNone(tau_sweep.otsu_threshold([0, 5, 0, 0], edges))

  def test_sweep_row_fractions(self):
    cfg = sweep.row_config(_cd("tau_sweep"), "oracle",
                           semantic={"tau": 0.02})
    self.assertEqual(cfg.semantic.tau, 0.02)
    r = tau_sweep.sweep_row(0.02, cfg, _metrics(21.0), None, 20.0)
    self.assertAlmostEqual(r["delta_psnr"], 1.0)
    self.assertAlmostEqual(r["fraction_pruned"], 0.3)
    self.assertAlmostEqual(r["fraction_pruned_by_score"], 0.2)
    self.assertAlmostEqual(r["fraction_pruned_by_rule"], 0.1)
    failed = tau_sweep.sweep_row(0.3, cfg, None, "error: disk full", 20.0)
    self.assertEqual(failed["status"], "failed")
    text = tau_sweep.format_markdown([r, failed], {"steps": 30})
    self.assertIn("| 0.02 | 21.00 | +1.00 |", text)
    self.assertIn("FAILED (error: disk full)", text)

  def test_histogram_plot_and_otsu_of_first_prune(self):
    edges = np.linspace(0.0, 0.05, 51).tolist()
    event = lambda step, peak: {"step": step, "histogram": np.eye(50)[
        peak].tolist()}
    events = {0.02: {"histogram_edges": edges,
                     "events": [event(50, 10), event(90, 12)]},
              0.3: {"histogram_edges": edges, "events": [event(50, 10)]}}
    out = os.path.join(self.create_tempdir().full_path, "h.png")
    tau_sweep.plot_histograms(events, out)
    self.assertGreater(os.path.getsize(out), 1000)
    self.assertIsNone(tau_sweep.first_prune_otsu(events))   # one bin
    with self.assertRaisesRegex(ValueError, "no run has a prune event"):
      tau_sweep.plot_histograms({0.02: None}, out)

  def test_sweep_plans_one_run_per_tau(self):
    cd = _cd("tau_sweep")
    cd.sweep.taus = "0.3,0.01"
    root = self.create_tempdir().full_path
    bench = self.create_tempdir("bench_a").full_path
    cd.sweep.benchmarks = bench
    ran = {}

    def fake_row(cfg, workdir, **kwargs):
      del kwargs
      ran[os.path.relpath(workdir, root)] = cfg
      return _metrics(20.0 + cfg.semantic.tau), None
    with mock.patch.object(sweep, "run_row", fake_row), \
        mock.patch.object(tau_sweep, "plot_histograms"):
      out = sweep.run(cd, root)
    self.assertEqual(sorted(ran), ["bench_a/oracle_tau0.01",
                                   "bench_a/oracle_tau0.3",
                                   "bench_a/vanilla"])
    self.assertEqual(ran["bench_a/oracle_tau0.3"].semantic.tau, 0.3)
    self.assertEqual(ran["bench_a/vanilla"].semantic.scorer, "off")
    self.assertEqual([r["tau"] for r in out["rows"]], [0.3, 0.01])
    self.assertTrue(os.path.exists(os.path.join(root, "bench_a",
                                                "calibrate_tau.md")))


class AblateTest(absltest.TestCase):

  def test_row_configs(self):
    cd = _cd("ablate")
    reg = sweep.row_config(cd, "oracle_reg_only", semantic={"tau": 0.03})
    self.assertEqual(reg.semantic.scorer, "oracle")
    self.assertFalse(reg.semantic.prune)
    self.assertEqual(reg.semantic.tau, 0.03)
    self.assertEqual(sweep.row_config(cd, "oracle_prune_only")
                     .semantic.lambda_c, 0.0)
    uniform = sweep.row_config(cd, "uniform_pixel")
    self.assertEqual((uniform.semantic.scorer, uniform.semantic.evidence,
                      uniform.pixel.loss_masking), ("uniform", "pixel", False))
    self.assertIn("UNIFORM control", run_lib.semantic_label(uniform))
    generic = sweep.row_config(cd, "clip_generic")
    self.assertEqual(generic.semantic.distractor_prompts,
                     ("a photo of an object", "a photo of a thing"))
    with self.assertRaisesRegex(Exception, "unknown row 'bogus'"):
      sweep.row_config(cd, "bogus")

  def test_rows_and_markdown(self):
    cd = _cd("ablate")
    cfg = lambda row: sweep.row_config(cd, row)
    rows = [table.ablation_row("vanilla", "vanilla 3DGS (clutter)",
                               cfg("vanilla"), _metrics(20.0), None, 20.0,
                               23.0),
            table.ablation_row("oracle_reg_only", "ORACLE: opacity loss only",
                               cfg("oracle_reg_only"), _metrics(21.5), None,
                               20.0, 23.0),
            table.ablation_row("clip_generic", "CLIP: generic prompts",
                               cfg("clip_generic"), None, None, 20.0, 23.0)]
    self.assertAlmostEqual(rows[1]["delta_psnr"], 1.5)
    self.assertAlmostEqual(rows[1]["gap_to_clean"], 1.5)
    self.assertEqual(rows[2]["status"], "not run")
    text = table.format_ablation(rows, {"steps": 30})
    self.assertIn("| ORACLE: opacity loss only | 21.50 | +1.50 | +1.50 |",
                  text)
    self.assertIn("| CLIP: generic prompts | not run: needs --clip_weights",
                  text)
    self.assertIn("| vanilla 3DGS (clutter) | 20.00 | — | +3.00 |", text)

  def test_clip_rows_not_run_without_weights(self):
    cd = _cd("ablate")
    root = self.create_tempdir().full_path
    cd.sweep.benchmarks = self.create_tempdir("b").full_path
    ran = []

    def fake_row(cfg, workdir, **kwargs):
      del kwargs
      ran.append(os.path.basename(workdir))
      return _metrics(20.0 + (cfg.semantic.scorer != "off")), None
    with mock.patch.object(sweep, "run_row", fake_row):
      out = sweep.run(cd, root)
    self.assertNotIn("clip", ran)
    self.assertNotIn("clip_generic", ran)
    status = {r["row"]: r["status"] for r in out["rows"]}
    self.assertEqual(status["clip_generic"], "not run")
    self.assertEqual(status["oracle_prune_only"], "ok")
    with open(os.path.join(root, "b", "ablate.md")) as f:
      text = f.read()
    self.assertIn("ORACLE: pruning only | 21.00 | +1.00 |", text)


if __name__ == "__main__":
  absltest.main()
