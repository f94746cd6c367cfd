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
ends the worker), writes no file (its answers come back on a pipe of their own: nothing it or a
library prints can be taken for one), and ends with the process that started it
(:func:`mi_bivariate.process.die_with_parent`). It runs with the command's interpreter flags (``-B``,
``-O``, ``-W``, ``-X``) and imports from the command's own ``sys.path`` (not the current folder, which
``python -c`` would put first): the same copy of the toolkit and of matplotlib as the command, where that
path alone finds them (an import hook a ``.pth`` file installs is the worker's own ``site``'s). What the drawing warns about is said again by the
command, as the nearest built-in category (a ``MatplotlibDeprecationWarning`` as a
``DeprecationWarning``), through the command's own warning filters. Only the command line's process
starts it: this module loads the toolkit's :mod:`~mi_bivariate.atomic` and
:mod:`~mi_bivariate.process` (and numpy, through them) and the standard library, so the command line can
start the worker before it loads the pipeline; the worker loads the report's module.
"""

from __future__ import annotations

import os
import pickle
import selectors
import signal
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any, List, Optional, Union

from mi_bivariate.atomic import atomic_path
from mi_bivariate.process import die_with_parent

#: What the worker runs, ``python [the command's flags] -c BOOT PARENT_PID REPLY_FD``: the current folder that
#: ``-c`` puts first on the path is dropped before anything is imported, and its first message is the
#: command's ``sys.path``, so that it imports what the command imports (not the current folder's modules).
BOOT = ("import sys\nif sys.path and sys.path[0] == '':\n    del sys.path[0]\nimport pickle\n"
        "sys.path[:] = pickle.load(sys.stdin.buffer)\nfrom mi_bivariate.report_worker import serve\n"
        "sys.exit(serve(int(sys.argv[1]), int(sys.argv[2])))")
#: Seconds the command waits for the worker to be ready (matplotlib loaded: seconds, or longer where
#: matplotlib builds its font cache), and then again for each report; past either it draws the report itself.
REPLY_TIMEOUT_S = 120.0
#: Seconds a worker asked to end (SIGTERM: it unwinds, so that matplotlib's font-cache lock is not left
#: behind) is given before it is killed.
END_TIMEOUT_S = 10.0
#: The worker's first answer: it has loaded matplotlib and is waiting for panels.
READY = "ready"
#: Panels above this many bytes of arrays (a photo of ~5 megapixels and more) are drawn in the command's
#: own process: the worker would hold a copy of them (and pickling another) for nothing but speed.
MAX_PANEL_BYTES = 64 * 2**20


class ReportWorker:
    """A process that draws recovery reports (see the module's notes).

    Methods: :meth:`write` (one report; blocks until it is written), :meth:`close` (ends the
    process; also on leaving a ``with`` block). A closed or failed worker draws in this process.
    """

    def __init__(self) -> None:
        self._process: Optional[subprocess.Popen] = None
        self._replies: Optional[Any] = None
        self._ready = False
        read_fd, write_fd = os.pipe()
        try:
            self._process = subprocess.Popen(
                [sys.executable, *_interpreter_flags(), "-c", BOOT, str(os.getpid()), str(write_fd)],
                stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                pass_fds=(write_fd,), start_new_session=True)
            self._replies, read_fd = os.fdopen(read_fd, "rb"), -1
            path = [os.fspath(p) if isinstance(p, os.PathLike) else p for p in sys.path]
            pickle.dump([p for p in path if isinstance(p, str)], self._process.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._process.stdin.flush()
        except Exception:  # noqa: BLE001 (no process to be had, it ended at once, or no pipes to pass on this
            self.close()   # platform: the report is drawn here)
        finally:
            os.close(write_fd)
            if read_fd >= 0:
                os.close(read_fd)

    def write(self, panels: Any, path: Union[str, os.PathLike]) -> Path:
        """Write the report of :func:`~mi_bivariate.report.recovery_report_panels`' ``panels`` to ``path`` (a
        ``.png``, atomically), drawn in the worker, or here where it cannot be (another format, panels over
        :data:`MAX_PANEL_BYTES`, a worker that failed or gave no answer in :data:`REPLY_TIMEOUT_S`).
        Returns the path.

        The worker hands back the file's bytes and what it warned about (said again here, as a
        report drawn here would say it); it writes no file, so ending it at any moment leaves none.
        """
        reply = None
        if self._process is not None and Path(path).suffix.lower() == ".png" and _array_bytes(panels) <= MAX_PANEL_BYTES:
            try:
                if not self._ready:  # its start, bounded too: the panels would wait in a full pipe meanwhile
                    self._ready = self._answer() == READY
                if self._ready:
                    pickle.dump(panels, self._process.stdin, protocol=pickle.HIGHEST_PROTOCOL)
                    self._process.stdin.flush()
                    reply = self._answer()
            except Exception:  # noqa: BLE001 (it died, could not take the panels, or answered nonsense)
                reply = None
            except BaseException:  # Ctrl-C, SIGTERM: the worker ends with the command's stop
                self.close()
                raise
            if not (isinstance(reply, tuple) and len(reply) == 2 and isinstance(reply[0], bytes)):
                reply = None
                self.close()  # a worker that failed once is not asked again
        if reply is None:
            from mi_bivariate.report import draw_recovery_report  # loaded by the pipeline by then
            return draw_recovery_report(panels, path)
        png, said = reply
        for message, category in said:
            warnings.warn(message, category, stacklevel=2)
        with atomic_path(path) as tmp:
            tmp.write_bytes(png)
        return Path(path)

    def _answer(self) -> Any:
        """The worker's next answer, or ``None`` where none comes within :data:`REPLY_TIMEOUT_S`."""
        with selectors.DefaultSelector() as selector:
            selector.register(self._replies, selectors.EVENT_READ)
            return pickle.load(self._replies) if selector.select(REPLY_TIMEOUT_S) else None

    def close(self) -> None:
        """End the worker (it holds no work between reports) and wait for it; a second call does nothing."""
        process, self._process = self._process, None
        replies, self._replies = self._replies, None
        if process is not None:
            process.terminate()  # while it waits for panels it ends at once; inside matplotlib, it unwinds first
            try:
                process.wait(END_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        for stream in (process.stdin if process is not None else None, replies):
            try:
                if stream is not None:
                    stream.close()
            except OSError:  # a broken pipe's unsent bytes
                pass

    def __enter__(self) -> "ReportWorker":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _interpreter_flags() -> List[str]:
    """This interpreter's command-line flags (``-B``, ``-O``, ``-W``, ``-X``) for the worker's, as
    :mod:`multiprocessing` passes them to its own workers (the standard library's helper)."""
    flags = getattr(subprocess, "_args_from_interpreter_flags", None)
    return list(flags()) if callable(flags) else []


def _array_bytes(panels: Any) -> int:
    """The bytes of the arrays among ``panels``' attributes."""
    return sum(int(getattr(value, "nbytes", 0)) for value in vars(panels).values())


def _builtin_category(category: type) -> type:
    """``category``, or its nearest built-in base class (a library's category would load that library to be
    read back, and the command's filters know the built-in ones)."""
    return next((c for c in category.__mro__ if c.__module__ == "builtins" and issubclass(c, Warning)), UserWarning)


def serve(parent: int, reply_fd: int) -> int:
    """The worker's loop: load the report's module and warm matplotlib up, answer :data:`READY` on
    ``reply_fd``, then, for each panels object read from stdin, answer ``(PNG bytes, [(warning text,
    category), ...])``, or ``None`` where the drawing failed (the command then draws it itself, and says what
    went wrong); until stdin ends."""
    busy = [True]

    def stop(signum: int, frame: Any) -> None:
        """SIGTERM (the command's :meth:`ReportWorker.close`, or the end of the command): inside matplotlib,
        unwind (its font-cache lock file is removed on the way out); waiting for panels, end at once."""
        if busy[0]:
            raise SystemExit(1)
        os._exit(0)

    signal.signal(signal.SIGTERM, stop)
    die_with_parent(parent)
    replies = os.fdopen(reply_fd, "wb")
    requests = sys.stdin.buffer
    from mi_bivariate import report  # the point of this process: loaded while the command runs

    report.warm_up()
    answer: Any = READY
    while True:
        pickle.dump(answer, replies, protocol=pickle.HIGHEST_PROTOCOL)
        replies.flush()
        busy[0] = False
        try:
            panels = pickle.load(requests)
        except EOFError:
            return 0
        busy[0] = True
        try:
            with warnings.catch_warnings(record=True) as said:
                warnings.simplefilter("always")  # each one; the command's filters decide
                png = report.recovery_report_png(panels)
            answer = png, [(str(w.message), _builtin_category(w.category)) for w in said]
        except Exception:  # noqa: BLE001 (the command draws it again, and says what went wrong)
            answer = None
