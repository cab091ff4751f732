"""Hostile-input corpus: the harness (fixtures, file writers, runner, grader).

Every case runs the real ``mvreg`` command line as a subprocess in its own temporary folder
and is graded by code, by the generic rules in :data:`RULES` plus what the case declares
(``expect_exit``, ``culprit``, ``expect_result``, ...). The cases themselves live in
``bench/bad_input_cases*.py``; ``scripts/bad_input_corpus.py`` runs them and writes the
report.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import resource
import shutil
import signal
import stat
import struct
import subprocess
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
MVREG = str(REPO / ".venv" / "bin" / "mvreg")
SHARED = Path("/work/shared/data")
TIMEOUT_S = 240.0
MEM_LIMIT = 6 * 1024**3

RULES = """\
- **BAD**: a traceback on stderr/stdout; an exit code mvreg does not document (not 0/2/3/4/130/143);
  exit 4 where the case is bad *input* (not an environment fault such as a full disk); a
  crash by a signal nobody sent (e.g. the 6 GiB address-space limit, `RLIMIT_AS`, or a
  `MemoryError`); exit 0 (or 3: those poses are claimed verified) with any pose more than
  2 deg (rotation, gauge-free: the best reference scan) off the known truth; an input file
  modified, deleted or a new file appearing in the input folder (every input file hashed
  before and after); previous results lost or changed without `--force` or after a failed /
  interrupted run; an output folder left inconsistent (a file of the previous set surviving
  `--force`, missing or unparsable `poses.json`/`report.json` after exit 0/3, an expected
  recording missing) or a leftover hidden/staging entry (a new name starting with `.` beside
  or inside the output, or containing `mvreg-tmp`/`staging`); a timeout (240 s) or hang.
  After SIGKILL (which no process can handle) a leftover staging entry is BAD only if the
  next ordinary run does not clean it up.
- **POOR**: an exit code other than the case expects, but within the documented family; the
  error message does not name the culprit (file name, option or value), is missing, is more
  than one line (the Typer/Click usage-error panel counts: it is several lines; debatable,
  but it is what a log shows), or comes with noise (any other stderr line: numpy
  RuntimeWarning, Open3D/libE57/rerun native log lines ...; Open3D/rerun lines on stdout);
  something the user gave silently dropped or ignored (the case then expects a warning
  naming it); a result markedly worse than the clean twin (fewer scans registered than the
  same scans in their original units/frames, or exit 3 where the case expects a full
  result).
- **GOOD**: otherwise. N/A cases (e.g. `chmod 000` while running as root) are GOOD with
  the reason stated.
"""

# --------------------------------------------------------------------------------------
# file writers (the hostile inputs are built from these and then mutated)
# --------------------------------------------------------------------------------------


def read_ply_xyz(path: Path) -> np.ndarray:
    """Points of a synth PLY (binary little endian, double x y z)."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    n = int(re.search(rb"element vertex (\d+)", raw[:end]).group(1))
    return np.frombuffer(raw[end : end + n * 24], dtype="<f8").reshape(n, 3).copy()


def ply_header(n: int, fmt: str = "binary_little_endian", props=None, extra: str = "") -> bytes:
    props = props or [("double", "x"), ("double", "y"), ("double", "z")]
    lines = [
        "ply",
        f"format {fmt} 1.0",
        "comment bad_input corpus",
        f"element vertex {n}",
    ]
    lines += [f"property {t} {name}" for t, name in props]
    if extra:
        lines.append(extra.rstrip("\n"))
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode()


def ply_binary(pts: np.ndarray, endian: str = "<", ftype: str = "double") -> bytes:
    fmt = "binary_little_endian" if endian == "<" else "binary_big_endian"
    code = {"double": "f8", "float": "f4"}[ftype]
    props = [(ftype, "x"), (ftype, "y"), (ftype, "z")]
    return ply_header(len(pts), fmt, props) + np.asarray(pts, dtype=endian + code).tobytes()


