"""Tests for persistent transients: billboards.py and transients.build."""

import json
import os
import pathlib
import subprocess
import sys

import numpy as np
import pycolmap
import pytest

from clipgs_jax.data import billboards
from clipgs_jax.data import images
from clipgs_jax.data import transients
from test_colmap import _pose  # pylint: disable=g-bad-import-order

ROOT = pathlib.Path(__file__).resolve().parents[1]
WIDTH, HEIGHT = 96, 72
NUM_VIEWS = 25            # tests 0, 8, 16, 24; 21 training views
NUM_TRAIN = 21
K = 5                     # runs [0, 5) .. [15, 20) and [16, 21)
# The ring of test_colmap._pose: radius ~3.2 about the origin, so the
# 5 degree steps of 72 views move a camera by ~0.28 units per view.
RING = 72
GREY = 64 / 255           # exact in 8 bits


def _write_source(root):
  """A ring of cameras in capture order (sorted names = ring order) around
  a cloud of SfM points at the origin; grey images."""
  rec = pycolmap.Reconstruction()
  rec.add_camera_with_trivial_rig(pycolmap.Camera(
      camera_id=1, model="PINHOLE", width=WIDTH, height=HEIGHT,
      params=[80.0, 80.0, 48.0, 36.0]))
  for image_id in range(1, NUM_VIEWS + 1):
    rot, trans = _pose(image_id, RING)
    name = f"frame_{image_id:03d}.png"
    rec.add_image_with_trivial_frame(
        pycolmap.Image(name=name, camera_id=1, image_id=image_id),
        pycolmap.Rigid3d(pycolmap.Rotation3d(rot), trans))
    images.write_png(os.path.join(root, "images", name),
                     np.full((HEIGHT, WIDTH, 3), GREY))
  rng = np.random.default_rng(0)
  for xyz in rng.uniform(-0.5, 0.5, (60, 3)):
    rec.add_point3D(xyz, pycolmap.Track(), np.array([9, 9, 9], np.uint8))
  os.makedirs(os.path.join(root, "sparse", "0"))
  rec.write_binary(os.path.join(root, "sparse", "0"))


def _photo(folder):
  """A person photo whose colour says where it was hit: (u, v, 0.5)."""
  v, u = (np.mgrid[0:50, 0:40] + 0.5) / np.array([50, 40])[:, None, None]
  images.write_png(os.path.join(folder, "person", "p.png"),
                   np.stack([u, v, np.full_like(u, 0.5)], -1), bits=16)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
  root = tmp_path_factory.mktemp("bb")
  _write_source(str(root / "scene"))
  _photo(str(root / "photos"))
  out = {}
  for f in (0.5, 1.0):
    out[f] = transients.build(str(root / "scene"), str(root / "photos"),
                              str(root / f"f{f}"), seed=2, fraction=f,
                              per_view="1", mode="persistent",
                              persist_views=K)
  return root, out


def _camera(root, name):
  rec = pycolmap.Reconstruction(str(root / "f1.0" / "sparse" / "0"))
  image, = [im for im in rec.images.values() if im.name == name]
  matrix = image.cam_from_world().matrix()
  return matrix[:, :3], matrix[:, 3], np.asarray(rec.cameras[1].params)


def _mask(root, folder, name):
  return images.read_image(str(root / folder / "masks" / name))[..., 0] > 0.5


def test_make_runs():
  assert billboards.make_runs(21, 5) == [
      list(range(s, s + 5)) for s in (0, 5, 10, 15, 16)]
  assert billboards.make_runs(10, 5) == [[0, 1, 2, 3, 4], [5, 6, 7, 8, 9]]
  with pytest.raises(ValueError, match="--persist_views"):
    billboards.make_runs(4, 5)


