"""The recovery report drawn in a process of its own, started when the command starts.

A fresh ``mi-bivariate recover`` spends its first ~0.9 s on one core of two (its imports, the Mitsuba
variant, the probe, the sphere fit), and with its report it then loads matplotlib (~0.4 s) once the
table is solved. :class:`ReportWorker` starts a process at once that loads matplotlib and draws a small
figure (its fonts, Agg's first draw) on the idle core; the report's panels
(:func:`mi_bivariate.report.recovery_report_panels`, ~2-3 MB of arrays and text) are then drawn there
and the PNG file's bytes (the same, byte for byte) come back to be written by the command. Where the
worker cannot start, dies, or fails to draw, the report is drawn in the command's own process as before
(and a real problem is then raised there).

The command line uses it for ``recover`` and ``recover-batch`` with their report, in a process of its
own, where a second core is free and ``--threads`` is not 1 (:func:`mi_bivariate.cli.main`). A program
draws in its own process (:func:`mi_bivariate.report.write_recovery_report`), or, the same way::

    worker = ReportWorker()          # before the recovery: matplotlib loads meanwhile
    result = recover(...)
    worker.write(recovery_report_panels(result), "report.png")
    worker.close()

The worker is in a session of its own (a Ctrl-C at the terminal is the command's to handle, which
ends the worker), writes no file, and ends with the process that started it
(:func:`mi_bivariate.process.die_with_parent`). This module loads only the standard library and the
toolkit's :mod:`~mi_bivariate.atomic` and :mod:`~mi_bivariate.process`, so the command line can start
the worker before it loads the pipeline; the worker loads the report's module.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any, Optional, Union

from mi_bivariate.atomic import atomic_path
from mi_bivariate.process import die_with_parent


class ReportWorker:
    """A process that draws recovery reports (see the module's notes).

    Methods: :meth:`write` (one report; blocks until it is written), :meth:`close` (ends the
    process; also on leaving a ``with`` block). A closed or failed worker draws in this process.
    """

    def __init__(self) -> None:
        self._process: Optional[subprocess.Popen] = None
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-m", "mi_bivariate.report_worker", str(os.getpid())],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                start_new_session=True)
        except OSError:  # no process to be had (limits, memory): the report is drawn here
            self._process = None

    def write(self, panels: Any, path: Union[str, os.PathLike]) -> Path:
        """Write the report of :func:`~mi_bivariate.report.recovery_report_panels`' ``panels`` to ``path`` (a
        PNG, atomically), drawn in the worker, or here where it cannot be. Returns the path.

        The worker hands back the file's bytes and what it warned about (said again here, as a
        report drawn here would say it); it writes no file, so ending it at any moment leaves none.
        """
        process = self._process
        reply = None
        if process is not None:
            try:
                pickle.dump(panels, process.stdin, protocol=pickle.HIGHEST_PROTOCOL)
                process.stdin.flush()
                reply = pickle.load(process.stdout)
            except Exception:  # noqa: BLE001 (it died, could not take the panels, or answered nonsense)
                reply = None
            except BaseException:  # Ctrl-C, SIGTERM: the worker ends with the command's stop
                self.close()
                raise
        if not (isinstance(reply, tuple) and len(reply) == 2 and isinstance(reply[0], bytes)):
            self.close()  # a worker that failed once is not asked again
            from mi_bivariate.report import draw_recovery_report  # loaded by the pipeline by then
            return draw_recovery_report(panels, path)
        png, said = reply
        for message, category in said:
            warnings.warn(message, category, stacklevel=2)
        with atomic_path(path) as tmp:
            tmp.write_bytes(png)
        return Path(path)

    def close(self) -> None:
        """End the worker (it holds no work between reports) and wait for it; a second call does nothing."""
        process, self._process = self._process, None
        if process is None:
            return
        process.kill()
        process.wait()
        for stream in (process.stdin, process.stdout):
            try:
                stream.close()
            except OSError:  # a broken pipe's unsent bytes
                pass

    def __enter__(self) -> "ReportWorker":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def serve(parent: int) -> int:
    """The worker's loop: load the report's module and warm matplotlib up, then, for each panels object read
    from stdin, answer on stdout with ``(PNG bytes, [(warning text, category), ...])``, or ``None`` where
    the drawing failed (the command then draws it itself, and says what went wrong); until stdin ends."""
    die_with_parent(parent)
    replies = os.fdopen(os.dup(1), "wb")
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)  # what matplotlib or a library prints goes nowhere
    requests = sys.stdin.buffer
    from mi_bivariate import report  # the point of this process: loaded while the command runs

    report.warm_up()
    while True:
        try:
            panels = pickle.load(requests)
        except EOFError:
            return 0
        try:
            with warnings.catch_warnings(record=True) as said:
                warnings.simplefilter("always")
                png = report.recovery_report_png(panels)
            # A library's own category (matplotlib's) would load that library to be read back: its base instead.
            answer = (png, [(str(w.message), w.category if w.category.__module__ == "builtins" else UserWarning)
                            for w in said])
        except Exception:  # noqa: BLE001 (the command draws it again, and says what went wrong)
            answer = None
        pickle.dump(answer, replies, protocol=pickle.HIGHEST_PROTOCOL)
        replies.flush()


if __name__ == "__main__":
    sys.exit(serve(int(sys.argv[1])))
