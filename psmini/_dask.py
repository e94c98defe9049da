"""The Dask backend of :mod:`psmini.batch`: run chunks of samples as tasks of a ``dask.distributed`` cluster.

``dask[distributed]`` is optional (``pip install psmini[dask]``) and imported only here, only when a run asks for
a cluster: importing psmini or :mod:`psmini.batch` never imports dask.

A cluster user starts a scheduler (``dask scheduler``) and workers (``dask worker tcp://HEAD:8786``) on machines
that see the data and the output folder at the same paths, then passes the scheduler's address; each task
decodes, solves and writes its chunk on its worker's device (see docs/guides/batch.md).
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from psmini.errors import InputError

logger = logging.getLogger(__name__)

_INSTALL = "pip install 'psmini[dask]'"


def parse_scheduler(scheduler: str | None) -> int | None:
    """The worker count of ``"local"`` / ``"local:N"`` (``"local"``: the CPU count), or None for an address.

    Raises:
        InputError: ``local:`` followed by anything but a positive integer, or an empty address.

    Example:
        >>> parse_scheduler("local:2"), parse_scheduler("tcp://head:8786")
        (2, None)
    """
    if not isinstance(scheduler, str) or not scheduler.strip():
        raise InputError(f"scheduler must be a Dask scheduler address or local[:N], got {scheduler!r}")
    if scheduler == "local":
        return os.cpu_count() or 1
    match = re.fullmatch(r"local:(\d+)", scheduler)
    if scheduler.startswith("local") and (match is None or int(match.group(1)) < 1):
        raise InputError(f"a local cluster is local or local:N with N >= 1 worker processes, got {scheduler!r}")
    return None if match is None else int(match.group(1))


def _distributed():
    try:
        import distributed
    except ImportError as error:
        raise InputError(f"the Dask backend needs dask.distributed, which is not installed: {_INSTALL}") from error
    return distributed


@contextmanager
def connect(scheduler: str | None, client: Any = None, timeout_s: float = 10.0) -> Iterator[Any]:
    """A ``distributed.Client`` for the run: ``client`` as given (left open), a fresh ``LocalCluster`` for
    ``local[:N]`` (closed after), or a connection to the scheduler at ``scheduler`` (closed after).

    Raises:
        InputError: dask.distributed missing, a scheduler that does not answer within ``timeout_s`` seconds, or a
            cluster with no worker after ``timeout_s`` seconds.
    """
    if client is not None:
        yield client
        return
    distributed = _distributed()
    local = parse_scheduler(scheduler)
    if local is not None:
        # single-threaded worker processes (the nanny sets OMP_NUM_THREADS=1: one sample per core); the scheduler's
        # web server on a free port (8787 may belong to another cluster)
        with distributed.LocalCluster(n_workers=local, threads_per_worker=1, processes=True, dashboard_address=":0",
                                      silence_logs=logging.WARNING) as cluster, distributed.Client(cluster) as own:
            yield own
        return
    try:
        own = distributed.Client(scheduler, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as error:
        raise InputError(
            f"cannot reach the Dask scheduler at {scheduler!r} within {timeout_s:g} s ({type(error).__name__}: "
            f"{error}); start one with `dask scheduler` and pass its address (tcp://HOST:8786), or use local[:N]"
        ) from error
    with own:
        yield own


def map_chunks(task: Callable[[Any], list], chunks: Sequence[Any], *, scheduler: str | None, client: Any = None,
               timeout_s: float = 10.0) -> Iterator[tuple[int, list | None, BaseException | None]]:
    """Run ``task(chunk)`` for every chunk on the cluster and yield ``(index, result, error)`` as tasks finish.

    A task that raises, or whose worker dies, yields its exception as ``error`` and the others go on.

    Raises:
        InputError: as :func:`connect`.
    """
    distributed = _distributed()
    with connect(scheduler, client, timeout_s) as dask_client:
        try:
            dask_client.wait_for_workers(1, timeout=timeout_s)
        except (TimeoutError, OSError) as error:
            raise InputError(f"the Dask cluster at {dask_client.scheduler.address} has no worker after "
                             f"{timeout_s:g} s; start some with `dask worker ADDRESS`") from error
        logger.info("sending %d chunks to %d Dask workers", len(chunks), len(dask_client.nthreads()))
        futures = {dask_client.submit(task, chunk, pure=False): index for index, chunk in enumerate(chunks)}
        for future in distributed.as_completed(futures, loop=dask_client.loop):  # the client need not be the default
            index = futures.pop(future)
            try:
                result = future.result()
            except Exception as error:  # noqa: BLE001 - a raising task, a lost worker: that chunk fails, not the run
                yield index, None, error
            else:
                yield index, result, None
