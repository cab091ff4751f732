"""Preprocessing and pairwise alignment as Dask tasks, against a real LocalCluster of two
worker processes: the same poses bit for bit as in-process, small tasks, errors that name
the pair or scan, an interrupt that cancels the tasks, a lost worker's task retried."""

from __future__ import annotations

import json
import operator
import os
import pickle
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cloudpickle
import dask
import numpy as np
import pytest
from typer.testing import CliRunner

from data_synth import synthesize_scans
from mvreg.cli import app
from mvreg.config import AlignConfig, load_config
from mvreg.distributed import DaskExecutor
from mvreg.distributed.executor import KEEP_REPLICAS
from mvreg.errors import ConfigError, TaskError
from mvreg.executor import map_shared
from mvreg.pairwise import align_pairs, derive_scales, preprocess_all, with_noise
from mvreg.pipeline import register
from mvreg.pipeline.load import load_source
from mvreg.pipeline.run import NoProgress

distributed = pytest.importorskip("distributed")

# The helper tasks below travel to the worker processes by value.
cloudpickle.register_pickle_by_value(sys.modules[__name__])


@pytest.fixture(scope="module")
def cluster():
    # Configured as DaskExecutor.local configures its clusters (no Active Memory Manager,
    # which would drop the broadcast copies of the scans while the tests look at them).
    with dask.config.set(KEEP_REPLICAS):
        c = distributed.LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"},
        )
    yield c
    c.close()


@pytest.fixture(scope="module")
def ex(cluster):
    with DaskExecutor(distributed.Client(cluster)) as e:
        yield e


@pytest.fixture(scope="module")
def scans_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("dist") / "scans"
    synthesize_scans("builtin", folder, views=7, points_per_scan=2500, seed=0, random_frames=True)
    return folder


@pytest.fixture(scope="module")
def in_process(scans_dir):
    return register(scans_dir, load_config(seed=0))


@pytest.fixture(scope="module")
def preprocessed(scans_dir, ex):
    scans = load_source(scans_dir, None, 100, 10**7, None, NoProgress(), "registration").scans
    scales = derive_scales(scans, None, ex)
    pre = preprocess_all(scans, scales.voxel, None, ex)
    return pre, with_noise(scales, pre)


def test_poses_bit_identical_in_process_and_on_a_scheduler_address(in_process, scans_dir, cluster):
    on_cluster = register(scans_dir, load_config(seed=0, scheduler=cluster.scheduler_address))
    assert sorted(on_cluster.T_world_scan) == sorted(in_process.T_world_scan)
    assert len(in_process.T_world_scan) == 7
    for name, T in in_process.T_world_scan.items():
        assert np.array_equal(on_cluster.T_world_scan[name], T), name
    a = [(p["scans"], p["accepted"], p["overlap_ratio"]) for p in in_process.pairs]
    b = [(p["scans"], p["accepted"], p["overlap_ratio"]) for p in on_cluster.pairs]
    assert a == b
    assert on_cluster.config.scheduler == cluster.scheduler_address
    assert in_process.truth_errors["rotation_deg_max"] < 1.0


def test_cli_workers_2_exit_0_same_poses(in_process, scans_dir, tmp_path):
    out = tmp_path / "out"
    r = CliRunner().invoke(
        app, ["register", str(scans_dir), "--out", str(out), "--workers", "2", "--no-rrd"]
    )
    assert r.exit_code == 0, r.output
    poses = json.loads((out / "poses.json").read_text())["poses"]
    assert sorted(poses) == sorted(in_process.T_world_scan)
    for name, T in in_process.T_world_scan.items():
        assert np.array_equal(np.array(poses[name]), T), name
    report = json.loads((out / "report.json").read_text())
    assert report["config"]["workers"] == 2 and report["config"]["threads"] == 2
    assert report["timings_s"]["start_cluster"] > 0


