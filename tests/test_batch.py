import dataclasses
import json
import os
import shutil

import numpy as np
import pytest
import torch

import psmini.batch as batch
import psmini.errors
import psmini.io
from psmini.batch import iter_reconstructions, parse_outputs, reconstruct_dataset
from psmini.cli import main
from psmini.config import ReconstructionConfig
from psmini.errors import InputError
from psmini.io import load_sample
from psmini.pipeline import reconstruct
from tests._captures import DISTANT, GOOD, write_capture_tree

ALL = sorted(GOOD + ["lotC/broken"])


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    return write_capture_tree(tmp_path_factory.mktemp("captures"), size=64)


def _fresh(tree, tmp_path):
    """A private copy of the tree (runs write nothing into it, but tests that break things need their own)."""
    return shutil.copytree(tree, tmp_path / "captures")


class TestReconstructDataset:
    def test_statuses_and_summary_files(self, tree, tmp_path):
        summary = reconstruct_dataset(tree, tmp_path / "out", DISTANT, batch_size=4)
        statuses = {row["sample"]: row["status"] for row in summary["samples"]}
        assert statuses == {**{name: "done" for name in GOOD}, "lotC/broken": "failed"}
        assert summary["counts"] == {"done": 3, "skipped": 0, "failed": 1}
        broken = next(row for row in summary["samples"] if row["sample"] == "lotC/broken")
        assert "led_03.png" in broken["error"]
        assert not (tmp_path / "out" / "lotC" / "broken").exists()
        on_disk = json.loads((tmp_path / "out" / "summary.json").read_text())
        assert on_disk["samples"] == json.loads(json.dumps(summary["samples"]))
        csv_lines = (tmp_path / "out" / "summary.csv").read_text().splitlines()
        assert csv_lines[0].split(",") == list(batch.SUMMARY_FIELDS)
        assert [line.split(",")[0] for line in csv_lines[1:]] == ALL
        for row in summary["samples"]:
            if row["status"] == "done":
                # synthetic fabrics under the near LEDs, solved as distant: a few degrees, not tens
                assert 0.5 < row["mean_angular_error_deg"] < 8.0
                assert row["time_s"] >= row["decode_s"] + row["write_s"]
                assert row["batch_size"] == (2 if row["sample"].startswith("lotA") else 1)

    def test_outputs_equal_single_sample_reconstruction(self, tree, tmp_path):
        reconstruct_dataset(tree, tmp_path / "out", DISTANT, batch_size=8)
        for name in GOOD:
            expected = reconstruct(load_sample(tree / name), DISTANT)
            depth = np.load(tmp_path / "out" / name / "depth.npy")
            inside = expected.mask[0, 0].numpy()
            np.testing.assert_allclose(depth[inside], expected.depth[0, 0].numpy()[inside], atol=1e-5)
            assert np.isnan(depth[~inside]).all()
            files = json.loads((tmp_path / "out" / name / "outputs.json").read_text())["files"]
            assert set(files) == {"albedo.png", "normals.png", "depth.npy", "depth.png", "depth.json", "points.ply",
                                  "mesh.ply"}

    def test_workers_give_the_same_outputs(self, tree, tmp_path):
        reconstruct_dataset(tree, tmp_path / "serial", DISTANT, batch_size=3, workers=0)
        summary = reconstruct_dataset(tree, tmp_path / "workers", DISTANT, batch_size=3, workers=2)
        assert summary["counts"] == {"done": 3, "skipped": 0, "failed": 1}
        for name in GOOD:
            np.testing.assert_array_equal(np.load(tmp_path / "serial" / name / "depth.npy"),
                                          np.load(tmp_path / "workers" / name / "depth.npy"))

    def test_card_decoded_once_per_calibration(self, tree, tmp_path, monkeypatch):
        decoded = []
        read_capture = psmini.io.read_capture

        def counting(folder):
            capture = read_capture(folder)
            decoded.append((capture.kind, str(folder)))
            return capture

        monkeypatch.setattr(psmini.io, "read_capture", counting)
        reconstruct_dataset(tree, tmp_path / "out", DISTANT, batch_size=2)
        cards = sorted(path for kind, path in decoded if kind == "flatfield")
        assert [p.rsplit("/", 2)[-2] for p in cards] == ["lotA", "lotB"]

    def test_resume_skips_finished_samples(self, tree, tmp_path):
        first = reconstruct_dataset(tree, tmp_path / "out", DISTANT)
        stamps = {name: (tmp_path / "out" / name / "outputs.json").stat().st_mtime_ns for name in GOOD}
        second = reconstruct_dataset(tree, tmp_path / "out", DISTANT)
        assert second["counts"] == {"done": 0, "skipped": 3, "failed": 1}
        assert stamps == {name: (tmp_path / "out" / name / "outputs.json").stat().st_mtime_ns for name in GOOD}
        # the skipped rows keep the errors the first run measured
        before = {r["sample"]: r["mean_angular_error_deg"] for r in first["samples"]}
        after = {r["sample"]: r["mean_angular_error_deg"] for r in second["samples"]}
        assert before == after

    def test_run_killed_half_way_then_restarted_writes_each_sample_once(self, tree, tmp_path, monkeypatch):
        written = []
        write = batch._write

        def dying_after_one(out_dir, *args):
            if len(written) == 1:
                # the kill lands while the second sample is being written: its temporary folder is left behind
                (out_dir.parent / f".{out_dir.name}.tmp-0123abcd").mkdir(parents=True)
                raise KeyboardInterrupt
            write(out_dir, *args)
            written.append(out_dir.name)

        monkeypatch.setattr(batch, "_write", dying_after_one)
        with pytest.raises(KeyboardInterrupt):
            reconstruct_dataset(tree, tmp_path / "out", DISTANT, batch_size=1)
        assert written == ["jute"]

        def counting(out_dir, *args):
            write(out_dir, *args)
            written.append(out_dir.name)

        monkeypatch.setattr(batch, "_write", counting)
        summary = reconstruct_dataset(tree, tmp_path / "out", DISTANT, batch_size=1)
        assert sorted(written) == ["cotton", "jute", "twill"]  # every good sample written exactly once
        assert {r["sample"]: r["status"] for r in summary["samples"]} == {
            "lotA/jute": "skipped", "lotA/twill": "done", "lotB/cotton": "done", "lotC/broken": "failed"}
        hidden = [p for p in (tmp_path / "out").rglob(".*")]
        assert hidden == []  # the killed run's temporary folder was cleared
        for name in GOOD:
            assert np.isfinite(np.load(tmp_path / "out" / name / "depth.npy")).any()

    def test_only_the_samples_temporaries_are_removed(self, tree, tmp_path):
        # a temporary beside a sample still to do goes; a look-alike of no sample of the run, and a file, stay
        lot = tmp_path / "out" / "lotA"
        (lot / ".jute.tmp-0123abcd").mkdir(parents=True)
        (lot / ".mine.tmp-0123abcd").mkdir()
        (lot / ".twill.tmp-89abcdef").write_text("not a folder")
        reconstruct_dataset(tree, tmp_path / "out", DISTANT, outputs="depth", score=False)
        assert sorted(p.name for p in lot.glob(".*")) == [".mine.tmp-0123abcd", ".twill.tmp-89abcdef"]

    def test_selected_outputs_only(self, tree, tmp_path):
        summary = reconstruct_dataset(tree, tmp_path / "out", DISTANT, outputs="depth,normals", score=False)
        assert all(row["mean_angular_error_deg"] == "" for row in summary["samples"])
        folder = tmp_path / "out" / "lotB" / "cotton"
        assert {p.name for p in folder.iterdir()} == {"normals.png", "depth.npy", "depth.png", "depth.json",
                                                      "outputs.json"}
        meta = json.loads((folder / "outputs.json").read_text())
        assert meta["files"] == ["normals.png", "depth.npy", "depth.png", "depth.json"]
        assert meta["metadata"]["batch"]["status"] == "done"
        from psmini.io import read_image_raw

        assert read_image_raw(folder / "normals.png")[1] == 16  # as write_outputs: describe reads the slopes back

    def test_near_light_normal_std_written_and_summarised(self, tree, tmp_path):
        """Near light's predicted normal errors reach the output folder (normal_std.npy/.png, their median in
        outputs.json, whatever the outputs chosen) and the summary (normal_std_median_deg); distant rows leave the
        cell empty."""
        summary = reconstruct_dataset(tree / "lotA", tmp_path / "near", outputs="depth", score=False, batch_size=1)
        for row in summary["samples"]:
            expected = reconstruct(load_sample(tree / "lotA" / row["sample"]))
            median = float(expected.normal_std[expected.mask].median())
            assert row["solver"] == "near" and row["normal_std_median_deg"] == pytest.approx(median, rel=1e-5)
            folder = tmp_path / "near" / row["sample"]
            meta = json.loads((folder / "outputs.json").read_text())
            assert meta["files"][-2:] == ["normal_std.npy", "normal_std.png"]
            written = np.load(folder / "normal_std.npy")
            np.testing.assert_allclose(written[expected.mask[0, 0].numpy()],
                                       expected.normal_std[expected.mask].numpy(), rtol=1e-5)
        distant = reconstruct_dataset(tree / "lotA", tmp_path / "distant", DISTANT, outputs="depth", score=False)
        assert all(row["normal_std_median_deg"] == "" for row in distant["samples"])
        assert not (tmp_path / "distant" / "jute" / "normal_std.npy").exists()
        rows = (tmp_path / "near" / "summary.csv").read_text().splitlines()
        column = rows[0].split(",").index("normal_std_median_deg")
        assert all(0 < float(line.split(",")[column]) < 10 for line in rows[1:])

    def test_sample_whose_card_is_missing_fails_alone(self, tree, tmp_path):
        root = _fresh(tree, tmp_path)
        shutil.rmtree(root / "lotB" / "card")
        summary = reconstruct_dataset(root, tmp_path / "out", DISTANT)
        statuses = {row["sample"]: row["status"] for row in summary["samples"]}
        assert statuses["lotB/cotton"] == "failed" and statuses["lotA/jute"] == "done"

    def test_errors(self, tree, tmp_path):
        with pytest.raises(InputError, match="does not exist"):
            reconstruct_dataset(tmp_path / "missing", tmp_path / "out")
        (tmp_path / "empty").mkdir()
        with pytest.raises(InputError, match="no sample folders"):
            reconstruct_dataset(tmp_path / "empty", tmp_path / "out")
        with pytest.raises(InputError, match="subset of normals,albedo,depth,ply"):
            reconstruct_dataset(tree, tmp_path / "out", DISTANT, outputs="normals,mesh")
        for bad in (0, True, 2.0):  # True was taken as a batch of 1
            with pytest.raises(InputError, match="batch_size"):
                reconstruct_dataset(tree, tmp_path / "out", DISTANT, batch_size=bad)
        for bad in (-1, False):
            with pytest.raises(InputError, match="workers"):
                reconstruct_dataset(tree, tmp_path / "out", DISTANT, workers=bad)
        with pytest.raises(InputError, match="ReconstructionConfig"):
            reconstruct_dataset(tree, tmp_path / "out", {"solver": "far"})
        assert not (tmp_path / "out").exists()

    def test_out_over_the_samples_is_refused_before_any_work(self, tree, tmp_path):
        """out = root replaced each capture folder by its outputs: the raw captures were deleted."""
        root = _fresh(tree, tmp_path)
        before = sorted(p.relative_to(root).as_posix() for p in root.rglob("*"))
        with pytest.raises(InputError, match=r"over the sample itself .*apart from ROOT"):
            reconstruct_dataset(root / "lotB", root / "lotB", DISTANT)
        with pytest.raises(InputError, match="over the sample itself"):
            reconstruct_dataset(root / "lotA" / "jute", root / "lotA", DISTANT)  # one sample: out/jute is it
        assert sorted(p.relative_to(root).as_posix() for p in root.rglob("*")) == before