def fmt_rows(pts: np.ndarray, sep: str = " ", nl: str = "\n") -> str:
    return "".join(sep.join(repr(float(v)) for v in row) + nl for row in pts)


def ply_ascii(pts: np.ndarray, nl: str = "\n") -> bytes:
    head = ply_header(len(pts), "ascii", [("float", "x"), ("float", "y"), ("float", "z")])
    if nl != "\n":
        head = head.replace(b"\n", nl.encode())
    return head + fmt_rows(pts, nl=nl).encode()


def pcd_header(
    n: int,
    data: str,
    fields="x y z",
    size="8 8 8",
    typ="F F F",
    count="1 1 1",
    width=None,
    height=1,
    points=None,
) -> bytes:
    width = n if width is None else width
    points = n if points is None else points
    return (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {fields}\nSIZE {size}\nTYPE {typ}\nCOUNT {count}\n"
        f"WIDTH {width}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {data}\n"
    ).encode()


def lzf_literal(data: bytes) -> bytes:
    """A valid LZF stream made only of literal runs (what PCD binary_compressed uses)."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i : i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def pcd_bytes(pts: np.ndarray, data: str = "ascii") -> bytes:
    pts = np.asarray(pts, dtype="<f8")
    if data == "ascii":
        return pcd_header(len(pts), "ascii") + fmt_rows(pts).encode()
    if data == "binary":
        return pcd_header(len(pts), "binary") + pts.tobytes()
    soa = np.ascontiguousarray(pts.T).tobytes()
    comp = lzf_literal(soa)
    return (
        pcd_header(len(pts), "binary_compressed") + struct.pack("<II", len(comp), len(soa)) + comp
    )


def pts_bytes(pts: np.ndarray, count: int | None = None, extra_cols: int = 0) -> bytes:
    rows = pts
    if extra_cols:
        rows = np.hstack([pts, np.full((len(pts), extra_cols), 7.0)])
    return (f"{len(pts) if count is None else count}\n" + fmt_rows(rows)).encode()


def npy_bytes(arr: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=True)
    return buf.getvalue()


def write_las(path: Path, pts: np.ndarray, scale: float = 1e-5, laz: bool = False) -> None:
    import laspy

    hdr = laspy.LasHeader(point_format=6, version="1.4")
    hdr.scales = np.array([scale] * 3)
    hdr.offsets = np.floor(pts.min(axis=0))
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.write(str(path), do_compress=laz)


def write_e57(path: Path, clouds: list[np.ndarray]) -> None:
    import pye57

    e = pye57.E57(str(path), mode="w")
    try:
        for c in clouds:
            e.write_scan_raw(
                {
                    "cartesianX": c[:, 0].copy(),
                    "cartesianY": c[:, 1].copy(),
                    "cartesianZ": c[:, 2].copy(),
                }
            )
    finally:
        e.close()


# --------------------------------------------------------------------------------------
# fixtures: generated once per corpus run, copied and mutated per case
# --------------------------------------------------------------------------------------


def child_env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (
        os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else ""
    )
    env.pop("COLUMNS", None)
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


def _mvreg(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [MVREG, *args], cwd=cwd, env=child_env(), capture_output=True, text=True, timeout=600
    )


def build_fixtures(root: Path) -> dict:
    """Scans, a clean result, a previous result with an extra file, a sequence and a patch
    problem. Returns a JSON-able dict of paths and the clean twin's numbers."""
    root.mkdir(parents=True, exist_ok=True)
    fx: dict = {"root": str(root)}
    steps = [
        [
            "synth",
            "builtin",
            "--out",
            "scans8",
            "--views",
            "8",
            "--points-per-scan",
            "3000",
            "--random-frames",
            "--seed",
            "1",
        ],
        [
            "synth",
            "builtin",
            "--out",
            "seq30",
            "--sequence",
            "--views",
            "30",
            "--points-per-scan",
            "3000",
            "--seed",
            "1",
        ],
        ["make-problem", "--patches", "30", "--seed", "0", "--out", "problem.npz"],
        ["make-problem", "--patches", "12", "--d", "2", "--seed", "0", "--out", "problem2d.npz"],
        ["register", "scans8", "--out", "clean_result"],
        ["register", "scans8", "--out", "prev_laz", "--set", "output.merged_format=laz"],
    ]
    for a in steps:
        r = _mvreg(a, root)
        if r.returncode not in (0, 3):
            raise RuntimeError(f"fixture step failed: mvreg {' '.join(a)}: {r.stderr[-2000:]}")
        if a[0] == "register" and a[3] == "clean_result":
            fx["clean_exit"] = r.returncode
    poses = json.loads((root / "clean_result" / "poses.json").read_text())
    fx["clean_registered"] = len(poses["poses"])
    fx["clean_files"] = sorted(p.name for p in (root / "clean_result").iterdir())
    fx["prev_files"] = sorted(p.name for p in (root / "prev_laz").iterdir())
    return fx