def test_render_fronto_parallel_closed_form():
  # Camera at the origin looking down +z, f = 100, principal point (50, 50).
  # A 1 x 0.5 board at z = 2 projects to x in [25, 75], y in [37.5, 62.5]:
  # pixel centres 25.5..74.5 and 38.5..61.5 lie inside.
  corners = np.array([[-0.5, -0.25, 2], [0.5, -0.25, 2], [0.5, 0.25, 2],
                      [-0.5, 0.25, 2]])
  rgb = np.ones((25, 50, 3), np.float32)
  alpha = np.ones((25, 50), np.float32)
  view = np.zeros((100, 100, 3), np.float32)
  out, full = billboards.render(view, corners, rgb, alpha, np.eye(3),
                                np.zeros(3), np.array([100., 100, 50, 50]))
  want = np.zeros((100, 100), bool)
  want[38:62, 25:75] = True
  # Inside, alpha is 1; the texture's outer half texel fades to 0.
  np.testing.assert_array_equal(full > 0.5, want)
  np.testing.assert_allclose(full[40:60, 27:73], 1, atol=1e-6)
  np.testing.assert_allclose(out[..., 0], full, atol=1e-6)


def test_billboards_span_exactly_their_runs(built):
  root, manifests = built
  for f, manifest in manifests.items():
    names = [v["name"] for v in manifest["views"]]
    boards = manifest["billboards"]
    assert manifest["persist_views"] == K and manifest["mode"] == "persistent"
    shown = {}
    for b in boards:
      start = names.index(b["views"][0])
      assert b["views"] == names[start:start + K]       # consecutive, k
      for name in b["views"]:
        shown.setdefault(name, []).append(b["id"])
    for v in manifest["views"]:
      mask = _mask(root, f"f{f}", v["name"])
      ids = [t["billboard"] for t in v["transients"]]
      assert ids == shown.get(v["name"], [])
      assert mask.any() == bool(ids), v["name"]         # non-empty iff shown
      assert all(t["mask_pixels"] > 0 for t in v["transients"])
      assert v["mask_pixels"] == mask.sum()
  # Runs nest across fractions: f = 0.5's billboards are f = 1.0's.
  full = {b["run"]: b for b in manifests[1.0]["billboards"]}
  # floor(0.5 * 5 + 0.5) = 3 of the 5 runs.
  assert len(full) == 5 and len(manifests[0.5]["billboards"]) == 3
  for b in manifests[0.5]["billboards"]:
    assert {**b, "id": 0} == {**full[b["run"]], "id": 0}
  # Test views stay clean.
  for t in manifests[1.0]["tests"]:
    np.testing.assert_allclose(
        images.read_image(str(root / "f1.0" / "images" / t["name"])), GREY,
        atol=1e-6)


