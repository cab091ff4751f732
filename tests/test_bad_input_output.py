"""Output folders under faults (issue 16): one consistent set, never a mix, never a user's
files deleted; SIGTERM, SIGKILL and a full disk leave the previous set intact."""

from __future__ import annotations

import errno
import os
import signal
import stat
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from mvreg.cli import app, run_guarded
from mvreg.errors import InputError, OutputExistsError
from mvreg.io.atomic import OutputWriteError, atomic_path, atomic_write_text
from mvreg.io.output_folder import OutputFolder
from tests.conftest import small_tmpfs

runner = CliRunner()
ROOT = Path(__file__).resolve().parents[1]


def old_set(out: Path) -> dict[str, str]:
    out.mkdir(parents=True, exist_ok=True)
    files = {"poses.json": "old poses", "merged.ply": "old cloud", "report.json": "old report"}
    for name, text in files.items():
        (out / name).write_text(text)
    return files


def contents(out: Path) -> dict[str, str]:
    return {p.name: p.read_text() for p in sorted(out.iterdir())}


def leftovers(parent: Path) -> list[str]:
    return [p.name for p in parent.iterdir() if ".mvreg-" in p.name]


def test_new_set_replaces_old_set_exactly(tmp_path):
    out = tmp_path / "out"
    old_set(out)
    with OutputFolder(out, force=True) as staging:
        atomic_write_text(staging / "poses.json", "new poses")
    assert contents(out) == {"poses.json": "new poses"}  # stale merged.ply, report.json gone
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("exchange", [True, False])
def test_swap_with_and_without_renameat2(tmp_path, monkeypatch, exchange):
    if not exchange:
        monkeypatch.setattr("mvreg.io.output_folder.exchange_paths", lambda a, b: False)
    out = tmp_path / "out"
    old_set(out)
    with OutputFolder(out, force=True) as staging:
        (staging / "report.json").write_text("new")
    assert contents(out) == {"report.json": "new"} and leftovers(tmp_path) == []


def test_failure_keeps_the_old_set(tmp_path):
    out = tmp_path / "out"
    before = old_set(out)
    with pytest.raises(RuntimeError), OutputFolder(out, force=True) as staging:
        (staging / "poses.json").write_text("half")
        raise RuntimeError("crash")
    assert contents(out) == before and leftovers(tmp_path) == []


def test_paths_inside_out_are_staged(tmp_path):
    output = OutputFolder(tmp_path / "out")
    with output as staging:
        assert output.staged(tmp_path / "out" / "x.rrd") == staging / "x.rrd"
        assert output.staged(tmp_path / "y.rrd") == tmp_path / "y.rrd"
        assert output.final_path(staging / "x.rrd") == tmp_path / "out" / "x.rrd"


def test_modes_follow_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        with OutputFolder(tmp_path / "out") as staging:
            (staging / "recording.rrd").write_text("rrd")
            os.chmod(staging / "recording.rrd", 0o600)  # as rerun writes it
            atomic_write_text(staging / "poses.json", "{}")
            (staging / ".recording.rrd.tmp.rrd").write_text("temp")
    finally:
        os.umask(old)
    for name in ("recording.rrd", "poses.json"):
        assert stat.S_IMODE((tmp_path / "out" / name).stat().st_mode) == 0o644
    assert sorted(os.listdir(tmp_path / "out")) == ["poses.json", "recording.rrd"]


@pytest.mark.parametrize(
    ("where", "message"),
    [
        ("same", "inside the input folder"),
        ("inside", "inside the input folder"),
        ("holds", "holds the input folder"),
        ("empty", "give a named output folder"),
        ("dot", "give a named output folder"),
        ("cwd", "current folder"),
        ("file", "not a folder"),
        ("foreign", r"did not write \(notes.txt\)"),
        ("foreign-hidden", r"did not write \(.git\)"),
        ("results", "already holds results"),
    ],
)
def test_refused_outputs(tmp_path, monkeypatch, where, message):
    scans = tmp_path / "data" / "scans"
    scans.mkdir(parents=True)
    out = {
        "same": scans,
        "inside": scans / "result",
        "holds": tmp_path / "data",
        "empty": "",
        "dot": ".",
        "cwd": tmp_path,
        "file": tmp_path / "f",
        "foreign": tmp_path / "o",
        "foreign-hidden": tmp_path / "o",
        "results": tmp_path / "o",
    }[where]
    monkeypatch.chdir(tmp_path)
    force = where.startswith("foreign")
    if where == "file":
        (tmp_path / "f").write_text("x")
    if where.startswith("foreign"):
        old_set(tmp_path / "o")
        (tmp_path / "o" / ("notes.txt" if where == "foreign" else ".git")).mkdir()
    if where == "results":
        old_set(tmp_path / "o")
    error = InputError if where in ("same", "inside", "holds", "empty", "dot", "cwd") else None
    with pytest.raises(error or OutputExistsError, match=message):
        with OutputFolder(out, force=force, inputs=[scans]):
            pass
    assert scans.is_dir()
    if where.startswith("foreign"):
        assert len(os.listdir(tmp_path / "o")) == 4  # untouched