class TestIterReconstructions:
    def test_yields_each_readable_sample(self, tree):
        results = dict(iter_reconstructions(tree, DISTANT, batch_size=4))
        assert sorted(results) == GOOD
        expected = reconstruct(load_sample(tree / "lotA" / "twill"), DISTANT)
        torch.testing.assert_close(results["lotA/twill"].normals, expected.normals, atol=1e-5, rtol=1e-5)
        assert results["lotA/twill"].depth.shape == (1, 1, 64, 64)

    @pytest.mark.slow
    def test_near_light_model(self, tree):
        results = dict(iter_reconstructions(tree / "lotB", ReconstructionConfig(solver="near")))
        expected = reconstruct(load_sample(tree / "lotB" / "cotton"), ReconstructionConfig(solver="near"))
        torch.testing.assert_close(results["cotton"].depth, expected.depth, atol=1e-4, rtol=1e-4)
        assert type(results["cotton"]) is type(expected) and results["cotton"].normal_std.shape == (1, 1, 64, 64)

    def test_errors(self, tmp_path):
        with pytest.raises(InputError, match="does not exist"):
            next(iter_reconstructions(tmp_path / "missing"))


def test_parse_outputs():
    assert parse_outputs(None) == ("normals", "albedo", "depth", "ply")
    assert parse_outputs(["ply", "albedo"]) == ("albedo", "ply")
    for bad in ("", "depth,mesh", ","):
        with pytest.raises(InputError, match="subset of"):
            parse_outputs(bad)
    for bad in (3, [3], b"depth"):  # a TypeError from split or strip before
        with pytest.raises(InputError, match="a comma-separated string or a sequence of names"):
            parse_outputs(bad)  # type: ignore[arg-type]


