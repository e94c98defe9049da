"""The Dask backend of psmini.batch: same files and summary as the local path, resume, failures, bad addresses."""

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from psmini.batch import reconstruct_dataset
from psmini.cli import main
from psmini.errors import InputError
from tests._captures import DISTANT, GOOD, write_capture_tree

distributed = pytest.importorskip("distributed")

FILES = ["albedo.png", "normals.png", "depth.npy", "depth.png", "depth.json", "points.ply"]


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    return write_capture_tree(tmp_path_factory.mktemp("captures"), size=48)


@pytest.fixture(scope="module")
def cluster():
    """An in-process cluster (threads, no worker processes to start): the tasks still travel through the scheduler."""
    with distributed.LocalCluster(processes=False, n_workers=1, threads_per_worker=2,
                                  dashboard_address=None) as cluster:
        yield cluster


@pytest.fixture(scope="module")
def client(cluster):
    """A client that is not the default one, as a user's may not be."""
    with distributed.Client(cluster, set_as_default=False) as client:
        yield client


def _rows(summary):
    """The summary rows without the times, which differ from run to run."""
    return [{k: v for k, v in row.items() if not k.endswith("_s")} for row in summary["samples"]]


class TestSameAsLocal:
    def test_files_and_summary_equal_the_local_path(self, tree, tmp_path, client):
        local = reconstruct_dataset(tree, tmp_path / "local", DISTANT, batch_size=2)
        dask = reconstruct_dataset(tree, tmp_path / "dask", DISTANT, batch_size=2, client=client)
        assert dask["counts"] == local["counts"] == {"done": 3, "skipped": 0, "failed": 1}
        assert _rows(dask) == _rows(local)  # statuses, batch sizes, errors against ground truth, error messages
        assert dask["settings"]["scheduler"] == client.scheduler.address and local["settings"]["scheduler"] is None
        for name in GOOD:
            for file in FILES:
                assert (tmp_path / "dask" / name / file).read_bytes() == (tmp_path / "local" / name / file).read_bytes()
        csv = [(tmp_path / out / "summary.csv").read_text().splitlines() for out in ("local", "dask")]
        assert [line.split(",")[:2] for line in csv[0]] == [line.split(",")[:2] for line in csv[1]]

    def test_through_a_scheduler_address(self, tree, tmp_path, cluster):
        summary = reconstruct_dataset(tree / "lotB", tmp_path / "out", DISTANT, scheduler=cluster.scheduler_address,
                                      outputs="depth", score=False)
        assert summary["counts"] == {"done": 1, "skipped": 0, "failed": 0}
        assert summary["settings"]["scheduler"] == cluster.scheduler_address
        assert (tmp_path / "out" / "cotton" / "depth.npy").is_file()

    def test_resume_after_a_partial_run(self, tree, tmp_path, client):
        out = tmp_path / "out"
        # a run that covered part of the tree
        first = reconstruct_dataset(tree / "lotA", out / "lotA", DISTANT, client=client)
        assert first["counts"] == {"done": 2, "skipped": 0, "failed": 0}
        stamps = {name: (out / name / "outputs.json").stat().st_mtime_ns for name in GOOD[:2]}
        (out / "lotB").mkdir()
        (out / "lotB" / ".cotton.tmp-0123abcd").mkdir()  # what a run killed while writing cotton leaves behind
        summary = reconstruct_dataset(tree, out, DISTANT, client=client, outputs="depth")
        assert {r["sample"]: r["status"] for r in summary["samples"]} == {
            "lotA/jute": "skipped", "lotA/twill": "skipped", "lotB/cotton": "done", "lotC/broken": "failed"}
        assert stamps == {name: (out / name / "outputs.json").stat().st_mtime_ns for name in GOOD[:2]}
        assert not list(out.rglob(".*"))  # the temporary folder was cleared
        assert np.isfinite(np.load(out / "lotB" / "cotton" / "depth.npy")).any()
        again = reconstruct_dataset(tree, out, DISTANT, client=client)
        assert again["counts"] == {"done": 0, "skipped": 3, "failed": 1}


