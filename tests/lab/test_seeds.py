"""clipgs_jax.lab.seeds: a benchmark table over the roots of several seeds."""

import json
import os
import pathlib
import subprocess
import sys

import pytest

from clipgs_jax.lab import seeds

ROOT = pathlib.Path(__file__).resolve().parents[2]
BENCH = "bonsai_f1.0"


def _write_run(root, row, seed, views, clean=False, steps=100, recall=None):
  """ROOT/BENCH/row/ with the metrics.json and config.json a run writes."""
  folder = root / BENCH / row
  folder.mkdir(parents=True)
  metrics = {"steps": steps, "train_seconds": 10.0 + seed,
             "test": {"psnr": sum(views.values()) / len(views),
                      "per_image": {k: {"psnr": v} for k, v in views.items()}}}
  config = {"train": {"seed": seed},
            "data": {"train_split": "clean" if clean else "clutter"}}
  if recall is not None:   # a guided row: its config says so
    metrics["semantic"] = {"mask_quality": {"precision": 0.9,
                                            "recall": recall}}
    config["semantic"] = {"scorer": "residual", "evidence": "pixel"}
  (folder / "metrics.json").write_text(json.dumps(metrics))
  (folder / "config.json").write_text(json.dumps(config))


def _views(a, b, window):
  """Three test views: two steady ones and a window that moves by seed."""
  return {"a.png": a, "b.png": b, "window.png": window}


@pytest.fixture
def roots(tmp_path):
  """Two seeds of vanilla, a row, clean and the row's clean control."""
  out = []
  for seed, window in ((0, 20.0), (1, 16.0)):
    root = tmp_path / f"s{seed}"
    _write_run(root, "vanilla", seed, _views(24.0, 26.0, window))
    _write_run(root, "residual_features", seed,
               _views(25.0, 27.0, window - 3.0 * seed), recall=0.5 + seed / 10)
    _write_run(root, "clean", seed, _views(26.0, 28.0, window), clean=True)
    _write_run(root, "residual_features_clean", seed,
               _views(26.0, 28.0, window - 1.0), clean=True)
    out.append(str(root))
  return out


def test_seed_table(roots):
  result = seeds.seed_table(seeds.find_runs(roots))
  cells = {c["row"]: c for c in result["cells"]}
  # table.ROWS order, whatever order the folders come in.
  assert [c["row"] for c in result["cells"]] == [
      "vanilla", "residual_features", "clean", "residual_features_clean"]
  row = cells["residual_features"]
  assert row["seeds"] == [0, 1] and row["base"] == "vanilla"
  # Seed 0: +1 on two views, 0 on the window; seed 1: +1, +1, -3.
  assert row["delta"] == pytest.approx({0: 2.0 / 3.0, 1: -1.0 / 3.0})
  assert row["mean_delta"] == pytest.approx(1.0 / 6.0)
  assert row["delta_std_error"] == pytest.approx(0.5)
  assert row["recall"] == pytest.approx(0.55)
  assert row["seconds"] == pytest.approx(10.5)
  # The window moves between seeds; the steady views not at all.
  assert [v for v, _ in result["unstable"][BENCH]] == [
      "window.png", "a.png", "b.png"]
  assert result["unstable"][BENCH][1][1] == 0.0
  # A control is measured against clean, not vanilla.
  control = cells["residual_features_clean"]
  assert control["base"] == "clean"
  assert control["mean_delta"] == pytest.approx(-1.0 / 3.0)
  assert cells["vanilla"]["base"] is None
  assert cells["vanilla"]["mean"] == pytest.approx((70.0 + 66.0) / 6.0)


def test_other_views_leave_out_the_unstable_ones(roots):
  result = seeds.seed_table(seeds.find_runs(roots))
  # Three views, three named unstable: nothing is left to compare.
  row = [c for c in result["cells"] if c["row"] == "residual_features"][0]
  assert row["delta_other_views"] is None
  assert row["delta_set_apart"] is None
  result = seeds.seed_table(seeds.find_runs(roots), num_unstable=1)
  row = [c for c in result["cells"] if c["row"] == "residual_features"][0]
  # Window variances over seeds: 8 in three rows, 24.5 in the row.
  assert result["unstable"][BENCH] == [("window.png", pytest.approx(
      ((8.0 + 24.5 + 8.0 + 8.0) / 4.0) ** 0.5))]
  assert row["delta_other_views"] == pytest.approx(1.0)


