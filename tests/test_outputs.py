"""Outputs: written atomically, one writer per bench folder, one overwrite policy (--force),
unwritable paths refused before the work. With real processes and real files."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from certpose.cli import main
from certpose.io.output import (
    FolderBusyError,
    atomic_path,
    check_output_path,
    folder_lock,
    write_json,
)

REPO = Path(__file__).resolve().parents[1]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    return env


def _bench(out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "certpose", "bench", "--trials", "400", "--workers", "0",
         "--solvers", "gnc", "--outlier-ratios", "0.2", "0.5", "--out", str(out), "-q", *extra],
        env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for_lock(out: Path, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    lock, rows = out / ".certpose.lock", out / "trials.csv"
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if (lock.exists() and lock.read_text().strip() == str(proc.pid) and rows.exists()
                and rows.stat().st_size > 0):
            return
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.01)
    raise AssertionError("the first bench never took its folder")


@pytest.mark.slow
def test_two_benches_on_one_folder_the_second_is_refused_and_no_row_is_duplicated(tmp_path):
    out = tmp_path / "D"
    first = _bench(out)
    _wait_for_lock(out, first)
    second = _bench(out, "--resume")  # what once appended 344 duplicate rows
    _, err = second.communicate(timeout=120)
    assert second.returncode == 2, err
    assert "is in use by another certpose run" in err and str(first.pid) in err
    assert "Traceback" not in err
    _, err1 = first.communicate(timeout=300)
    assert first.returncode == 0, err1
    again = _bench(out, "--resume")  # now free: nothing left to run
    _, err2 = again.communicate(timeout=120)
    assert again.returncode == 0, err2
    with (out / "trials.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    keys = [(r["suite"], r["instance"], r["solver"]) for r in rows]
    assert len(rows) == 800 and len(set(keys)) == 800
    with (out / "summary.csv").open(newline="") as fh:
        summary = list(csv.DictReader(fh))
    assert sorted(int(r["trials"]) for r in summary) == [400, 400]


def test_folder_lock_refuses_another_process_and_nests_in_this_one(tmp_path):
    with folder_lock(tmp_path), folder_lock(tmp_path):  # re-entrant in one process
        code = ("import sys; from certpose.io.output import folder_lock\n"
                "try:\n    folder_lock(sys.argv[1]).__enter__()\n"
                "except OSError as e:\n    print(type(e).__name__, e); sys.exit(3)\n")
        res = subprocess.run([sys.executable, "-c", code, str(tmp_path)], env=_env(),
                             capture_output=True, text=True, timeout=60)
        assert res.returncode == 3 and "FolderBusyError" in res.stdout
        assert str(os.getpid()) in res.stdout
    # Released: another process takes it.
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path)], env=_env(),
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
    assert issubclass(FolderBusyError, OSError)


_WRITER = """
import sys
import numpy as np
from certpose.io.output import write_json
from certpose.io.problems import save_problem
path, npz, tag = sys.argv[1], sys.argv[2], int(sys.argv[3])
rng = np.random.default_rng(tag)
for k in range(40):
    write_json(path, {"writer": tag, "k": k, "payload": list(range(20000))})
    src = rng.normal(size=(2000, 3))
    save_problem(npz, source=src, target=src, noise_bound=0.1)
