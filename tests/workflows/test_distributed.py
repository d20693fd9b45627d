"""Renders on Dask (``experiment --scheduler``): the tables equal the in-process run's whichever worker rendered
what, a killed worker does not change them, racing workers leave one valid entry, foreign code is refused."""

import json
import multiprocessing as mp
import socket
import subprocess
import sys
import threading
import time

import pytest

pytest.importorskip("distributed")

from stereorepro.errors import StereoreproError  # noqa: E402
from stereorepro.workflows.experiment import ExperimentConfig, RenderCache, run_experiment  # noqa: E402
from stereorepro.workflows.experiment import distributed as dist  # noqa: E402
from stereorepro.workflows.experiment.inputs import RenderSpec, eye_tasks  # noqa: E402

SMALL = dict(
    scene="living_room",
    frames=2,
    width=160,
    height=90,
    reference_spp=16,
    reference_chunk_spp=8,
    ladder_spp=4,
    progress=False,
    alphas=(0.5,),
    flip=False,
)
# 160 x 90 x 3 values: above torch's parallel grain, so a float64 sum's last bits depend on the thread count (the
# workers run single-threaded; the ladder's RMSEs must still equal the in-process run's)


def same_tables(a: dict, b: dict) -> None:
    assert a["table1"] == b["table1"] and a["table2"] == b["table2"]
    assert a["table2_variants"] == b["table2_variants"] and a["reference_study"] == b["reference_study"]
    assert a["temporal_error"] == b["temporal_error"]
    for ra, rb in zip(a["per_frame"], b["per_frame"], strict=True):
        assert ra["rmse"] == rb["rmse"] and ra["ladder_rmse"] == rb["ladder_rmse"]
        assert ra["temporal_error"] == rb["temporal_error"]


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    out = tmp_path_factory.mktemp("serial")
    return run_experiment(ExperimentConfig(out=str(out), **SMALL), log=lambda *a: None)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def cluster(tmp_path):
    """A scheduler and two workers (no nanny: a killed worker stays dead), each its own process on 127.0.0.1."""
    port = _free_port()
    common = ["--no-dashboard"]
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "distributed.cli.dask_scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
                *common,
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    ]
    addr = f"tcp://127.0.0.1:{port}"
    for _ in range(2):
        procs.append(
            subprocess.Popen(
                [sys.executable, "-m", "distributed.cli.dask_worker", addr, "--nthreads", "1", "--no-nanny", *common],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        )
    from distributed import Client

    client = Client(addr, timeout="60s")
    try:
        client.wait_for_workers(2, timeout=60)
        pids = client.run(lambda: __import__("os").getpid())
    finally:
        client.close()
    yield addr, list(pids.values())
    for p in procs:
        p.kill()
        p.wait()


class TestDistributed:
    def test_local_cluster_equals_in_process(self, serial, tmp_path):
        res = run_experiment(ExperimentConfig(out=str(tmp_path), scheduler="local:2", **SMALL), log=lambda *a: None)
        same_tables(serial, res)
        d = res["distributed"]
        assert d["workers"] == 2 and d["tasks"] == 2 * 2 * (1 + 2 + 1) and d["cached"] == 0
        assert res["cache"]["misses"] == 0  # the analysis only read what the workers wrote

    def test_scheduler_and_workers_as_processes(self, serial, cluster, tmp_path):
        addr, _ = cluster
        res = run_experiment(ExperimentConfig(out=str(tmp_path), scheduler=addr, **SMALL), log=lambda *a: None)
        same_tables(serial, res)
        # a rerun finds every render in the cache
        again = run_experiment(ExperimentConfig(out=str(tmp_path), scheduler=addr, **SMALL), log=lambda *a: None)
        assert again["distributed"]["cached"] == again["distributed"]["tasks"]
        same_tables(serial, again)

    def test_killed_worker(self, serial, cluster, tmp_path):
        """A worker killed mid-run: Dask moves its tasks to the other worker and the tables do not change."""
        addr, pids = cluster
        cache = tmp_path / "cache"
        killed = []

        def kill_after_first_entry():
            for _ in range(600):
                if cache.is_dir() and any(cache.glob("*.npz")):
                    subprocess.run(["kill", "-9", str(pids[0])], check=False)
                    killed.append(pids[0])
                    return
                time.sleep(0.05)

        t = threading.Thread(target=kill_after_first_entry)
        t.start()
        res = run_experiment(
            ExperimentConfig(out=str(tmp_path), scheduler=addr, cache_dir=str(cache), **SMALL), log=lambda *a: None
        )
        t.join()
        assert killed
        same_tables(serial, res)

    def test_racing_workers_leave_one_entry(self, tmp_path):
        spec = RenderSpec(
            scene="living_room",
            width=32,
            height=18,
            seed=0,
            ladder_spp=3,
            reference_spp=4,
            reference_chunk_spp=4,
            base_key=json.dumps({"race": 1}),
            cache_dir=str(tmp_path),
            workers=1,
        )
        with mp.get_context("spawn").Pool(2) as pool:
            names = pool.starmap(dist.run_task, [(spec, "ladder_task", (0, 1))] * 2)
        assert names == ["ladder_task"] * 2
        files = sorted(p.name for p in tmp_path.iterdir())
        assert len(files) == 2 and all(f.endswith(".npz") for f in files)  # the chunk and the ladder, no temporaries
        cache = RenderCache(tmp_path)
        for _, _, key in eye_tasks(spec, 0, 1)[1:]:
            cache.get_or_make(key, lambda: pytest.fail("a racing write left an invalid entry"))

    def test_foreign_code_is_refused(self, tmp_path, monkeypatch):
        spec = RenderSpec(
            scene="living_room",
            width=32,
            height=18,
            seed=0,
            ladder_spp=3,
            reference_spp=4,
            reference_chunk_spp=4,
            base_key="{}",
            cache_dir=str(tmp_path),
            client_code="0" * 16,
        )
        with pytest.raises(RuntimeError, match="runs renderer code .* the client 0000000000000000"):
            dist.run_task(spec, "gbuffer_task", (0, 0))
        assert not any(tmp_path.glob("*.npz"))
        monkeypatch.setattr(dist, "_own_code", lambda: "f" * 16)  # this client differs from its workers
        with pytest.raises(RuntimeError, match="worker tcp://.* runs renderer code .* this client ffff"):
            run_experiment(ExperimentConfig(out=str(tmp_path / "o"), scheduler="local:1", **SMALL))
        assert not (tmp_path / "o").exists()  # the workers are checked before anything is created

    def test_no_scheduler_there(self, tmp_path, monkeypatch, capsys):
        """An unreachable scheduler: one line, exit 2, and no folder created (--out and --out/cache were left
        behind, empty)."""
        from stereorepro.cli import main

        monkeypatch.setattr(dist, "CONNECT_TIMEOUT", "1s")
        with pytest.raises(dist.ClusterError, match="cannot reach the Dask scheduler") as info:
            run_experiment(
                ExperimentConfig(out=str(tmp_path / "o"), scheduler=f"tcp://127.0.0.1:{_free_port()}", **SMALL)
            )
        assert isinstance(info.value, StereoreproError) and list(tmp_path.iterdir()) == []
        addr = f"tcp://127.0.0.1:{_free_port()}"
        rc = main(
            [
                "experiment",
                "--scene",
                "living_room",
                "--out",
                str(tmp_path / "cli"),
                "--scheduler",
                addr,
                "--frames",
                "1",
                "--resolution",
                "32x18",
                "--reference-spp",
                "4",
                "--ladder-spp",
                "2",
            ]
        )
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and "cannot reach the Dask scheduler" in err[0]
        assert list(tmp_path.iterdir()) == []
