"""The experiment's renders on a Dask cluster (``stereorepro experiment --scheduler local:N | tcp://HOST:PORT``;
needs the ``[distributed]`` extra).

Every render of the run (each frame and eye's G-buffer, reference chunks and lean ladder: :func:`.inputs.eye_tasks`)
becomes one Dask task whose key is its cache entry's name, so the same render is never submitted twice and Dask
retries a task whose worker died. A worker renders into the shared, content-addressed cache (``cache_dir`` on a
filesystem every worker and the client see) and returns only the entry's name; once every task is done, the client
runs the analysis in process, reading the same entries as an in-process run would: **the tables are identical**
whichever machine rendered what (tested with a LocalCluster and with a scheduler and workers started as separate
processes).

* **Code versions**: every task carries the client's renderer version (:func:`.cache.code_version`); a worker whose
  own differs refuses it with an error naming the worker, and the client checks every connected worker first.
* **Races**: two workers making one entry both write a complete temporary and rename it into place (atomic); one
  valid entry remains.
* **Resume**: a killed run (or worker) leaves only complete entries; the rerun submits every task again and the
  ones already in the cache return at once.
* ``force``: the client removes the run's entries before submitting (workers then render them anew).
"""

from __future__ import annotations

import functools
import os
import socket
import time
from dataclasses import dataclass, replace

from ..._extras import require
from ...errors import StereoreproError
from .cache import RenderCache, code_version
from .inputs import (
    RenderSpec,
    eye_tasks,
    gbuffer_task,
    jitter_gbuffer_task,
    jitter_sample_task,
    ladder_task,
    reference_chunk_task,
    worker_context,
)

__all__ = [
    "render_all",
    "run_task",
    "connect",
    "open_cluster",
    "Cluster",
    "task_key",
    "ClusterError",
    "CONNECT_TIMEOUT",
]

#: How long the client waits for a ``tcp://`` scheduler.
CONNECT_TIMEOUT = "30s"


class ClusterError(StereoreproError, RuntimeError):
    """The cluster cannot run this experiment: the scheduler is unreachable, has no workers, or a worker runs
    other renderer code (the command line reports it in one line, exit code 2).

    Examples:
        >>> from stereorepro.workflows.experiment.distributed import ClusterError
        >>> try:
        ...     raise ClusterError("no Dask workers are connected to tcp://10.0.0.5:8786")
        ... except RuntimeError as e:
        ...     print(type(e).__name__, isinstance(e, RuntimeError))
        ClusterError True
    """


_TASKS = {
    "gbuffer_task": gbuffer_task,
    "reference_chunk_task": reference_chunk_task,
    "ladder_task": ladder_task,
    "jitter_gbuffer_task": jitter_gbuffer_task,
    "jitter_sample_task": jitter_sample_task,
}


@functools.lru_cache(maxsize=1)
def _own_code() -> str:
    return code_version()


def worker_code_version() -> str:
    """This process's renderer version (run on every worker by :func:`render_all`)."""
    return _own_code()


def run_task(spec: RenderSpec, name: str, args: tuple, *deps) -> str:
    """Run one render task on this worker (``deps``: the results of the tasks it must follow; unused) and
    return the name of its cache entry.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from stereorepro.scenes import load_scene
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.inputs import spec_for
        >>> from stereorepro.workflows.experiment.distributed import run_task
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, reference_chunk_spp=2)
        >>> spec = spec_for(cfg, load_scene(cfg.scene), tmp.name)
        >>> run_task(spec, "reference_chunk_task", (0, 1, 0))  # what a Dask worker runs, here in process
        'reference_chunk_task'
        >>> len(list(Path(tmp.name).glob("*.npz")))
        1
        >>> tmp.cleanup()
    """
    own = _own_code()
    if spec.client_code and own != spec.client_code:
        raise RuntimeError(
            f"worker {socket.gethostname()} (pid {os.getpid()}) runs renderer code {own}, the client "
            f"{spec.client_code}: install the same stereorepro version on every worker"
        )
    ctx = worker_context(spec)
    _TASKS[name](ctx, *args)
    return name


def task_key(cache: RenderCache, name: str, key: dict) -> str:
    """The Dask key of a render task: its kind and its cache entry's file name.

    Examples:
        >>> import tempfile
        >>> from stereorepro.workflows.experiment.cache import RenderCache
        >>> from stereorepro.workflows.experiment.distributed import task_key
        >>> with tempfile.TemporaryDirectory() as d:
        ...     k = task_key(RenderCache(d), "gbuffer_task", {"frame": 0, "eye": 1})
        >>> k.startswith("gbuffer_task-"), len(k) - len("gbuffer_task-")
        (True, 32)
    """
    return f"{name}-{cache.path(key).stem}"


def connect(scheduler: str):
    """A Dask client for ``"local:N"`` (a LocalCluster of N single-threaded worker processes, this machine) or
    ``"tcp://HOST:PORT"`` (a running scheduler); returns (client, cluster or None).

    Examples:
        >>> from stereorepro.workflows.experiment.distributed import connect
        >>> from distributed import LocalCluster
        >>> lc = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0")
        >>> client, local = connect(lc.scheduler_address)  # a running scheduler (here one in this process)
        >>> type(client).__name__, local
        ('Client', None)
        >>> client.close(); lc.close()
    """
    distributed = require("distributed", "--scheduler (Dask)")
    Client, LocalCluster = distributed.Client, distributed.LocalCluster
    if scheduler.startswith("local:"):
        cluster = LocalCluster(
            n_workers=int(scheduler.split(":", 1)[1]), threads_per_worker=1, processes=True, dashboard_address=":0"
        )
        return Client(cluster), cluster
    try:
        return Client(scheduler, timeout=CONNECT_TIMEOUT), None
    except OSError as e:
        raise ClusterError(f"cannot reach the Dask scheduler at {scheduler} ({e})") from None