def test_pair_tasks_are_small_and_the_scans_are_on_every_worker(preprocessed, ex):
    pre, scales = preprocessed
    pairs = [(0, 1), (0, 2), (1, 2), (2, 3)]
    results = align_pairs(pre, pairs, AlignConfig(), 0, executor=ex, scales=scales)
    assert [(r.i, r.j) for r in results] == pairs
    scan_bytes = min(len(pickle.dumps(p)) for p in pre)
    assert scan_bytes > 100_000
    assert 0 < ex.task_bytes < 1_000  # fn by reference, a label, the data's key, (i, j)
    assert ex.task_bytes * 100 < scan_bytes
    assert ex.shared_bytes > sum(len(pickle.dumps(p)) for p in pre)  # all scans, once
    holders = ex.client.who_has()
    shared = [k for k in holders if str(k).startswith("mvreg-data")]
    assert shared and max(len(holders[k]) for k in shared) == 2  # broadcast to both workers


def test_a_started_cluster_keeps_the_broadcast_copies(preprocessed):
    # The Active Memory Manager would drop one of the two copies within seconds (every 2 s
    # by default): the copies must still be on both workers well after the call.
    pre, scales = preprocessed
    with DaskExecutor.local(2) as own:
        assert not own.client.run_on_scheduler(_amm_running)
        align_pairs(pre, [(0, 1), (1, 2)], AlignConfig(), 0, executor=own, scales=scales)
        time.sleep(5.0)
        holders = own.client.who_has()
        shared = [k for k in holders if str(k).startswith("mvreg-data")]
        assert shared and min(len(holders[k]) for k in shared) == 2


def _amm_running(dask_scheduler=None):
    amm = dask_scheduler.extensions.get("amm")
    return bool(amm is not None and amm.running)


def test_a_pair_task_error_names_the_pair(preprocessed, ex):
    pre, scales = preprocessed
    broken = AlignConfig().model_copy(update={"ransac_backend": "no-such-backend"})
    with pytest.raises(TaskError) as info:
        align_pairs(pre, [(0, 1), (1, 2)], broken, 0, executor=ex, scales=scales)
    assert info.value.task == f"pair {pre[0].name}, {pre[1].name}"
    assert "KeyError" in str(info.value) and info.value.exit_code == 4


def test_a_scan_task_error_names_the_scan(scans_dir, ex):
    scans = load_source(scans_dir, None, 100, 10**7, None, NoProgress(), "registration").scans
    scans[3].points = scans[3].points[:, :2]  # not 3-D: fails inside preprocessing
    with pytest.raises(TaskError) as info:
        preprocess_all(scans, 0.05, None, ex)
    assert info.value.task == f"preprocessing scan {scans[3].name}"


def test_workers_and_scheduler_are_exclusive():
    with pytest.raises(ConfigError, match="workers"):
        load_config(workers=2, scheduler="tcp://127.0.0.1:8786")