# --------------------------------------------------------------------------------------
# cases
# --------------------------------------------------------------------------------------


@dataclass
class Case:
    id: str
    family: str
    desc: str
    setup: Callable[[Ctx], None] | None
    argv: list[str] | Callable[[Ctx], list[str]]
    expect_exit: set[int]
    culprit: list[str] = field(default_factory=list)  # any of these, case-insensitive
    expect_result: str = "any"  # full | partial | any (exit 0/3 of register)
    expect_warn: list[str] = field(default_factory=list)  # exit 0/3: each must be named
    note: str = ""  # why the expectation is what it is (debatable cases)
    signal: tuple[int, float] | None = None  # (signal, delay s)
    followup: bool = False  # SIGKILL: run the command again, then check leftovers
    check: Callable[[Ctx, Run], list[tuple[str, str]]] | None = None
    skip: Callable[[Ctx], str | None] | None = None
    timeout: float = TIMEOUT_S


@dataclass
class Run:
    rc: int | None
    stdout: str
    stderr: str
    seconds: float
    timed_out: bool = False


class Ctx:
    """What a case's setup sees: its work folder and the fixtures."""

    def __init__(self, work: Path, fx: dict):
        self.work = work
        self.fx = fx
        self.froot = Path(fx["root"])
        self.inp = work / "in"
        self.out = work / "out"
        self.out_is_dir = True  # register/synth out folders; False for solve/make-problem files
        self.truth: dict[str, np.ndarray] | None = None  # name -> T_world_scan (rotation graded)
        self.inputs: list[Path] = []  # extra input paths to hash (the input folder always is)
        self.prev = False  # a previous result was planted in out
        self.twin = None  # clean twin: number of scans registered
        self.cleanup: list[Callable[[], None]] = []
        self.expected_files: list[str] | None = None
        self.solve_truth: Path | None = None
        self._pts: dict[int, np.ndarray] = {}

    # ---- data
    def pts(self, i: int) -> np.ndarray:
        if i not in self._pts:
            self._pts[i] = read_ply_xyz(self.froot / "scans8" / f"scan_{i:03d}.ply")
        return self._pts[i]

    def gt(self, src: str = "scans8") -> dict[str, np.ndarray]:
        d = json.loads((self.froot / src / "ground_truth.json").read_text())
        return {k: np.array(v, dtype=float) for k, v in d["poses"].items()}

    def scans(
        self,
        n: int = 8,
        fmt: str = "ply",
        skip=(),
        folder: Path | None = None,
        scale: float = 1.0,
        offset=None,
    ) -> Path:
        """Write the base scans (``fmt``) to the input folder, set the truth."""
        folder = folder or self.inp
        folder.mkdir(parents=True, exist_ok=True)
        gt = self.gt()
        truth = {}
        off = np.zeros(3) if offset is None else np.asarray(offset, dtype=float)
        for i in range(n):
            if i in skip:
                continue
            name = self.write_scan(folder, i, fmt, scale=scale, offset=off)
            T = gt[f"scan_{i:03d}.ply"].copy()
            T[:3, 3] = scale * T[:3, 3] - T[:3, :3] @ off
            truth[name] = T
        self.truth = truth
        return folder

    def write_scan(
        self, folder: Path, i: int, fmt: str, scale=1.0, offset=None, stem: str | None = None
    ) -> str:
        p = self.pts(i) * scale + (0 if offset is None else offset)
        stem = stem or f"scan_{i:03d}"
        if fmt == "ply" and scale == 1.0 and (offset is None or not np.any(offset)):
            name = stem + ".ply"
            shutil.copyfile(self.froot / "scans8" / f"scan_{i:03d}.ply", folder / name)
            return name
        writers = {
            "ply": (".ply", lambda: ply_binary(p)),
            "ply_ascii": (".ply", lambda: ply_ascii(p)),
            "ply_be": (".ply", lambda: ply_binary(p, ">")),
            "ply_f32": (".ply", lambda: ply_binary(p, "<", "float")),
            "pcd": (".pcd", lambda: pcd_bytes(p, "ascii")),
            "pcd_bin": (".pcd", lambda: pcd_bytes(p, "binary")),
            "pcd_comp": (".pcd", lambda: pcd_bytes(p, "binary_compressed")),
            "xyz": (".xyz", lambda: fmt_rows(p).encode()),
            "pts": (".pts", lambda: pts_bytes(p)),
            "npy": (".npy", lambda: npy_bytes(p)),
        }
        if fmt in ("las", "laz"):
            name = stem + "." + fmt
            write_las(folder / name, p, laz=fmt == "laz")
            return name
        if fmt == "e57":
            name = stem + ".e57"
            write_e57(folder / name, [p])
            return name
        ext, fn = writers[fmt]
        (folder / (stem + ext)).write_bytes(fn())
        return stem + ext

    def replace(self, i: int, name: str, data: bytes | None, keep_truth: bool = False) -> Path:
        """Replace scan i of the input folder by a file ``name`` holding ``data``."""
        old = f"scan_{i:03d}.ply"
        (self.inp / old).unlink(missing_ok=True)
        if self.truth is not None:
            T = self.truth.pop(old, None)
            if keep_truth and T is not None:
                self.truth[name] = T
        p = self.inp / name
        if data is not None:
            p.write_bytes(data)
        return p

    def plant_prev(self, which: str = "prev_laz") -> None:
        shutil.copytree(self.froot / which, self.out)
        self.prev = True


