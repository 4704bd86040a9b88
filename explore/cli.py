"""The ``selpath explore`` command, added to the command line through the ``selpath.commands`` entry points (the
engine's command line never imports this layer)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from selpath.pipeline.cli_common import console, guard


def explore(
    paths: Annotated[list[Path], typer.Argument(help="stores, or folders to look for stores in",
                                                metavar="STORE_OR_FOLDER")],
    host: Annotated[str, typer.Option(help="address to listen on (127.0.0.1: this machine only)",
                                      metavar="ADDRESS")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="port to listen on (0: any free one)", metavar="PORT")] = 5006,
    show: Annotated[bool, typer.Option("--show", help="open the page in a browser", metavar="")] = False,
) -> None:
    """Explore stores in a local web page: click a pixel of a transport for its delay profile (offset and µs) and
    I(t_d), slide delay and exposure for the ideal frame, pick projector rows to relight, a band for the epipolar
    images; a sinogram with its unobserved bins; a reconstruction beside its truth and error.

    Read-only: opens only the stores given (or found under a folder given), never writes them, and listens on
    127.0.0.1 unless `--host` says otherwise. Ctrl-C stops it.
    """
    from selpath.explore.explorer import serve

    with guard():
        try:
            serve(paths, host=host, port=port, show=show, log=lambda line: console.print(line, highlight=False,
                                                                                        soft_wrap=True))
        except FileNotFoundError as exc:
            from selpath.pipeline.errors import SelpathError

            raise SelpathError(f"{exc}: give selpath stores or folders holding them") from None