def test_disk_full_names_the_file_and_keeps_the_old_set(tmp_path):
    out = tmp_path / "out"
    before = old_set(out)
    with pytest.raises(OutputWriteError) as info, OutputFolder(out, force=True) as staging:
        atomic_write_text(staging / "poses.json", "new")
        with atomic_path(staging / "merged.ply") as tmp:
            tmp.write_text("partial")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert info.value.path == str(out / "merged.ply")
    assert "No space left on device" in str(info.value)
    assert contents(out) == before and leftovers(tmp_path) == []


def test_real_full_disk_on_a_small_tmpfs(tmp_path):
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    with small_tmpfs(mnt, "64k"):
        out = mnt / "out"
        before = old_set(out)
        with pytest.raises(OutputWriteError) as info, OutputFolder(out, force=True) as staging:
            atomic_write_text(staging / "poses.json", "new")
            atomic_write_text(staging / "merged.ply", "x" * 200_000)
        assert info.value.path == str(out / "merged.ply")
        assert contents(out) == before and leftovers(mnt) == []


def test_sigterm_exits_143_and_discards_the_run(tmp_path):
    out = tmp_path / "out"
    before = old_set(out)

    def body():
        with OutputFolder(out, force=True) as staging:
            (staging / "poses.json").write_text("new")
            os.kill(os.getpid(), signal.SIGTERM)
            raise AssertionError("not reached")

    previous = signal.getsignal(signal.SIGTERM)
    with pytest.raises(typer.Exit) as info:
        run_guarded(body)
    assert info.value.exit_code == 143
    assert signal.getsignal(signal.SIGTERM) == previous
    assert contents(out) == before and leftovers(tmp_path) == []


