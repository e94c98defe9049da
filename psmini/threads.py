r"""How psmini's threads wait and how many there are: concurrent processes must not stall each other.

PyTorch's CPU build runs its intra-op parallelism on GNU OpenMP (libgomp). Unless told otherwise, libgomp's
threads *spin* at the end of every parallel region, waiting for the others of their team (``GOMP_SPINCOUNT``
300,000 spins; only a process that itself asks for more threads than cores throttles this). psmini's maths is
thousands of short parallel regions (element-wise passes over a capture), so when several processes share the
cores (a second job, a Jupyter kernel, the test suite), a thread spins through its whole time slice waiting for a
team-mate that the scheduler has parked, at every region. On a 2-core machine, three concurrent bilateral
integrations of a 612 × 512 normal map took 6–32 s each instead of 0.5 s alone; near light on one 8 × 400² capture,
while two other jobs ran, 26–34 s instead of about 1 s. With ``OMP_WAIT_POLICY=PASSIVE`` the idle threads sleep
instead, and the same runs took 1.0–1.3 s (``benchmarks/concurrency.py`` measures it).

The wait policy is read once, when torch loads its OpenMP runtime, so it must be in the environment before
``import torch``. :func:`prefer_passive_waiting` sets it (unless the user chose a policy) when psmini is imported
before torch: every ``psmini`` command, every worker process psmini starts, and every script or notebook that
imports psmini first. A session that imported torch first keeps torch's spinning threads; set
``OMP_WAIT_POLICY=PASSIVE`` in its environment, or use one thread (:func:`set_threads`).

Sleeping threads do not make many threads cheap: on a machine already busy, every short parallel region waits for
a team-mate to be woken and scheduled. Three concurrent bilateral integrations on two cores with other work running
took 7.2 times as long as the same work run one after another with two threads each (passive; three near-light
solves 7.0 times), 0.56 times with the one thread each that :func:`choose_threads` gave them (0.79) at ``a1d725c``.
So psmini's commands start with one thread per *idle* core (:func:`choose_threads`: the usable cores less the
other threads the kernel has runnable at that instant, at least one), unless ``psmini --threads N`` or
``OMP_NUM_THREADS`` says otherwise; in Python, :func:`set_threads` sets the count and :func:`idle_cores` says what
the commands would choose. A library import leaves torch's count alone. ``psmini batch`` divides the threads among
its worker processes.
"""

from __future__ import annotations

import os
import sys

from psmini.errors import InputError

__all__ = ["choose_threads", "idle_cores", "prefer_passive_waiting", "set_threads", "usable_cores"]


def prefer_passive_waiting() -> bool:
    """Ask OpenMP to put idle threads to sleep (``OMP_WAIT_POLICY=PASSIVE``) unless a policy was chosen.

    Must run before torch is imported (its OpenMP runtime reads the variable once, when it loads). The variable is
    left set, so the worker processes this one starts wait the same way.

    Returns:
        whether this process's OpenMP threads wait passively: the policy is PASSIVE and torch was not loaded before
        it was set.
    """
    torch_loaded = "torch" in sys.modules
    if not torch_loaded:
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    return not torch_loaded and os.environ["OMP_WAIT_POLICY"].upper() == "PASSIVE"


def usable_cores() -> int:
    """The number of CPUs this process may run on (its affinity mask, as ``taskset`` or a container sets it)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS and Windows have no affinity masks
        return os.cpu_count() or 1


def _other_runnable_threads() -> int:
    """Threads the kernel has runnable right now besides this one: ``/proc/loadavg``'s fourth field (instantaneous,
    so that processes started together see each other), or the 1-minute load average where there is no ``/proc``."""
    try:
        with open("/proc/loadavg", encoding="ascii") as file:
            return max(0, int(file.read().split()[3].split("/")[0]) - 1)
    except (OSError, ValueError, IndexError):
        return round(os.getloadavg()[0]) if hasattr(os, "getloadavg") else 0


def idle_cores() -> int:
    """The usable cores (:func:`usable_cores`) that no other runnable thread is using now, at least 1.

    Example:
        >>> 1 <= idle_cores() <= usable_cores()
        True
    """
    return max(1, usable_cores() - _other_runnable_threads())


def choose_threads() -> int:
    """What every ``psmini`` command does first without ``--threads``: one intra-op thread per idle core
    (:func:`idle_cores`), unless ``OMP_NUM_THREADS`` chose a count, which is kept.

    Returns:
        the number of threads torch now uses.
    """
    if os.environ.get("OMP_NUM_THREADS"):
        import torch

        return torch.get_num_threads()
    return set_threads(idle_cores())


def set_threads(threads: int | None = None) -> int:
    """Set the number of intra-op threads of torch in this process (the ``psmini --threads`` option).

    Args:
        threads: how many; ``None``: one per core this process may use (:func:`usable_cores`).

    Returns:
        the number of threads set.

    Raises:
        InputError: for a count that is not a positive integer.

    Example:
        >>> import torch
        >>> before = torch.get_num_threads()
        >>> set_threads(1)
        1
        >>> _ = set_threads(before)
    """
    if threads is None:
        threads = usable_cores()
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise InputError(f"threads must be a positive integer, got {threads!r}")
    import torch

    torch.set_num_threads(threads)
    return threads