def test_same_physical_object_in_every_view(built):
  """A point of the billboard, projected into each of its views, shows the
  photo's colour at that point: one object seen from k cameras."""
  root, manifests = built
  board = manifests[1.0]["billboards"][0]
  corners = np.array(board["corners"])
  eyes = []
  for name in board["views"]:
    rot, trans, (fx, fy, cx, cy) = _camera(root, name)
    eyes.append(-rot.T @ trans)
    image = images.read_image(str(root / "f1.0" / "images" / name))
    for u, v in [(0.5, 0.5), (0.35, 0.4), (0.6, 0.65)]:
      point = corners[0] + u * (corners[1] - corners[0]) + v * (
          corners[3] - corners[0])
      cam = rot @ point + trans
      x, y = fx * cam[0] / cam[2] + cx, fy * cam[1] / cam[2] + cy
      pixel = image[int(y), int(x)]
      # Nearest pixel centre is < 0.71 px away; the texture changes by
      # ~1/texture width per pixel, so 0.05 covers it and 8-bit rounding.
      np.testing.assert_allclose(pixel, [u, v, 0.5], atol=0.05)
  # It faces the cameras of its run and stands in front of the content.
  normal = np.cross(corners[1] - corners[0], corners[3] - corners[0])
  centre = corners.mean(axis=0)
  # TL->TR x TL->BL is right x down = forward: away from the cameras.
  assert all((eye - centre) @ normal < 0 for eye in eyes)
  mid = eyes[K // 2]
  assert np.linalg.norm(centre - mid) < 0.7 * np.linalg.norm(mid)


def _carry(mask, corners, cam_a, cam_b):
  """Share of `mask`'s pixels (view a) whose ray meets the billboard's
  plane at a point that view b shows inside its own mask, and the count."""
  (rot_a, trans_a, k_a), (rot_b, trans_b, k_b, mask_b) = cam_a, cam_b
  ys, xs = np.nonzero(mask)
  rays = np.stack([(xs + 0.5 - k_a[2]) / k_a[0], (ys + 0.5 - k_a[3]) / k_a[1],
                   np.ones(len(xs))], -1) @ rot_a
  eye = -rot_a.T @ trans_a
  normal = np.cross(corners[1] - corners[0], corners[3] - corners[0])
  s = ((corners[0] - eye) @ normal) / (rays @ normal)
  xy, _ = billboards.project(eye + s[:, None] * rays, rot_b, trans_b, k_b)
  inside = ((xy[:, 0] >= 0) & (xy[:, 0] < WIDTH) & (xy[:, 1] >= 0) &
            (xy[:, 1] < HEIGHT))
  hits = mask_b[xy[inside, 1].astype(int), xy[inside, 0].astype(int)]
  return hits.mean(), inside.sum()


def test_masks_agree_through_the_plane(built):
  """Each mask pixel of one view, carried to another view through the
  billboard's plane, lands on that view's mask, both ways: the two masks
  are one projection of the same 3D rectangle."""
  root, manifests = built
  board = manifests[1.0]["billboards"][0]
  corners = np.array(board["corners"])
  for a, b in [(0, K - 1), (K - 1, 0), (1, 2), (2, 1)]:
    name_a, name_b = board["views"][a], board["views"][b]
    mask_a, mask_b = _mask(root, "f1.0", name_a), _mask(root, "f1.0", name_b)
    share, count = _carry(mask_a, corners, _camera(root, name_a),
                          (*_camera(root, name_b), mask_b))
    # Only pixels at the soft edge may round to the other side of 0.5.
    assert count > 0.9 * mask_a.sum() and share > 0.97, (a, b, share)
    assert not np.array_equal(mask_a, mask_b)    # the cameras did move


def test_deterministic_and_seeded(built, tmp_path):
  root, manifests = built
  again = transients.build(str(root / "scene"), str(root / "photos"),
                           str(tmp_path / "a"), seed=2, fraction=1.0,
                           per_view="1", mode="persistent", persist_views=K)
  assert again == manifests[1.0]
  for n in sorted(os.listdir(root / "f1.0" / "images")):
    assert (root / "f1.0" / "images" / n).read_bytes() == (
        tmp_path / "a" / "images" / n).read_bytes(), n
  other = transients.build(str(root / "scene"), str(root / "photos"),
                           str(tmp_path / "b"), seed=3, fraction=1.0,
                           per_view="1", mode="persistent", persist_views=K)
  assert other["billboards"] != manifests[1.0]["billboards"]
  written = json.loads((root / "f1.0" / "transients.json").read_text())
  assert written["billboards"] == manifests[1.0]["billboards"]


@pytest.mark.parametrize("kwargs,needle", [
    ({"persist_views": 0}, "--persist_views"),
    ({"persist_views": 22}, "--persist_views"),
    ({"mode": "sticky"}, "--mode"),
])
def test_bad_persistent_args(built, tmp_path, kwargs, needle):
  root, _ = built
  kwargs = {"mode": "persistent", **kwargs}
  with pytest.raises(ValueError, match=needle):
    transients.build(str(root / "scene"), str(root / "photos"),
                     str(tmp_path / "out"), seed=0, **kwargs)
  assert not (tmp_path / "out").exists()


def _sliding_cameras(step, k=5):
  """k cameras looking down +z, slid by `step` along x (forward-facing)."""
  trans = np.stack([[-step * i, 0.0, 0.0] for i in range(k)])
  return (np.tile(np.eye(3), (k, 1, 1)), trans,
          np.tile([80.0, 80.0, 48.0, 36.0], (k, 1)),
          np.tile([WIDTH, HEIGHT], (k, 1)))


def test_place_deeper_when_the_run_moves_far():
  """A wall of points at z = 5..5.5 seen by 5 cameras sliding 1 unit each:
  from the middle view the end views are 2 units away, so a billboard at
  depth d shifts by 80 * 2 / d pixels (96 wide). Within 0.3-0.6 of the
  near depth (d <= 3: >= 53 px) it leaves some view; the second band
  (d up to 4.5: >= 36 px) keeps it in all five. Sliding 3 units per view
  needs d > 11, behind the wall: refused, naming the flag."""
  points = np.random.default_rng(0).uniform([-20, -20, 5], [20, 20, 5.5],
                                            (400, 3))
  rots, trans, intr, sizes = _sliding_cameras(1.0)
  near = billboards.near_depth(points, rots[2], trans[2], intr[2], sizes[2])
  low, high, _ = billboards.DEPTH_STAGES[1]
  for seed in range(3):
    corners = billboards.place(np.random.default_rng(seed), (40, 50), rots,
                               trans, intr, sizes, points)
    centre = corners.mean(axis=0)[None]
    _, z = billboards.project(centre, rots[2], trans[2], intr[2])
    assert low * near <= z[0] <= high * near
    for r, t, k in zip(rots, trans, intr):
      xy, _ = billboards.project(centre, r, t, k)
      assert 0 < xy[0, 0] < WIDTH and 0 < xy[0, 1] < HEIGHT
  with pytest.raises(billboards.PlacementError, match="--persist_views"):
    billboards.place(np.random.default_rng(0), (40, 50),
                     *_sliding_cameras(3.0), points)


def _write_slide(root, xs):
  """A capture named 1.png .. N.png (unpadded, as a camera names them) of
  cameras looking down +z at a wall of SfM points at z = 5..5.5 (in front
  of every camera), camera i
  at x = xs[i - 1]; written in reverse id order, so only the names say the
  capture order."""
  rec = pycolmap.Reconstruction()
  rec.add_camera_with_trivial_rig(pycolmap.Camera(
      camera_id=1, model="PINHOLE", width=WIDTH, height=HEIGHT,
      params=[80.0, 80.0, 48.0, 36.0]))
  for i in range(len(xs), 0, -1):
    name = f"{i}.png"
    rec.add_image_with_trivial_frame(
        pycolmap.Image(name=name, camera_id=1, image_id=len(xs) + 1 - i),
        pycolmap.Rigid3d(pycolmap.Rotation3d(np.eye(3)),
                         np.array([-xs[i - 1], 0.0, 0.0])))
    images.write_png(os.path.join(root, "images", name),
                     np.full((HEIGHT, WIDTH, 3), GREY))
  rng = np.random.default_rng(0)
  for x in xs:     # the wall in front of each camera
    for xyz in rng.uniform([x - 4, -3, 5], [x + 4, 3, 5.5], (20, 3)):
      rec.add_point3D(xyz, pycolmap.Track(), np.array([9, 9, 9], np.uint8))
  os.makedirs(os.path.join(root, "sparse", "0"))
  rec.write_binary(os.path.join(root, "sparse", "0"))


def _slide(jumps_before=()):
  """Camera x of 1.png .. 25.png: 0.5 apart, plus 10 before each photo
  number in `jumps_before`. At the wall's near depth (~5), a billboard
  shifts by 80 * 10 / 4.5 > 96 pixels (the width) between two views 10
  apart, so no billboard is seen by both; 0.5 apart it shifts ~9 px."""
  return [0.5 * i + 10.0 * sum(i >= j for j in jumps_before)
          for i in range(1, NUM_VIEWS + 1)]


def _numbers(manifest, names):
  source = {v["name"]: v["source"] for v in manifest["views"]}
  return [int(source[n].split(".")[0]) for n in names]


def test_unpadded_names_run_in_capture_order(tmp_path):
  """1.png .. 25.png: tests are photos 1, 9, 17, 25 and each run is five
  consecutive training photos by number (sorted as strings, 1, 10, 11, ...
  would be a run)."""
  _write_slide(str(tmp_path / "scene"), _slide())
  _photo(str(tmp_path / "photos"))
  manifest = transients.build(
      str(tmp_path / "scene"), str(tmp_path / "photos"), str(tmp_path / "b"),
      seed=0, fraction=1.0, per_view="1", mode="persistent", persist_views=K)
  assert [t["source"] for t in manifest["tests"]] == [
      "1.png", "9.png", "17.png", "25.png"]
  train = [i for i in range(1, NUM_VIEWS + 1) if (i - 1) % 8]
  assert _numbers(manifest, [v["name"] for v in manifest["views"]]) == train
  runs = [_numbers(manifest, b["views"]) for b in manifest["billboards"]]
  assert runs == [train[s:s + K] for s in (0, 5, 10, 15, 16)]
  assert transients.billboard_summary(manifest) == "5 billboards of 5 views"
  assert "unplaced" not in manifest


def test_a_jump_shortens_or_skips_a_run(tmp_path):
  """Training runs (photo numbers): [2-6], [7 8 10 11 12], [13-16 18],
  [19-23], [20-24]. A jump before photo 10 leaves run 1 its stretch
  10-12; jumps before each of 19-23 leave run 3 no two views that see one
  billboard (skipped) and run 4 the pair 23, 24; the rest is built."""
  _write_slide(str(tmp_path / "scene"), _slide((10, 19, 20, 21, 22, 23)))
  _photo(str(tmp_path / "photos"))
  manifest = transients.build(
      str(tmp_path / "scene"), str(tmp_path / "photos"), str(tmp_path / "b"),
      seed=0, fraction=1.0, per_view="1", mode="persistent", persist_views=K)
  runs = {b["run"]: _numbers(manifest, b["views"])
          for b in manifest["billboards"]}
  assert runs == {0: [2, 3, 4, 5, 6], 1: [10, 11, 12],
                  2: [13, 14, 15, 16, 18], 4: [23, 24]}
  assert manifest["unplaced"] == [{"run": 3, "photo": "person/p.png"}]
  assert transients.billboard_summary(manifest) == (
      "4 billboards: 2 of 5 views, 1 of 3, 1 of 2 (their runs could not "
      "show them in all 5); 1 not placed, run 3 skipped")
  for v in manifest["views"]:    # only views a billboard was placed in
    shown = any(v["name"] in b["views"] for b in manifest["billboards"])
    assert (v["mask_pixels"] > 0) == shown, v["name"]


def test_no_run_can_show_a_billboard(tmp_path):
  """Every photo 10 apart: no two consecutive views see one billboard, so
  the build is refused, naming what to check, and leaves nothing."""
  _write_slide(str(tmp_path / "scene"), _slide(range(2, NUM_VIEWS + 1)))
  _photo(str(tmp_path / "photos"))
  with pytest.raises(ValueError, match="could not place a billboard seen "
                     "by 2 or more consecutive views of any of the 5 "
                     "chosen runs") as err:
    transients.build(str(tmp_path / "scene"), str(tmp_path / "photos"),
                     str(tmp_path / "b"), seed=0, fraction=1.0, per_view="1",
                     mode="persistent", persist_views=K)
  assert "\n" not in str(err.value) and "--persist_views" in str(err.value)
  assert not (tmp_path / "b").exists()


def test_cli_persistent(built, tmp_path):
  root, _ = built
  out = tmp_path / "cli"
  cmd = [sys.executable, str(ROOT / "experiments" / "prepare.py"),
         "--prepare=benchmark", f"--clean_scene={root / 'scene'}",
         f"--distractors={root / 'photos'}",
         f"--out={out}", "--seed=1", "--fraction=1", "--mode=persistent",
         "--persist_views=4"]
  env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
  run = subprocess.run(cmd, env=env, capture_output=True, text=True,
                       check=False, timeout=120)
  assert run.returncode == 0, run.stderr
  assert "(persistent)" in run.stdout and "of 4 views" in run.stdout
  manifest = json.loads((out / "transients.json").read_text())
  assert manifest["persist_views"] == 4
  assert all(len(b["views"]) == 4 for b in manifest["billboards"])
