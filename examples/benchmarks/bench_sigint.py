"""Ctrl-C at random moments of ``certpose`` commands: exit code and seconds to exit.

Each trial starts a command in a new process, sends it SIGINT after a uniformly random delay in
``[0.5, --max-delay]`` seconds and measures the time from the signal to the process's exit
(``wait``: worker processes of a Dask cluster that close their copy of the output a moment later
are not counted, as a shell does not wait for them). A trial passes when the exit code is 130 within
``--limit`` seconds, nothing is printed on standard output after the command's ``-q`` (no library
output: Open3D's memory statistics), and no temporary file is left in the output folder. Commands
that finish before the signal are counted apart. Run it in the foreground: a shell starts
background jobs (``&`` without job control) with SIGINT ignored, and the commands then rightly
ignore it too.

Usage::

    python examples/benchmarks/bench_sigint.py --trials 25 --commands register pose object bench
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data"

COMMANDS = {
    "register": (["register", "--demo", "--demo-n", "150", "--demo-outliers", "0", "--certify",
                  "--json", "{out}/r.json"], 20.0),
    "pose": (["pose", "--demo", "--json", "{out}/p.json"], 4.0),
    "object": (["object", "build", "--ycbv", str(DATA / "ycbv"), "--object", "025_mug",
                "--views", "0000/000001", "-o", "{out}/m.npz"], 2.0),
    "bench": (["bench", "--trials", "30", "--solvers", "gnc", "--out", "{out}/bench"], 8.0),
}


def trial(argv: list[str], delay: float, env: dict[str, str]) -> dict[str, object]:
    """One command, SIGINT after ``delay`` seconds."""
    with tempfile.TemporaryDirectory() as out, tempfile.TemporaryFile("w+") as fo, \
            tempfile.TemporaryFile("w+") as fe:
        args = [a.format(out=out) for a in argv]
        p = subprocess.Popen([sys.executable, "-m", "certpose", *args, "-q"], env=env, cwd=out,
                             stdout=fo, stderr=fe, text=True)
        time.sleep(delay)
        if p.poll() is not None:
            return {"finished": True}
        t0 = time.monotonic()
        p.send_signal(signal.SIGINT)
        try:
            p.wait(timeout=120)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
        seconds = time.monotonic() - t0
        fo.seek(0)
        leftovers = [q.name for q in Path(out).rglob("*") if ".tmp" in q.name]
        return {"finished": False, "code": p.returncode, "seconds": seconds,
                "stdout_lines": len(fo.read().splitlines()), "temporary_files": leftovers}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=25)
    ap.add_argument("--commands", nargs="+", default=list(COMMANDS), choices=list(COMMANDS))
    ap.add_argument("--limit", type=float, default=1.0, help="seconds allowed (default 1)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    rng = random.Random(args.seed)
    print(f"load average {os.getloadavg()[0]:.2f} at the start")
    for name in args.commands:
        argv, max_delay = COMMANDS[name]
        results = [trial(argv, rng.uniform(0.5, max_delay), env) for _ in range(args.trials)]
        sent = [r for r in results if not r["finished"]]
        ok = [r for r in sent if r["code"] == 130 and r["seconds"] <= args.limit
              and r["stdout_lines"] == 0 and not r["temporary_files"]]
        worst = max((r["seconds"] for r in sent), default=float("nan"))
        print(f"{name:9s} {len(ok)}/{len(sent)} exit 130 within {args.limit:g} s, nothing on "
              f"stdout, no temporary file (worst {worst:.2f} s; {len(results) - len(sent)} "
              "finished before the signal)")
        for r in sent:
            if r not in ok:
                print(f"          failed: {r}")
    print(f"load average {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    main()