def test_views_set_apart(roots):
  runs = seeds.find_runs(roots)
  result = seeds.seed_table(runs, set_apart=["window.png", "b.png"])
  cells = {c["row"]: c for c in result["cells"]}
  row = cells["residual_features"]
  # a.png: +1 on both seeds; window and b: (0 + 1) / 2 on s0, (-3 + 1) / 2
  # on s1, mean -0.25; whatever the least stable views are.
  assert row["delta_other_views"] == pytest.approx(1.0)
  assert row["delta_set_apart"] == pytest.approx(-0.25)
  assert cells["residual_features_clean"]["delta_set_apart"] == (
      pytest.approx(-0.5))
  assert cells["vanilla"]["delta_set_apart"] is None
  text = seeds.format_markdown(result)
  assert "| Δ, other views | Δ, set apart |" in text
  assert "| +0.17 ± 0.50 | +1.00 | -0.25 | 0.90 / 0.55 |" in text
  assert "those set apart (window.png, b.png)" in text
  with pytest.raises(ValueError, match=r"--set_apart: door.png is not a "
                     r"test view of .*s0/bonsai_f1.0/clean \(its views: "
                     r"a.png, b.png, window.png\)"):
    seeds.seed_table(runs, set_apart=["door.png", "a.png"])


def test_one_seed_has_no_spread(roots):
  result = seeds.seed_table(seeds.find_runs(roots[:1]))
  row = [c for c in result["cells"] if c["row"] == "residual_features"][0]
  assert row["delta_std_error"] is None
  assert result["unstable"][BENCH] == []
  assert "(one seed)" in seeds.format_markdown(result)


def test_a_run_without_psnr_is_not_paired(roots):
  path = os.path.join(roots[1], BENCH, "vanilla", "metrics.json")
  with open(path) as f:
    metrics = json.load(f)
  metrics["test"]["psnr"] = None     # non-finite in the run: not a number
  with open(path, "w") as f:
    json.dump(metrics, f)
  result = seeds.seed_table(seeds.find_runs(roots))
  row = [c for c in result["cells"] if c["row"] == "residual_features"][0]
  assert row["delta"] == pytest.approx({0: 2.0 / 3.0})
  assert row["delta_std_error"] is None
  assert "| 0,1 | 23.33 / n/a | 23.33 |" in seeds.format_markdown(result)


def test_bad_roots(roots, tmp_path):
  with pytest.raises(ValueError, match=r"s0/bonsai_f1.0/clean are both seed 0 of clean"):
    seeds.find_runs([roots[0], roots[0]])
  empty = tmp_path / "empty"
  empty.mkdir()
  with pytest.raises(ValueError, match=f"{empty}: no <benchmark>/<row>/"):
    seeds.find_runs([str(empty)])
  other = tmp_path / "s2"
  _write_run(other, "vanilla", 2, _views(1.0, 2.0, 3.0), steps=50)
  with pytest.raises(ValueError, match=r"ran \[50, 100\] steps"):
    seeds.seed_table(seeds.find_runs(roots + [str(other)]))


def test_cli(roots, tmp_path):
  env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
  cmd = [sys.executable, str(ROOT / "experiments" / "report.py"),
         "--report=seeds"]
  out = subprocess.run(cmd + ["--runs=" + ",".join(roots)],
                       capture_output=True, text=True, env=env, check=False,
                       timeout=300)
  assert out.returncode == 0, out.stderr
  assert ("| bonsai_f1.0 | residual_features | 0,1 | 24.00 / 21.67 | "
          "22.83 | +0.67 / -0.33 | +0.17 ± 0.50 | — | 0.90 / 0.55 | 10 |"
          ) in out.stdout
  assert "window.png (3.48 dB)" in out.stdout
  out = subprocess.run(cmd + ["--runs=" + ",".join(roots),
                              "--set_apart=door.png"],
                       capture_output=True, text=True, env=env, check=False,
                       timeout=300)
  assert out.returncode != 0
  assert out.stderr.strip().splitlines()[-1].startswith(
      "error: --set_apart: door.png is not a test view of ")
  missing = tmp_path / "nowhere"
  out = subprocess.run(cmd + [f"--runs={missing}"], capture_output=True,
                       text=True, env=env, check=False, timeout=300)
  assert out.returncode != 0
  assert out.stderr.strip().splitlines()[-1] == (
      f"error: --runs={missing} does not exist; pass an existing folder")