# --------------------------------------------------------------------------------------
# snapshots
# --------------------------------------------------------------------------------------


def tree_state(path: Path) -> dict[str, str]:
    """relative name -> content hash / link target / 'dir' (no symlink following)."""
    state: dict[str, str] = {}
    if not os.path.lexists(path):
        return state
    if not path.is_dir() or path.is_symlink():
        return {".": _entry_hash(path)}
    for dirpath, dirnames, filenames in os.walk(path):
        for n in dirnames + filenames:
            p = Path(dirpath) / n
            rel = str(p.relative_to(path))
            state[rel] = _entry_hash(p)
    return state


def _entry_hash(p: Path) -> str:
    try:
        st = os.lstat(p)
    except OSError as e:
        return f"error:{e.errno}"
    if stat.S_ISLNK(st.st_mode):
        return "link:" + os.readlink(p)
    if stat.S_ISDIR(st.st_mode):
        return "dir"
    if not stat.S_ISREG(st.st_mode):
        return f"special:{stat.S_IFMT(st.st_mode)}"
    if st.st_size > 2 * 1024**3:  # sparse giants: size and mtime
        return f"big:{st.st_size}:{st.st_mtime_ns}"
    h = hashlib.sha256()
    try:
        with open(p, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
    except OSError as e:
        return f"unreadable:{e.errno}:{st.st_size}:{st.st_mtime_ns}"
    return h.hexdigest()


def _listing(path: Path) -> set[str]:
    try:
        return set(os.listdir(path))
    except OSError:
        return set()


# --------------------------------------------------------------------------------------
# running
# --------------------------------------------------------------------------------------


def _limits() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEM_LIMIT, MEM_LIMIT))
    os.setsid()