class TestCommand:
    def test_batch_then_resume(self, tree, tmp_path, capsys):
        out = tmp_path / "out"
        assert main(["batch", str(tree), "--light-model", "distant", "--out", str(out), "--workers", "0",
                     "--no-progress", "--json"]) == 1
        report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert report["counts"] == {"done": 3, "skipped": 0, "failed": 1}
        assert report["solvers"] == ["distant"] and report["config"]["solver"] == "distant"
        assert main(["batch", str(tree / "lotA"), "--light-model", "distant", "--out", str(out / "lotA"),
                     "--workers", "0", "--json"]) == 0
        captured = capsys.readouterr()
        assert json.loads(captured.out.strip().splitlines()[-1])["counts"] == {"done": 0, "skipped": 2, "failed": 0}
        assert "2sample" in captured.err.replace(" ", "")  # the progress bar (on stderr)

    def test_error_paths(self, tree, tmp_path, capsys):
        assert main(["batch", str(tmp_path / "missing"), "--out", str(tmp_path / "out")]) == 1
        assert "does not exist" in capsys.readouterr().err
        (tmp_path / "empty").mkdir()
        assert main(["batch", str(tmp_path / "empty"), "--out", str(tmp_path / "out")]) == 1
        assert "no sample folders" in capsys.readouterr().err
        assert main(["batch", str(tree), "--light-model", "distant", "--out", str(tmp_path / "out"),
                     "--outputs", "depth,mesh"]) == 1
        assert "normals,albedo,depth,ply" in capsys.readouterr().err
        assert not (tmp_path / "out").exists()