class TestFailures:
    def test_a_failing_sample_does_not_stop_the_others(self, tree, tmp_path, client):
        summary = reconstruct_dataset(tree, tmp_path / "out", DISTANT, batch_size=4, client=client, score=False)
        rows = {row["sample"]: row for row in summary["samples"]}
        assert rows["lotC/broken"]["status"] == "failed" and "led_03.png" in rows["lotC/broken"]["error"]
        assert all(rows[name]["status"] == "done" for name in GOOD)
        assert not (tmp_path / "out" / "lotC" / "broken").exists()

    @pytest.mark.skipif(torch.cuda.is_available(), reason="needs a worker without CUDA")
    def test_a_raising_task_fails_its_own_samples_and_the_run_goes_on(self, tree, tmp_path, client):
        summary = reconstruct_dataset(
            tree, tmp_path / "out", dataclasses.replace(DISTANT, device="cuda"), batch_size=2, client=client
        )
        assert summary["counts"] == {"done": 0, "skipped": 0, "failed": 4}
        assert all("no CUDA device on this worker" in row["error"] for row in summary["samples"])
        assert json.loads((tmp_path / "out" / "summary.json").read_text())["counts"]["failed"] == 4

    def test_unreachable_scheduler_is_a_clear_error(self, tree, tmp_path):
        with pytest.raises(InputError, match="cannot reach the Dask scheduler at 'tcp://127.0.0.1:1' within 1 s"):
            reconstruct_dataset(tree, tmp_path / "out", DISTANT, scheduler="tcp://127.0.0.1:1", scheduler_timeout_s=1.0)
        assert not (tmp_path / "out").exists()

    def test_bad_arguments(self, tree, tmp_path, client):
        for bad in ("local:0", "local:two", ""):
            with pytest.raises(InputError, match="local|scheduler"):
                reconstruct_dataset(tree, tmp_path / "out", DISTANT, scheduler=bad)
        with pytest.raises(InputError, match="not both"):
            reconstruct_dataset(tree, tmp_path / "out", DISTANT, scheduler="local:1", client=client)
        assert not (tmp_path / "out").exists()

    def test_missing_dask_names_the_extra(self, tree, tmp_path, monkeypatch):
        monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed now raises ImportError
        with pytest.raises(InputError, match=r"pip install 'psmini\[dask\]'"):
            reconstruct_dataset(tree, tmp_path / "out", DISTANT, scheduler="tcp://127.0.0.1:8786")


@pytest.mark.slow
def test_importing_psmini_does_not_import_dask():
    code = ("import sys, psmini, psmini.batch, psmini.cli; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed')))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "[]"


class TestCommand:
    @pytest.mark.slow
    def test_local_cluster_from_the_command_line(self, tree, tmp_path, capsys):
        out = tmp_path / "out"
        code = main(["batch", str(tree / "lotA"), "--light-model", "distant", "--out", str(out),
                     "--scheduler", "local:1", "--no-score", "--outputs", "depth", "--no-progress", "--json"])
        assert code == 0
        report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert report["counts"] == {"done": 2, "skipped": 0, "failed": 0}
        assert json.loads((out / "summary.json").read_text())["settings"]["scheduler"] == "local:1"
        assert sorted(p.name for p in (out / "jute").iterdir()) == ["depth.json", "depth.npy", "depth.png",
                                                                   "outputs.json"]

    def test_unreachable_scheduler(self, tree, tmp_path, capsys):
        code = main(["batch", str(tree), "--light-model", "distant", "--out", str(tmp_path / "out"), "--scheduler", "tcp://127.0.0.1:1",
                     "--scheduler-timeout", "1", "--no-progress"])
        assert code == 1
        assert "cannot reach the Dask scheduler" in capsys.readouterr().err
