"""How long the command line takes before it does anything (#57): ``selpath --version``, ``selpath --help``,
``selpath stages`` and ``selpath kinds`` (piped: plain lines), ``selpath validate`` on shipped workflows and
``import selpath``, each in a fresh interpreter (cold: nothing of selpath imported), the median of ``--runs``. Peers
measured in the same run: the bare interpreter, and importing xarray alone (the floor of any command that must read
a workflow's labelled arrays). The stage manifest is built once first (``selpath.pipeline.manifest``), as after the
first command of an installation. Prints one line each, then ``cli_startup: version_s=… help_s=… stages_s=…
kinds_s=… validate_tomography_s=… validate_procam_s=… import_s=…``.

    python -m benchmarks.cli_startup [--runs 5]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from selpath import workflows


def _seconds(command: list[str], runs: int) -> float:
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True, check=False)
        times.append(time.perf_counter() - start)
        if done.returncode != 0:
            raise SystemExit(f"{' '.join(command)} failed ({done.returncode}): {done.stderr[-2000:]}")
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="runs of each command (the median is printed)")
    args = parser.parse_args()
    script = Path(sys.executable).with_name("selpath")  # this environment's, not another on PATH
    cli = [str(script) if script.exists() else shutil.which("selpath") or sys.exit("install selpath first")]
    python = [sys.executable, "-c"]
    subprocess.run([*cli, "validate", str(workflows.path("tomography-sim"))], capture_output=True, check=False)
    commands = {
        "python": [*python, "pass"],
        "xarray": [*python, "import xarray"],
        "version": [*cli, "--version"],
        "help": [*cli, "--help"],
        "stages": [*cli, "stages"],
        "kinds": [*cli, "kinds"],
        "validate_tomography": [*cli, "validate", str(workflows.path("tomography-sim"))],
        "validate_procam": [*cli, "validate", str(workflows.path("procam-sim"))],
        "import": [*python, "import selpath"],
    }
    results = {}
    for name, command in commands.items():
        results[name] = _seconds(command, args.runs)
        ratio = results[name] / results["xarray"] if name != "python" else float("nan")
        print(f"{name:>20}: {results[name]:6.2f} s  ({ratio:4.2f}× importing xarray)")
    print("cli_startup: " + " ".join(f"{name}_s={results[name]:.2f}" for name in commands if name not in
                                     ("python", "xarray")))


if __name__ == "__main__":
    main()