@pytest.mark.parametrize("sig,code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_swallowed_into_another_error_still_exits_as_the_signal(tmp_path, sig, code):
    # A signal landing in an extension's import becomes an ImportError, which a loader
    # then wraps into a file error (CI saw exit 2, "cannot read file", for a SIGTERM).
    from mvreg.errors import MvregError

    out = tmp_path / "out"
    before = old_set(out)

    def body():
        with OutputFolder(out, force=True) as staging:
            (staging / "poses.json").write_text("new")
            try:
                os.kill(os.getpid(), sig)
            except BaseException as e:  # what pybind11's module init does with it
                raise ImportError("initialization failed") from e
            raise AssertionError("not reached")

    def loader():
        try:
            body()
        except ImportError as e:
            raise MvregError(f"scan.ply: cannot read file ({e})") from e

    with pytest.raises(typer.Exit) as info:
        run_guarded(loader)
    assert info.value.exit_code == code
    assert contents(out) == before and leftovers(tmp_path) == []


KILLED = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from mvreg.io.output_folder import OutputFolder
    out = Path(sys.argv[1])
    with OutputFolder(out, force=True) as staging:
        (staging / "poses.json").write_text("new")
        print("ready", flush=True)
        time.sleep(60)
    """
)


def test_sigkill_mid_write_leaves_the_old_set_and_next_run_cleans_up(tmp_path):
    out = tmp_path / "out"
    before = old_set(out)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.Popen([sys.executable, "-c", KILLED, str(out)], stdout=subprocess.PIPE,
                         env=env, text=True)  # fmt: skip
    assert p.stdout.readline().strip() == "ready"
    p.kill()
    p.wait()
    assert contents(out) == before
    assert leftovers(tmp_path) == [f".out.mvreg-tmp-{p.pid}"]
    with OutputFolder(out, force=True) as staging:
        (staging / "report.json").write_text("next")
    assert contents(out) == {"report.json": "next"} and leftovers(tmp_path) == []


def test_a_swap_cut_between_its_renames_is_restored(tmp_path):
    p = subprocess.run([sys.executable, "-c", "pass"], check=True)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    assert p.returncode == 0
    before = old_set(tmp_path / f".out.mvreg-old-{dead.pid}")
    OutputFolder(tmp_path / "out").remove_stale()
    assert contents(tmp_path / "out") == before and leftovers(tmp_path) == []


# ------------------------------------------------------------------ through the CLI
def small_scans(tmp: Path) -> Path:
    from data_synth import synthesize_scans

    folder = tmp / "scans"
    synthesize_scans("builtin", folder, views=4, noise=0.001, seed=0, points_per_scan=3000)
    return folder


def test_cli_refuses_bad_out_before_registering(tmp_path, monkeypatch):
    d = tmp_path / "scans"
    d.mkdir()
    for k in range(2):
        np.save(d / f"s{k}.npy", np.random.default_rng(k).normal(size=(300, 3)))
    monkeypatch.chdir(tmp_path)
    for out, message in ((str(d), "inside the input folder"), (str(d / "r"), "inside"),
                         ("", "named output folder"), (".", "named output folder")):  # fmt: skip
        r = runner.invoke(app, ["register", str(d), "--out", out, "--no-rrd"])
        assert r.exit_code == 2 and message in r.output, r.output
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("precious")
    r = runner.invoke(app, ["register", str(d), "--out", "mine", "--force", "--no-rrd"])
    assert r.exit_code == 2 and "thesis.tex" in r.output
    assert (tmp_path / "mine" / "thesis.tex").read_text() == "precious"


def test_cli_force_replaces_the_whole_set(tmp_path):
    folder = small_scans(tmp_path)
    out = tmp_path / "out"
    old_set(out)
    (out / "poses_kitti.txt").write_text("stale")
    stale = tmp_path / ".out.mvreg-tmp-999999999"
    stale.mkdir()
    old = os.umask(0o022)
    try:
        r = runner.invoke(app, ["register", str(folder), "--out", str(out), "--force"])
    finally:
        os.umask(old)
    assert r.exit_code in (0, 3), r.output  # 3: a scan left unregistered, still a full set
    names = sorted(os.listdir(out))
    # Pose text files and the merged cloud exist when some scan is registered and
    # verified; the rest always. Nothing of the old set survives either way.
    full = ["poses.json", "poses_tum.txt", "poses_kitti.txt", "merged.ply", "report.json",
            "recording.rrd"]  # fmt: skip
    assert set(names) <= set(full) and {"poses.json", "report.json", "recording.rrd"} <= set(names)
    if "poses_kitti.txt" in names:
        assert (out / "poses_kitti.txt").read_text() != "stale"
    for name in names:
        assert stat.S_IMODE((out / name).stat().st_mode) == 0o644, name
    assert leftovers(tmp_path) == []
    assert str(out / "recording.rrd") in r.output and ".mvreg-tmp" not in r.output


@pytest.fixture(scope="module")
def synth_scans(tmp_path_factory) -> Path:
    return small_scans(tmp_path_factory.mktemp("synth"))


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGKILL])
def test_signal_during_register_keeps_the_old_set(tmp_path, synth_scans, sig):
    import time

    out = tmp_path / "out"
    before = old_set(out)
    env = dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1")
    args = ["register", str(synth_scans), "--out", str(out), "--force"]
    p = subprocess.Popen([sys.executable, "-m", "mvreg.cli", *args], env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    deadline = time.time() + 120
    while not leftovers(tmp_path) and time.time() < deadline and p.poll() is None:
        time.sleep(0.05)
    time.sleep(0.5)
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    expected = {signal.SIGTERM: 143, signal.SIGINT: 130, signal.SIGKILL: -9}[sig]
    assert p.returncode == expected, err
    if sig != signal.SIGKILL:
        assert ("terminated" if sig == signal.SIGTERM else "interrupted") in err
        assert "Traceback" not in err
        assert leftovers(tmp_path) == []
    assert contents(out) == before
    with OutputFolder(out, force=True) as staging:  # the next run cleans up after a SIGKILL
        (staging / "poses.json").write_text("next")
    assert leftovers(tmp_path) == [] and contents(out) == {"poses.json": "next"}


def test_out_that_is_a_mount_point_is_a_one_line_error(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    with small_tmpfs(out, "64k"):
        with pytest.raises(OutputWriteError, match="cannot replace the folder") as info:
            with OutputFolder(out) as staging:
                (staging / "poses.json").write_text("new")
        assert info.value.path == str(out)
        assert os.listdir(out) == [] and leftovers(tmp_path) == []