def run_cmd(argv: list[str], cwd: Path, timeout: float, sig: tuple[int, float] | None) -> Run:
    t0 = time.monotonic()
    proc = subprocess.Popen(
        argv,
        cwd=cwd,
        env=child_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        preexec_fn=_limits,
    )
    if sig is not None:
        try:
            proc.wait(timeout=sig[1])
        except subprocess.TimeoutExpired:
            if sig[0] == signal.SIGKILL:
                os.killpg(proc.pid, signal.SIGKILL)
            else:
                proc.send_signal(sig[0])  # to mvreg itself, like kill PID
    try:
        out, err = proc.communicate(timeout=timeout)
        timed_out = False
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        timed_out = True
    return Run(
        proc.returncode,
        out.decode("utf-8", "replace"),
        err.decode("utf-8", "replace"),
        time.monotonic() - t0,
        timed_out,
    )


def resolve_argv(case: Case, ctx: Ctx) -> list[str]:
    a = case.argv(ctx) if callable(case.argv) else list(case.argv)
    return [
        str(x).format(inp=ctx.inp, out=ctx.out, work=ctx.work, fx=ctx.froot)
        if isinstance(x, str)
        else x
        for x in a
    ]


def show_cmd(argv: list) -> str:
    import shlex

    parts = []
    for a in argv:
        if isinstance(a, bytes):
            parts.append(shlex.quote(a.decode("utf-8", "backslashreplace")))
        else:
            parts.append(shlex.quote(str(a)))
    return "mvreg " + " ".join(parts)


def run_case(case: Case, fx: dict, tmp_root: Path, keep: bool = False) -> dict:
    work = tmp_root / case.id
    if work.exists():
        _force_rmtree(work)
    work.mkdir(parents=True)
    ctx = Ctx(work, fx)
    rec = {
        "id": case.id,
        "family": case.family,
        "desc": case.desc,
        "note": case.note,
        "command": "",
        "exit": None,
        "stderr_head": [],
        "seconds": 0.0,
        "verdict": "BAD",
        "reasons": [],
    }
    try:
        if case.skip is not None:
            why = case.skip(ctx)
            if why:
                rec.update(verdict="GOOD", reasons=[f"N/A: {why}"], command="(skipped)")
                return rec
        if case.setup is not None:
            case.setup(ctx)
        argv = resolve_argv(case, ctx)
        rec["command"] = show_cmd(argv)
        in_paths = [ctx.inp, *ctx.inputs]
        before_in = {str(p): tree_state(p) for p in in_paths}
        out_parent = ctx.out.parent if ctx.out.name else ctx.work
        before_parent = _listing(out_parent)
        before_out = tree_state(ctx.out)
        run = run_cmd([MVREG, *argv], work, case.timeout, case.signal)
        rec["exit"] = run.rc
        rec["seconds"] = round(run.seconds, 2)
        rec["stderr_head"] = [
            ln[:500] + (f" ... [{len(ln)} chars]" if len(ln) > 500 else "")
            for ln in run.stderr.splitlines()
            if ln.strip()
        ][:6]
        levels = grade(case, ctx, run, before_in, before_parent, before_out, out_parent)
        if case.followup:
            levels += followup_check(case, ctx, argv, out_parent, before_parent)
        verdict = "GOOD"
        for lvl, _ in levels:
            if lvl == "BAD":
                verdict = "BAD"
            elif lvl == "POOR" and verdict == "GOOD":
                verdict = "POOR"
        rec["verdict"] = verdict
        rec["reasons"] = [f"{lvl}: {msg}" for lvl, msg in levels] or ["ok"]
    except Exception:
        rec["verdict"] = "BAD"
        rec["reasons"] = [
            "HARNESS ERROR (not graded against mvreg): "
            + traceback.format_exc(limit=3).splitlines()[-1]
        ]
        rec["harness_error"] = traceback.format_exc()
    finally:
        for fn in ctx.cleanup:
            try:
                fn()
            except Exception:
                pass
        if keep:
            rec["kept"] = str(work)
        else:
            _force_rmtree(work)
    return rec


