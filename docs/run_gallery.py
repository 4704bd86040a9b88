"""Run every shipped workflow for the documentation site's gallery (``.ci/docs`` does; ``SELPATH_DOCS_RUNS`` then
names the folder): the workflows are copied into FOLDER with ``selpath workflows --copy``, each is run there with
``selpath run`` as a user runs it, and ``<name>.run.json`` records its wall time and the machine. A workflow that
another reads (``selpath.workflows.AFTER``) runs first. ``--skip NAME`` leaves one out (its page then shows no run).

    python docs/run_gallery.py FOLDER [--skip tomography-scattering]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

from selpath import workflows


def order(names: list[str]) -> list[str]:
    """``names`` with every workflow that reads another's stores after that one."""
    return sorted(names, key=lambda name: name in workflows.AFTER)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--skip", action="append", default=[], metavar="NAME")
    args = parser.parse_args()
    selpath = [sys.executable, "-m", "selpath"]
    subprocess.run([*selpath, "workflows", "--copy", str(args.folder)], check=True, stdout=subprocess.DEVNULL)
    machine = f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
    failed = []
    for name in order([n for n in workflows.names() if n not in args.skip]):
        start = time.perf_counter()
        with open(args.folder / f"{name}.log", "w") as log:
            done = subprocess.run([*selpath, "run", f"{name}.yaml", "--report", "--no-progress"], cwd=args.folder,
                                  stdout=log, stderr=subprocess.STDOUT)
        seconds = time.perf_counter() - start
        print(f"{name}: {'ok' if done.returncode == 0 else 'FAILED'} in {seconds:.1f} s", flush=True)
        if done.returncode:
            failed.append(name)
            continue
        (args.folder / f"{name}.run.json").write_text(json.dumps({"seconds": seconds, "machine": machine}))
    if failed:
        print(f"failed: {', '.join(failed)} (their logs: {args.folder}/<name>.log)", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
