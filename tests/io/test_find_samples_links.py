"""Datasets as they are kept: sample folders reached through symbolic links, cycles and dangling links."""

from __future__ import annotations

import json
import os

import pytest

from psmini.batch import reconstruct_dataset
from psmini.errors import DataFormatError
from psmini.io import find_samples, load_sample, scan_samples
from tests._captures import write_capture_tree

pytestmark = pytest.mark.skipif(not hasattr(os, "symlink"), reason="symbolic links are not available here")


def _diligent_like(folder):
    folder.mkdir(parents=True)
    (folder / "filenames.txt").write_text("001.png\n")
    (folder / "light_directions.txt").write_text("0 0 1\n")


@pytest.fixture
def linked(tmp_path):
    """store/ holds the data; root/ assembles it with links: to a folder of samples, to a sample, a link to a
    folder above it (a cycle) and a link to nothing."""
    store, root = tmp_path / "store", tmp_path / "root"
    _diligent_like(store / "lot1" / "ball")
    _diligent_like(store / "lot1" / "cat")
    _diligent_like(store / "lone" / "pot")
    _diligent_like(root / "local" / "cow")
    (root / "lot1").symlink_to(store / "lot1", target_is_directory=True)
    (root / "pot").symlink_to(store / "lone" / "pot", target_is_directory=True)
    (root / "local" / "up").symlink_to(root, target_is_directory=True)
    (root / "gone").symlink_to(store / "deleted", target_is_directory=True)
    return root


class TestScanSamples:
    def test_follows_links_and_names_samples_through_them(self, linked):
        scan = scan_samples(linked)
        assert [p.relative_to(linked).as_posix() for p in scan.samples] == ["local/cow", "lot1/ball", "lot1/cat", "pot"]
        assert find_samples(linked) == scan.samples

    def test_cycle_and_dangling_link_reported_by_name(self, linked, caplog):
        scan = scan_samples(linked)
        assert sorted(p.relative_to(linked).as_posix() for p in scan.problems) == ["gone", "local/up"]
        assert "dangling symbolic link" in scan.problems[linked / "gone"]
        assert str(linked / "gone") in scan.problems[linked / "gone"]
        assert "loops back" in scan.problems[linked / "local" / "up"]
        assert "gone" in caplog.text and "local/up" in caplog.text  # find_samples' callers see them in the log

    def test_cycle_through_two_links_terminates(self, tmp_path):
        (tmp_path / "a").mkdir()
        (tmp_path / "b").mkdir()
        (tmp_path / "a" / "to_b").symlink_to(tmp_path / "b", target_is_directory=True)
        (tmp_path / "b" / "to_a").symlink_to(tmp_path / "a", target_is_directory=True)
        _diligent_like(tmp_path / "b" / "obj")
        scan = scan_samples(tmp_path)
        # b/obj directly and a/to_b/obj through the link; the loops back are reported, not followed
        assert [p.relative_to(tmp_path).as_posix() for p in scan.samples] == ["a/to_b/obj", "b/obj"]
        assert sorted(p.relative_to(tmp_path).as_posix() for p in scan.problems) == ["a/to_b/to_a", "b/to_a/to_b"]

    def test_root_that_is_a_link(self, linked, tmp_path):
        (tmp_path / "alias").symlink_to(linked / "lot1", target_is_directory=True)
        assert [p.name for p in find_samples(tmp_path / "alias")] == ["ball", "cat"]

    def test_errors(self, tmp_path):
        with pytest.raises(DataFormatError, match="not a folder"):
            scan_samples(tmp_path / "missing")
        (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
        with pytest.raises(DataFormatError, match="dangling"):
            scan_samples(tmp_path / "dangling")


@pytest.mark.slow
def test_batch_over_a_root_of_links(tmp_path):
    """Every linked sample is reconstructed under its path as seen through the link, the run resumes, and the
    cycle and the dangling link fail by name while the others go on."""
    store = write_capture_tree(tmp_path / "store", size=32)
    root = tmp_path / "root"
    root.mkdir()
    (root / "A").symlink_to(store / "lotA", target_is_directory=True)  # a folder of samples and their card
    (root / "cotton").symlink_to(store / "lotB" / "cotton", target_is_directory=True)  # a sample, card beside it
    (root / "loop").symlink_to(root, target_is_directory=True)
    (root / "gone").symlink_to(store / "lotZ", target_is_directory=True)
    assert load_sample(root / "cotton").reference is not None  # its card is found through the link
    first = reconstruct_dataset(root, tmp_path / "out", batch_size=2)
    statuses = {row["sample"]: row["status"] for row in first["samples"]}
    assert statuses == {"A/jute": "done", "A/twill": "done", "cotton": "done", "loop": "failed", "gone": "failed"}
    errors = {row["sample"]: row["error"] for row in first["samples"]}
    assert "loops back" in errors["loop"] and "dangling" in errors["gone"] and str(root / "gone") in errors["gone"]
    for rel in ("A/jute", "A/twill", "cotton"):
        assert json.loads((tmp_path / "out" / rel / "outputs.json").read_text())["files"]
    second = reconstruct_dataset(root, tmp_path / "out", batch_size=2)
    assert second["counts"] == {"done": 0, "skipped": 3, "failed": 2}
