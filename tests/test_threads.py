"""psmini's threads: OpenMP waits passively when psmini comes first, and ``--threads`` / ``set_threads`` set the
count."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

from psmini import InputError, set_threads, threads
from psmini.threads import choose_threads, idle_cores, usable_cores


def _python(code: str, **env: str) -> str:
    environment = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"} | env
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                          env=environment).stdout.strip()


def test_importing_psmini_first_makes_openmp_wait_passively():
    code = "import os, psmini, torch; print(os.environ['OMP_WAIT_POLICY'], psmini.threads.prefer_passive_waiting())"
    # the second call comes after torch loaded: it reports that the policy can no longer change
    assert _python(code) == "PASSIVE False"


def test_a_policy_the_user_chose_is_kept():
    assert _python("import os, psmini; print(os.environ['OMP_WAIT_POLICY'])", OMP_WAIT_POLICY="ACTIVE") == "ACTIVE"


def test_after_torch_the_environment_is_left_alone():
    code = "import os, torch, psmini; print(os.environ.get('OMP_WAIT_POLICY'))"
    assert _python(code) == "None"


def test_set_threads_sets_torch_and_defaults_to_the_usable_cores():
    before = torch.get_num_threads()
    try:
        assert set_threads(1) == 1 and torch.get_num_threads() == 1
        assert set_threads() == usable_cores() == torch.get_num_threads()
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("bad", [0, -2, 1.5, True, "2"])
def test_set_threads_refuses_what_is_not_a_positive_count(bad):
    with pytest.raises(InputError, match="positive integer"):
        set_threads(bad)


def test_cli_threads_option(tmp_path, capsys):
    from psmini.cli import main

    normals = torch.zeros(3, 8, 8)
    normals[2] = 1
    import numpy as np

    np.save(tmp_path / "n.npy", normals.numpy())
    before = torch.get_num_threads()
    try:
        assert main(["--threads", "1", "integrate", str(tmp_path / "n.npy"), "--out", str(tmp_path / "z.npy")]) == 0
        assert torch.get_num_threads() == 1
        assert main(["--threads", "0", "integrate", str(tmp_path / "n.npy"), "--out", str(tmp_path / "z.npy")]) == 1
        assert "threads must be a positive integer, got 0" in capsys.readouterr().err
    finally:
        torch.set_num_threads(before)


def test_idle_cores_are_the_usable_ones_no_other_thread_runs_on(monkeypatch):
    monkeypatch.setattr(threads, "usable_cores", lambda: 8)
    monkeypatch.setattr(threads, "_other_runnable_threads", lambda: 0)
    assert idle_cores() == 8
    monkeypatch.setattr(threads, "_other_runnable_threads", lambda: 3)
    assert idle_cores() == 5
    monkeypatch.setattr(threads, "_other_runnable_threads", lambda: 40)  # a busy machine: one thread, never none
    assert idle_cores() == 1


def test_other_runnable_threads_reads_the_kernels_count():
    count = threads._other_runnable_threads()
    assert isinstance(count, int) and count >= 0


def test_choose_threads_takes_the_idle_cores_unless_omp_num_threads_chose(monkeypatch):
    before = torch.get_num_threads()
    monkeypatch.setattr(threads, "usable_cores", lambda: 2)
    monkeypatch.setattr(threads, "_other_runnable_threads", lambda: 5)
    try:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
        torch.set_num_threads(2)
        assert choose_threads() == 1 and torch.get_num_threads() == 1
        monkeypatch.setattr(threads, "_other_runnable_threads", lambda: 0)
        assert choose_threads() == 2 and torch.get_num_threads() == 2
        monkeypatch.setenv("OMP_NUM_THREADS", "1")
        torch.set_num_threads(1)
        monkeypatch.setattr(threads, "_other_runnable_threads", lambda: 0)
        assert choose_threads() == 1  # the user's count is kept
    finally:
        torch.set_num_threads(before)


def test_cli_without_threads_takes_the_idle_cores(tmp_path, monkeypatch):
    import numpy as np

    from psmini.cli import main

    normals = torch.zeros(3, 8, 8)
    normals[2] = 1
    np.save(tmp_path / "n.npy", normals.numpy())
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(threads, "_other_runnable_threads", lambda: 10**6)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert main(["integrate", str(tmp_path / "n.npy"), "--out", str(tmp_path / "z.npy")]) == 0
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
