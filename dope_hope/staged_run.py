"""A long job as resumable `dope-hope` commands: the runner of the benches (bench/) and of the
tools that make what ships (tools/pretrain_start.py).

Each stage is one `dope-hope` subcommand run as a subprocess (``python -m dope_hope.cli``, so
the checkout's package runs), its output in ``OUT/logs/<stage>.log``. A stage that ends with
status 0 leaves ``OUT/stages/<stage>.json`` (its command line and seconds); a stage whose
marker exists is skipped, so running the same job again continues where it stopped (an
interrupted `synth` resumes frame by frame, an interrupted `train --resume` from its last
checkpoint). A failed stage leaves no marker and ends the job with its log's last lines.
:func:`settings_changed` keeps a job's folder to one set of settings.
"""
from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from dope_hope.config import differing_keys
from dope_hope.io.atomic import atomic_write_text


def settings_changed(path: str | os.PathLike, settings: dict) -> list[str]:
    """A job's settings, kept in ``path`` (JSON): recorded (atomically, folders made) the first
    time; later the sorted dotted keys whose values differ from the recorded ones ([]: the
    same job, which may go on in its folder). ``settings`` must survive a JSON round trip
    unchanged (lists, not tuples)."""
    path = Path(path)
    if path.is_file():
        return differing_keys(json.loads(path.read_text()), settings)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(settings, indent=1) + "\n")
    return []


class CommandStages:
    """Runs `dope-hope` commands as the stages of one job in ``out``, in the order asked.

    timings: {stage: seconds} of the stages run or skipped so far (a skipped stage reports
    the seconds its marker recorded).
    """

    def __init__(self, out: str | os.PathLike, cwd: str | os.PathLike | None = None):
        self.out = Path(out)
        self.cwd = None if cwd is None else Path(cwd)
        (self.out / "stages").mkdir(parents=True, exist_ok=True)
        (self.out / "logs").mkdir(parents=True, exist_ok=True)
        self.timings: dict[str, float] = {}

    def stage(self, name: str, argv: Sequence[object]) -> None:
        """Run ``dope-hope *argv`` unless stage ``name`` is done; SystemExit naming the log on
        failure. The log is appended to: a resumed stage keeps its earlier attempts' lines."""
        marker = self.out / "stages" / f"{name}.json"
        shown = "dope-hope " + " ".join(shlex.quote(str(a)) for a in argv)
        if marker.is_file():
            print(f"[{name}] done earlier, skipped: {shown}", flush=True)
            self.timings[name] = float(json.loads(marker.read_text())["seconds"])
            return
        print(f"[{name}] $ {shown}", flush=True)
        log = self.out / "logs" / f"{name}.log"
        t0 = time.perf_counter()
        with open(log, "a") as f:
            f.write(f"$ {shown}\n")
            f.flush()
            code = subprocess.run([sys.executable, "-m", "dope_hope.cli", *map(str, argv)], stdout=f,
                                  stderr=subprocess.STDOUT, cwd=self.cwd).returncode
        seconds = time.perf_counter() - t0
        if code != 0:
            tail = "\n  ".join(log.read_text(errors="replace").strip().splitlines()[-5:])
            raise SystemExit(f"[{name}] failed with status {code} after {seconds:.0f} s; log {log}:\n  {tail}")
        marker.write_text(json.dumps({"command": shown, "seconds": round(seconds, 1)}) + "\n")
        self.timings[name] = seconds
        print(f"[{name}] {seconds:.0f} s (log {log})", flush=True)