@dataclass
class Cluster:
    """A connected Dask cluster whose workers all run this client's renderer code (:func:`open_cluster`).

    Examples:
        >>> from stereorepro.workflows.experiment.distributed import Cluster
        >>> c = Cluster("tcp://10.0.0.5:8786", client=None, local=None, workers=4)  # normally from open_cluster
        >>> c.scheduler, c.workers
        ('tcp://10.0.0.5:8786', 4)
    """

    scheduler: str
    client: object
    local: object | None  #: the LocalCluster started for ``"local:N"``, else None
    workers: int

    def close(self) -> None:
        self.client.close()
        if self.local is not None:
            self.local.close()


def open_cluster(scheduler: str) -> Cluster:
    """Connect to ``scheduler`` and check its workers (at least one, each running this client's renderer code):
    ClusterError otherwise, with nothing left open. A run opens its cluster before it creates any folder.

    Examples:
        >>> from stereorepro.workflows.experiment.distributed import open_cluster
        >>> from distributed import LocalCluster
        >>> lc = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0")
        >>> cluster = open_cluster(lc.scheduler_address)
        >>> cluster.workers, cluster.local
        (1, None)
        >>> cluster.close(); lc.close()
    """
    client, local = connect(scheduler)
    try:
        versions = client.run(worker_code_version)
        if not versions:
            raise ClusterError(f"no Dask workers are connected to {scheduler}")
        own = _own_code()
        bad = {w: v for w, v in versions.items() if v != own}
        if bad:
            w, v = next(iter(bad.items()))
            raise ClusterError(
                f"worker {w} runs renderer code {v}, this client {own}: install the same stereorepro "
                f"version on every worker ({len(bad)} of {len(versions)} differ)"
            )
    except BaseException:
        Cluster(scheduler, client, local, 0).close()
        raise
    return Cluster(scheduler, client, local, len(versions))


def render_all(
    spec: RenderSpec, frames, scheduler: str | Cluster, force: bool = False, progress: bool = True, log=print
) -> dict:
    """Render every input of ``frames`` (both eyes) on the cluster ``scheduler`` (a ``"local:N"`` /
    ``"tcp://HOST:PORT"`` address, or a :class:`Cluster` from :func:`open_cluster`, closed here) into
    ``spec.cache_dir``.

    Returns what the run's ``results.json`` records under ``"distributed"``: the scheduler, the number of workers
    and of tasks, how many were already cached, and the wall time.

    Examples:
        >>> import tempfile
        >>> from distributed import Client
        >>> from stereorepro.scenes import load_scene
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.inputs import spec_for
        >>> from stereorepro.workflows.experiment.distributed import Cluster, render_all
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, reference_chunk_spp=2)
        >>> spec = spec_for(cfg, load_scene(cfg.scene), tmp.name)
        >>> from distributed import LocalCluster
        >>> lc = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0")
        >>> cluster = Cluster("in-process", Client(lc), lc, workers=1)  # closed by render_all
        >>> r = render_all(spec, range(1), cluster, progress=False, log=lambda message: None)
        >>> r["workers"], r["tasks"], r["cached"]  # per eye: G-buffer, two reference chunks, ladder
        (1, 8, 0)
        >>> tmp.cleanup()
    """
    as_completed = require("distributed", "--scheduler (Dask)").as_completed
    tqdm = require("tqdm.auto", "the experiment's progress bar", extra="experiment").tqdm

    t0 = time.perf_counter()
    cl = scheduler if isinstance(scheduler, Cluster) else open_cluster(scheduler)
    client, n_workers = cl.client, cl.workers
    try:
        if spec.workers is None and cl.local is not None:  # share this machine's cores among the local workers
            spec = replace(spec, workers=max(1, (os.cpu_count() or 1) // n_workers))
        spec = replace(spec, client_code=_own_code())
        cache = RenderCache(spec.cache_dir, sweep_on_start=False)
        futures, cached = [], 0
        for f in frames:
            for eye in (0, 1):
                chunk_futures = []
                for name, args, key in eye_tasks(spec, f, eye):
                    path = cache.path(key)
                    if force and path.exists():
                        path.unlink()
                    cached += path.exists()
                    deps = chunk_futures if name == "ladder_task" else []
                    fut = client.submit(
                        run_task, spec, name, args, *deps, key=task_key(cache, name, key), retries=3, pure=False
                    )
                    if name == "reference_chunk_task":
                        chunk_futures.append(fut)
                    futures.append(fut)
        bar = tqdm(total=len(futures), desc=f"renders on {n_workers} workers", unit="task", disable=not progress)
        for fut in as_completed(futures):
            fut.result()  # raises the task's error (after Dask's retries)
            bar.update(1)
        bar.close()
        wall = time.perf_counter() - t0
        log(
            f"distributed: {len(futures)} render tasks ({cached} already cached) on {n_workers} workers in {wall:.1f} s"
        )
        return {
            "scheduler": cl.scheduler,
            "workers": n_workers,
            "tasks": len(futures),
            "cached": cached,
            "wall_s": wall,
        }
    finally:
        cl.close()