def _force_rmtree(p: Path) -> None:
    for dirpath, dirnames, _ in os.walk(p):
        for d in dirnames:
            q = Path(dirpath) / d
            if q.is_symlink():
                continue
            try:
                os.chmod(q, 0o755)
            except OSError:
                pass
    try:
        os.chmod(p, 0o755)
    except OSError:
        pass
    shutil.rmtree(p, ignore_errors=True)


# --------------------------------------------------------------------------------------
# grading
# --------------------------------------------------------------------------------------

NOISE_STDOUT = re.compile(r"RuntimeWarning|UserWarning|\[Open3D|libE57|\[rerun|WARNING|Warning:")
BOX = "┌│└├┬┴┼─╭╰╮╯━┃┏┗┓┛┡┠┨╞╪╡═"


def classify_stderr(text: str):
    """(error lines, warning lines, usage panel lines, noise lines)."""
    errors, warns, panel, noise = [], [], [], []
    lines = text.splitlines()
    in_panel = False
    for ln in lines:
        s = ln.strip()
        if not s:
            continue
        if s.startswith("╭─ Error") or (in_panel and s[0] in BOX):
            in_panel = not s.startswith("╰")
            panel.append(s)
            continue
        if s.startswith("Usage: mvreg") or s.startswith("Try 'mvreg"):
            panel.append(s)
            continue
        if s.startswith("mvreg: error:") or s.startswith("Error:"):
            errors.append(s)
        elif s.startswith(("mvreg: warning:", "warning:", "mvreg: ")):
            warns.append(s)  # mvreg's own one-line messages (warnings, "mvreg: interrupted")
        elif s[0] in BOX or re.fullmatch(r"mvreg \w[\w -]*", s):
            continue  # the summary table
        elif s.startswith("wrote ") or re.match(r"^\S.*━", s):
            continue
        else:
            noise.append(s)
    return errors, warns, panel, noise