def test_robust_method_through_batch(tmp_path):
    """The estimator reaches the solver: the robust estimator gives a different (and valid) reconstruction, and
    every sample's outputs.json records the resolved configuration."""
    from data_synth.rig import write_synthetic_capture

    root = tmp_path / "captures"
    write_synthetic_capture(root, "jute", seed=0, size=48)
    distant = ReconstructionConfig(solver="distant")
    plain = reconstruct_dataset(root, tmp_path / "plain", distant, score=True)
    robust = reconstruct_dataset(root, tmp_path / "robust", dataclasses.replace(distant, estimator="robust"),
                                 score=True)
    (row_plain,), (row_robust,) = [[r for r in s["samples"] if r["status"] == "done"] for s in (plain, robust)]
    assert row_robust["mean_angular_error_deg"] != row_plain["mean_angular_error_deg"]
    assert robust["settings"]["config"]["estimator"] == "robust"
    recorded = json.loads((tmp_path / "robust" / "jute" / "outputs.json").read_text())["metadata"]["config"]
    assert (recorded["solver"], recorded["estimator"], recorded["integrator"]) == ("distant", "robust", "fc")


def test_card_cache_decodes_a_rewritten_card_again_and_keeps_at_most_limit(tree, tmp_path, monkeypatch):
    """A long-lived worker's card cache: a card replaced in place is decoded again; the oldest card goes first."""
    root = _fresh(tree, tmp_path)
    decoded = []
    read_capture = psmini.io.read_capture

    def counting(folder):
        decoded.append(str(folder))
        return read_capture(folder)

    monkeypatch.setattr(psmini.io, "read_capture", counting)
    cards = batch._Cards(torch.device("cpu"), torch.float32, limit=1)
    card_a, card_b = str(root / "lotA" / "card"), str(root / "lotB" / "card")
    shape = (8, 64, 64)
    first, _ = cards.get(card_a, shape)
    cards.get(card_a, shape)
    assert decoded == [card_a]  # decoded once
    manifest = root / "lotA" / "card" / "capture.json"
    stat = manifest.stat()
    os.utime(manifest, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))  # the card was captured again
    again, _ = cards.get(card_a, shape)
    assert decoded == [card_a, card_a] and torch.equal(again, first)
    cards.get(card_b, shape)
    cards.get(card_a, shape)  # dropped to keep one card: decoded once more
    assert decoded == [card_a, card_a, card_b, card_a]
    with pytest.raises(psmini.errors.DataFormatError, match="the card must be imaged under the same LEDs"):
        cards.get(card_a, (8, 32, 32))
