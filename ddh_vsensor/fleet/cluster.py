"""Running the fleet's tasks on Dask: a small LocalCluster on 127.0.0.1 by default, or an
existing scheduler. Results come back in the order of the inputs, whichever worker ran them,
so a local run and a cluster run give the same store and the same report.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from ddh_vsensor.errors import UserError

Progress = Callable[[int, int, Any], None]
DEFAULT_WORKERS = 2


@contextmanager
def dask_client(scheduler: str | None = None, workers: int = DEFAULT_WORKERS,
                worker_timeout_s: float = 30.0) -> Iterator[Any]:
    """A Dask client: to ``scheduler`` (``tcp://host:port``), once it has a worker (at most
    ``worker_timeout_s``: a scheduler without workers would hold every task forever), or
    to a LocalCluster of ``workers`` single-threaded processes bound to 127.0.0.1, without
    dashboard. The
    scheduler's HTTP server (health, metrics) is served anyway, on 8787 unless told: a free
    port of 127.0.0.1, so that two clusters on one host do not contend for it."""
    import logging

    from dask.distributed import Client, LocalCluster
    logging.getLogger("distributed").setLevel(logging.ERROR)
    if scheduler:
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as exc:
            raise UserError(f"--scheduler {scheduler}: cannot connect: {exc}") from None
        try:
            try:
                client.wait_for_workers(1, timeout=worker_timeout_s)
            except TimeoutError:
                raise UserError(f"--scheduler {scheduler}: no worker joined within "
                                f"{worker_timeout_s:g} s (start one with 'dask worker "
                                f"{scheduler}')") from None
            yield client
        finally:
            client.close()
        return
    if not 1 <= workers <= 64:
        raise UserError(f"--workers {workers}: 1..64")
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           host="127.0.0.1", dashboard_address=None,
                           scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                           silence_logs=logging.ERROR)
    client = Client(cluster)
    try:
        yield client
    finally:
        client.close()
        cluster.close()


def run_tasks(client: Any, fn: Callable[[Any], Any], items: Sequence[Any],
              progress: Progress | None = None) -> list[Any]:
    """``fn`` over ``items`` on the cluster; results in input order; ``progress(done, total,
    result)`` as each one finishes."""
    from dask.distributed import as_completed
    futures = client.map(fn, list(items), pure=False)
    index = {f.key: i for i, f in enumerate(futures)}
    results: list[Any] = [None] * len(futures)
    for done, future in enumerate(as_completed(futures), start=1):
        results[index[future.key]] = future.result()
        if progress is not None:
            progress(done, len(futures), results[index[future.key]])
    return results


MAX_BATCH = 16


def batch_size(n_items: int, n_workers: int) -> int:
    """Items per task: at least four tasks per worker (balance, progress), at most
    :data:`MAX_BATCH` items each (a task's fixed costs shared by many items)."""
    return max(1, min(MAX_BATCH, n_items // (4 * max(n_workers, 1))))


def run_batched(client: Any, fn: Callable[[list[Any]], list[Any]], items: Sequence[Any],
                progress: Progress | None = None) -> list[Any]:
    """``fn`` (a list of items in, one result per item out) over ``items`` in batches;
    results in input order; ``progress(done, total, result)`` per item as its batch ends."""
    items = list(items)
    size = batch_size(len(items), len(client.scheduler_info()["workers"]))
    batches = [items[i:i + size] for i in range(0, len(items), size)]
    done = 0

    def counted(_d: int, _n: int, results: list[Any]) -> None:
        nonlocal done
        for r in results:
            done += 1
            if progress is not None:
                progress(done, len(items), r)

    return [r for batch in run_tasks(client, fn, batches, counted) for r in batch]