"""


def test_two_processes_writing_one_file_never_leave_it_partial(tmp_path):
    """Two writers of the same JSON and .npz at once, a reader in between: every read is a
    complete file of one writer (once, two `object build -o` left a corrupt archive)."""
    path, npz = tmp_path / "out.json", tmp_path / "p.npz"
    procs = [subprocess.Popen([sys.executable, "-c", _WRITER, str(path), str(npz), str(t)],
                              env=_env()) for t in (1, 2)]
    from certpose.io.problems import load_problem

    reads = 0
    while any(p.poll() is None for p in procs):
        if path.exists():
            doc = json.loads(path.read_text())
            assert doc["writer"] in (1, 2) and len(doc["payload"]) == 20000
            reads += 1
        if npz.exists():
            assert load_problem(npz).n == 2000
    assert all(p.wait(timeout=120) == 0 for p in procs)
    assert reads > 0
    assert sorted(q.name for q in tmp_path.iterdir()) == ["out.json", "p.npz"]  # no temp left


def test_atomic_path_keeps_the_old_file_when_the_writer_fails(tmp_path):
    p = tmp_path / "a.json"
    write_json(p, {"v": 1})
    with pytest.raises(RuntimeError), atomic_path(p) as tmp:
        tmp.write_text("{partial")
        raise RuntimeError("killed mid-write")
    assert json.loads(p.read_text()) == {"v": 1}
    assert [q.name for q in tmp_path.iterdir()] == ["a.json"]
    assert oct(p.stat().st_mode & 0o777) != oct(0o600)  # the umask's mode, not mkstemp's


# --- one overwrite policy -------------------------------------------------------------------

def _points(tmp_path):
    rng = np.random.default_rng(0)
    src = rng.normal(size=(30, 3))
    np.save(tmp_path / "s.npy", src)
    np.save(tmp_path / "d.npy", src + 1.0)
    return [str(tmp_path / "s.npy"), str(tmp_path / "d.npy"), "--noise-bound", "0.01"]


def test_register_json_is_not_overwritten_without_force(tmp_path, capsys):
    out = tmp_path / "r.json"
    out.write_text("keep me")
    argv = ["register", *_points(tmp_path), "--json", str(out)]
    assert main(argv) == 2
    assert "already exists; pass --force to overwrite it" in capsys.readouterr().err
    assert out.read_text() == "keep me"
    assert main([*argv, "--force"]) == 0
    assert json.loads(out.read_text())["result"]["success"]


@pytest.mark.parametrize("argv", [
    ["pose", "--demo", "--json", "{out}"],
    ["pose", "--demo", "--samples", "10", "--particles", "{out}"],
    ["pose", "--demo", "--save-problem", "{out}"],
    ["bench", "--trials", "1", "--workers", "0", "--json", "{out}"],
], ids=["pose_json", "pose_particles", "pose_save_problem", "bench_json"])
def test_every_output_option_refuses_an_existing_file(tmp_path, capsys, argv):
    out = tmp_path / "exists.npz"
    out.write_bytes(b"keep")
    code = main([a.format(out=out) for a in argv])
    err = capsys.readouterr().err
    assert code == 2 and "already exists" in err and "--force" in err
    assert out.read_bytes() == b"keep"


@pytest.mark.skipif(not Path("/work/shared/data/ycbv").is_dir() and not os.environ.get("CI"),
                    reason="YCB-Video data not found")
def test_object_build_output_is_not_overwritten_without_force(tmp_path, capsys):
    data = REPO.parent / "shared" / "data" / "ycbv"
    out = tmp_path / "m.npz"
    out.write_bytes(b"keep")
    code = main(["object", "build", "--ycbv", str(data), "--object", "025_mug", "--views",
                 "0000/000001", "-o", str(out)])
    assert code == 2 and "already exists" in capsys.readouterr().err
    assert out.read_bytes() == b"keep"


# --- unwritable outputs, before the work ----------------------------------------------------

@pytest.mark.parametrize("argv", [
    ["register", "--demo", "--json", "/proc/certpose-r.json"],
    ["pose", "--demo", "--samples", "10", "--particles", "/proc/p.npz"],
    ["pose", "--demo", "--json", "/proc/p.json"],
    ["bench", "--trials", "1", "--workers", "0", "--out", "/proc/certpose-bench"],
], ids=["register_json", "pose_particles", "pose_json", "bench_out"])
def test_unwritable_outputs_are_refused_before_the_work_even_as_root(capsys, argv):
    """os.access says yes to root for /proc: creating a file there is what fails."""
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == 2, err
    assert "/proc/" in err and "Traceback" not in err
    assert out == ""  # refused up front: no result printed (once, after 17.8 s of work)


def test_check_output_path_tries_the_folder(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    check_output_path(ro / "x.json")
    with pytest.raises(FileExistsError, match="--force"):
        (ro / "y.json").write_text("")
        check_output_path(ro / "y.json", force=False)
