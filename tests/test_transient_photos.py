"""Tests for clipgs_jax/data/transient_photos.py: photo categories."""

import os

import numpy as np
import pytest

from clipgs_jax.data import images
from clipgs_jax.data import transient_photos
import shared_data


def _photo(path):
  os.makedirs(os.path.dirname(path), exist_ok=True)
  images.write_png(str(path), np.full((6, 4, 3), 0.5))


def _categories(folder):
  return {os.path.relpath(p, folder): c
          for p, c in transient_photos.list_photos(str(folder))}


def test_subfolders_manifest_and_names(tmp_path):
  for name in ("person/a.png", "clutter/b.jpg", "clutter/c.png", "d e.png",
               "astronaut.png", "clutter_x.png"):
    _photo(tmp_path / name)
  (tmp_path / "clutter" / "readme.txt").write_text("not a photo")
  (tmp_path / "categories.txt").write_text(
      "# my photos\n\nperson d e.png   # a person at the door\n"
      "clutter clutter/c.png\n")
  assert _categories(tmp_path) == {
      "person/a.png": "person", "clutter/b.jpg": "clutter",
      "clutter/c.png": "clutter", "d e.png": "person",
      "astronaut.png": "person", "clutter_x.png": "clutter"}


def test_manifest_names_subfolder_of_other_name(tmp_path):
  _photo(tmp_path / "shots" / "x.png")
  with pytest.raises(ValueError, match="shots"):
    transient_photos.list_photos(str(tmp_path))
  (tmp_path / "categories.txt").write_text("clutter shots/x.png\n")
  assert _categories(tmp_path) == {"shots/x.png": "clutter"}


@pytest.mark.parametrize("files,manifest,error,needle", [
    (["dog.png"], None, ValueError, "dog.png"),
    (["person/a.png", "dog.png"], None, ValueError, "dog.png"),
    (["dog.png"], "animal dog.png\n", ValueError, "line 1"),
    (["dog.png"], "person\n", ValueError, "line 1"),
    (["dog.png"], "person dog.png\nclutter cat.png\n", FileNotFoundError,
     "cat.png"),
    (["person/a.png"], "clutter person/a.png\n", ValueError, "agree"),
    ([], None, ValueError, "no photos"),
])
def test_bad_folders(tmp_path, files, manifest, error, needle):
  for name in files:
    _photo(tmp_path / name)
  if manifest is not None:
    (tmp_path / "categories.txt").write_text(manifest)
  with pytest.raises(error) as e:
    transient_photos.list_photos(str(tmp_path))
  assert "\n" not in str(e.value) and needle in str(e.value), str(e.value)


def test_unknown_photo_error_names_the_fixes(tmp_path):
  _photo(tmp_path / "dog.png")
  with pytest.raises(ValueError) as e:
    transient_photos.list_photos(str(tmp_path))
  msg = str(e.value)
  assert str(tmp_path / "dog.png") in msg
  assert str(tmp_path / "person") in msg and "categories.txt" in msg


def test_missing_folder(tmp_path):
  with pytest.raises(FileNotFoundError, match="--distractors"):
    transient_photos.list_photos(str(tmp_path / "nope"))


@shared_data.needs_data("distractors")
def test_shared_folder_needs_no_manifest():
  found = _categories(shared_data.DATA / "distractors")
  assert len(found) == 8
  assert sorted(found.values()).count("person") == 5