def test_ctrl_c_exits_130_with_no_output_and_no_process_left(scans_dir, tmp_path):
    import psutil

    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "mvreg.cli", "register", str(scans_dir), "--out", str(out)]
    root = str(Path(__file__).resolve().parents[1])
    proc = subprocess.Popen(
        [*cmd, "--workers", "2", "--no-rrd"],
        env=dict(os.environ, PYTHONPATH=root, OPENBLAS_NUM_THREADS="1"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a terminal's foreground job
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(_ignoring_sigint(proc.pid)) < 2:
        time.sleep(0.2)  # until the cluster's two worker processes have started
    time.sleep(0.5)
    os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C reaches the whole group
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "mvreg: interrupted" in err and "Traceback" not in err
    assert not out.exists() and list(tmp_path.iterdir()) == []
    time.sleep(0.5)
    group = [p for p in psutil.process_iter(["status"]) if _pgid(p.pid) == proc.pid]
    assert [p for p in group if p.info["status"] != psutil.STATUS_ZOMBIE] == []  # all exited


def _ignoring_sigint(pid):
    """The worker processes of ``pid`` that ignore SIGINT (its plugin has run)."""
    import psutil

    out = []
    for child in psutil.Process(pid).children():
        try:
            status = open(f"/proc/{child.pid}/status").read()
            ignored = int(status.split("SigIgn:")[1].split()[0], 16)
            if "spawn_main" in " ".join(child.cmdline()) and ignored & (1 << (signal.SIGINT - 1)):
                out.append(child)
        except (psutil.Error, OSError, IndexError):
            pass
    return out


def _pgid(pid):
    try:
        return os.getpgid(pid)
    except OSError:
        return None


def _sleep(seconds, item):
    time.sleep(seconds)
    return item


def test_an_interrupt_cancels_the_tasks(ex):
    def interrupt(_result):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        map_shared(ex, _sleep, 0.5, list(range(12)), progress=interrupt)
    deadline = time.monotonic() + 10
    while any(ex.client.processing().values()) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(ex.client.processing().values())
    assert map_shared(ex, operator.add, 1, [1, 2]) == [2, 3]  # the cluster still works


def test_lost_shared_data_is_named_and_sent_again(ex):
    # Scattered data has no lineage: when it is lost (here: released while tasks read it),
    # its tasks are cancelled; the error says why, and the next call sends it again
    # instead of handing out the dead reference.
    shared = 0.25

    def lose_it():
        time.sleep(1.0)
        ex.client.cancel([ex.share(shared)[0]])

    threading.Thread(target=lose_it).start()
    with pytest.raises(TaskError, match="the data it reads was lost"):
        map_shared(ex, _sleep, shared, list(range(12)))
    assert map_shared(ex, _sleep, shared, [1, 2]) == [1, 2]


def _die_once(marker, item):
    # O_EXCL: of two workers running their first tasks at once, exactly one dies (with a
    # test-then-create both could, and the shared data would be lost with them).
    try:
        os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return item * 2
    os._exit(1)  # the worker process dies mid-task


def test_a_lost_workers_task_is_retried(ex, tmp_path):
    # Both workers up first (an earlier test may have left one restarting): the shared
    # data is broadcast to the workers present, and the one that dies must not hold the
    # only copy (fresh-clone runs failed with "cancelled: already forgotten").
    ex.client.wait_for_workers(2, timeout=120)
    marker = str(tmp_path / "died")
    assert map_shared(ex, _die_once, marker, [1, 2, 3, 4]) == [2, 4, 6, 8]
    assert os.path.exists(marker)


def test_every_typed_error_survives_pickling():
    """A worker process sends an error back pickled: each typed error must come back as
    the same class with the same message and attributes (an error whose ``__init__``
    takes more than the message cannot be rebuilt from ``args`` alone)."""
    from mvreg.errors import (
        DisconnectedError,
        IllPosedError,
        OutputExistsError,
        ProblemError,
        ScanFileError,
        SolverError,
    )
    from mvreg.io.atomic import OutputWriteError
    from mvreg.io.loaders.base import TooFewPointsError
    from mvreg.io.merged_formats import MergedFormatError

    errors = [
        ScanFileError("/data/a.ply", "not a PLY file"),
        TooFewPointsError("/data/b.e57", "3 points, fewer than 50", scan="b.e57#2"),
        DisconnectedError([["p0", "p1"], ["p2"]]),
        IllPosedError("rotation of p3 not determined", ["p3"]),
        OutputWriteError("/out/merged.ply", "No space left on device"),
        MergedFormatError("/out/merged.e57", "pye57 missing"),
        TaskError("pair scan_001.ply, scan_004.ply", "ValueError: boom"),
        ConfigError("voxel_size 0 must be positive"),
        ProblemError("bad"),
        OutputExistsError("exists"),
        SolverError("nan"),
    ]
    for e in errors:
        for dumps in (pickle.dumps, cloudpickle.dumps):
            back = pickle.loads(dumps(e))
            assert type(back) is type(e)
            assert str(back) == str(e)
            assert back.__dict__ == e.__dict__