def _rot_err_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def pose_errors(est: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> tuple[float, str]:
    """Largest gauge-free rotation error (deg), minimised over the reference scan."""
    names = [n for n in est if n in truth]
    if len(names) < 2:
        return 0.0, ""
    best = (np.inf, "")
    for ref in names:
        G = truth[ref][:3, :3] @ est[ref][:3, :3].T
        errs = {n: _rot_err_deg(truth[n][:3, :3], G @ est[n][:3, :3]) for n in names}
        worst = max(errs, key=errs.get)
        if errs[worst] < best[0]:
            best = (errs[worst], worst)
    return best


def load_poses(p: Path) -> dict[str, np.ndarray]:
    d = json.loads(p.read_text())
    return {k: np.array(v, dtype=float) for k, v in d["poses"].items()}


def grade(case: Case, ctx: Ctx, run: Run, before_in, before_parent, before_out, out_parent):
    L: list[tuple[str, str]] = []
    rc = run.rc
    both = run.stderr + "\n" + run.stdout
    expected_sig = case.signal[0] if case.signal else None
    if run.timed_out:
        L.append(("BAD", f"timeout after {case.timeout:.0f} s (hang)"))
    if "Traceback (most recent call last)" in both:
        L.append(("BAD", "traceback printed"))
    if "MemoryError" in both or "std::bad_alloc" in both:
        L.append(("BAD", "memory blowup (MemoryError/bad_alloc under the 6 GiB limit)"))
    if rc is not None and rc < 0 and not run.timed_out:
        if expected_sig == signal.SIGKILL and -rc == signal.SIGKILL:
            pass
        else:
            L.append(("BAD", f"killed by signal {-rc} nobody sent (crash or memory limit)"))
    documented = {0, 2, 3, 4, 130, 143}
    if rc is not None and rc >= 0 and rc not in documented:
        L.append(("BAD", f"undocumented exit code {rc}"))
    if rc == 4 and 4 not in case.expect_exit:
        L.append(
            (
                "BAD",
                "exit 4 (internal failure) on bad input, expected "
                + "/".join(map(str, sorted(case.expect_exit))),
            )
        )
    elif (
        rc is not None
        and rc in documented
        and rc not in case.expect_exit
        and not (expected_sig == signal.SIGKILL)
    ):
        L.append(("POOR", f"exit {rc}, expected " + "/".join(map(str, sorted(case.expect_exit)))))

    errors, warns, panel, noise = classify_stderr(run.stderr)
    msg_text = " ".join(errors + panel)
    if rc in (2, 4):
        if panel:
            inner = [p for p in panel if p[0] in BOX and not p.startswith(("╭", "╰"))]
            L.append(
                (
                    "POOR",
                    f"usage error as a {len(panel)}-line panel ("
                    + " ".join(p.strip("│ ") for p in inner)[:160]
                    + ")",
                )
            )
        elif not errors:
            L.append(("POOR", "no 'mvreg: error:' line"))
        elif len(errors) > 1:
            L.append(("POOR", f"{len(errors)} error lines"))
        if case.culprit and rc in case.expect_exit:
            hay = (msg_text or run.stderr).lower()
            if not any(c.lower() in hay for c in case.culprit):
                L.append(
                    (
                        "POOR",
                        "message does not name "
                        + " / ".join(map(repr, case.culprit))
                        + f": {(errors or panel or [''])[0][:200]!r}",
                    )
                )
    if noise:
        L.append(("POOR", f"{len(noise)} noise line(s) on stderr: {noise[0][:160]!r}"))
    m = NOISE_STDOUT.search(run.stdout)
    if m:
        line = next(ln for ln in run.stdout.splitlines() if m.group(0) in ln)
        L.append(("POOR", f"noise on stdout: {line.strip()[:160]!r}"))

    # silently ignored / culprit for partial results
    if rc in (0, 3):
        for w in case.expect_warn:
            if w.lower() not in run.stderr.lower():
                L.append(("POOR", f"silently ignored: nothing on stderr names {w!r}"))
        if rc == 3 and case.culprit and 3 in case.expect_exit:
            if not any(c.lower() in run.stderr.lower() for c in case.culprit):
                L.append(("POOR", "partial result does not name " + " / ".join(case.culprit)))

    # inputs
    for p, st in before_in.items():
        after = tree_state(Path(p))
        if after != st:
            changed = sorted(k for k in set(st) | set(after) if st.get(k) != after.get(k))
            L.append(("BAD", f"input {Path(p).name}/ modified: {changed[:4]}"))

    # outputs
    after_parent = _listing(out_parent)
    new_hidden = sorted(
        n
        for n in after_parent - before_parent
        if n.startswith(".") or "mvreg-tmp" in n or "staging" in n
    )
    inner_hidden = []
    if ctx.out.is_dir() and not ctx.out.is_symlink():
        inner_hidden = sorted(
            n
            for n in _listing(ctx.out) - set(before_out)
            if n.startswith(".") or "mvreg-tmp" in n or "staging" in n
        )
    leftovers = new_hidden + inner_hidden
    if leftovers and not case.followup:
        L.append(("BAD", f"leftover temp entries: {leftovers[:3]}"))
    after_out = tree_state(ctx.out)
    forced = "--force" in resolve_argv(case, ctx)
    ok_run = rc in (0, 3) and not run.timed_out
    if not ok_run:
        if after_out != before_out and not (
            expected_sig == signal.SIGKILL and _complete_new_set(ctx, after_out)
        ):
            what = "previous results changed/lost" if ctx.prev else "output changed"
            L.append(
                (
                    "BAD",
                    f"{what} after exit {rc}: "
                    f"{sorted(k for k in set(after_out) ^ set(before_out))[:4] or 'contents differ'}",
                )
            )
    elif ctx.prev and not forced and after_out != before_out:
        L.append(("BAD", "previous results overwritten without --force"))
    if ok_run:
        L += check_outputs(case, ctx, run, before_out, forced)
    if case.check is not None:
        L += case.check(ctx, run)
    return L


def _complete_new_set(ctx: Ctx, after_out: dict) -> bool:
    names = set(after_out)
    return {"poses.json", "report.json"} <= names


def check_outputs(case: Case, ctx: Ctx, run: Run, before_out: dict, forced: bool):
    L: list[tuple[str, str]] = []
    argv = resolve_argv(case, ctx)
    cmd = argv[0] if argv else ""
    if cmd == "register":
        out = ctx.out
        try:
            poses = load_poses(out / "poses.json")
            json.loads((out / "report.json").read_text())
        except Exception as e:
            return [("BAD", f"exit {run.rc} but poses.json/report.json missing or unparsable: {e}")]
        if "--rrd" not in argv and "--no-rrd" not in argv:
            r = out / "recording.rrd"
            if not r.is_file() or r.stat().st_size == 0:
                L.append(("BAD", "recording.rrd missing or empty"))
        if ctx.prev and forced:
            joined = " ".join(argv)
            want = set(ctx.fx["clean_files"])
            if "--no-rrd" in argv or "--rrd" in argv:
                want.discard("recording.rrd")
            if "merged_format=laz" in joined:
                want = (want - {"merged.ply"}) | {"merged.laz"}
            if "merged_format=e57" in joined:
                want = (want - {"merged.ply"}) | {"merged.e57"}
            stale = sorted(
                n for n in before_out if "/" not in n and n not in want and (out / n).exists()
            )
            if stale:
                L.append(("BAD", f"--force kept files of the previous run: {stale}"))
            if before_out.get("report.json") == tree_state(out / "report.json").get("."):
                L.append(("BAD", "--force: report.json is still the previous one"))
        if ctx.truth:
            err, worst = pose_errors(poses, ctx.truth)
            if err > 2.0:
                L.append(("BAD", f"exit {run.rc} with {worst} {err:.1f} deg off the truth"))
        n = len(poses)
        if case.expect_result == "full" and run.rc == 3:
            L.append(("POOR", f"partial result ({n} registered) where the full set is expected"))
        if ctx.twin is not None and n < ctx.twin:
            L.append(("POOR", f"{n} scans registered, the clean twin registers {ctx.twin}"))
        if run.rc == 0 and ctx.truth and n < len(ctx.truth):
            L.append(("BAD", f"exit 0 but only {n} of {len(ctx.truth)} scans have a pose"))
    elif cmd == "solve" and run.rc == 0:
        try:
            est = load_poses(
                Path(argv[argv.index("--out") + 1])
                if "--out" in argv
                else Path(argv[argv.index("-o") + 1])
            )
        except Exception as e:
            return [("BAD", f"exit 0 but result.json missing/unparsable: {e}")]
        if ctx.solve_truth is not None:
            err, worst = pose_errors(est, load_poses(ctx.solve_truth))
            if err > 2.0 and "--allow-reflections" not in argv:
                L.append(("BAD", f"solve exit 0 with patch {worst} {err:.1f} deg off the truth"))
    return L


def followup_check(case: Case, ctx: Ctx, argv: list[str], out_parent: Path, before_parent):
    """After SIGKILL: leftovers are only BAD if the next ordinary run leaves them too."""
    L = []
    left = sorted(
        n
        for n in _listing(out_parent) - before_parent
        if n.startswith(".") or "mvreg-tmp" in n or "staging" in n
    )
    a = list(argv)
    if "--force" not in a:
        a.append("--force")
    r = run_cmd([MVREG, *a], ctx.work, case.timeout, None)
    if r.rc not in (0, 3):
        L.append(
            (
                "BAD",
                f"the run after SIGKILL exited {r.rc}: "
                + (classify_stderr(r.stderr)[0] or [""])[0][:160],
            )
        )
    still = sorted(
        n
        for n in _listing(out_parent) - before_parent
        if n.startswith(".") or "mvreg-tmp" in n or "staging" in n
    )
    if still:
        L.append(
            ("BAD", f"leftover staging entries after SIGKILL survive the next run: {still[:3]}")
        )
    elif left:
        L.append(("GOOD", f"SIGKILL left {left[:2]}; the next run cleaned it"))
    return L
