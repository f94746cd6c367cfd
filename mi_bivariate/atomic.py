"""Atomic output files: a failed run never leaves a half-written result, never clobbers an input.

- :func:`atomic_path` writes one file through a temporary next to it.
- :func:`atomic_paths` writes several files together: all to temporaries
  first, then renamed into place only once every one of them is complete.
- :func:`check_outputs` refuses, before any work is done, an output that is
  one of the inputs, a directory, or in a folder that cannot be written.

Operating-system failures while writing (a read-only folder, a full disk)
become one-line :class:`InputError` naming the destination.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Any, Iterable, Iterator, List, Optional, Sequence, Type

from mi_bivariate.common import PathLike
from mi_bivariate.errors import InputError, Terminated


def _write_error(path: Path, exc: OSError) -> InputError:
    return InputError(path, f"cannot be written ({exc.strerror or exc})",
                      "check the folder exists and is writable, and that the disk has space")


#: Open :func:`signals_deferred` blocks, and the stop a signal asked for meanwhile (raised when they end).
_held = 0
_pending: Optional[Type[BaseException]] = None


def stop_on_signal(stop: Type[BaseException] = Terminated):
    """A signal handler (``signal.signal(signal.SIGTERM, stop_on_signal())``) that raises ``stop`` where the
    program is, but not inside the few steps of :func:`atomic_paths` that must not be cut (a temporary
    file between its creation and its being recorded for removal, the renames of a set of files): there
    ``stop`` is raised as soon as they end. Python runs handlers in the main thread whichever thread the
    signal reached, so the hold is kept here rather than by the operating system's signal mask."""
    def handler(signum: int, frame: Any) -> None:
        global _pending
        if _held:
            _pending = stop
            return
        raise stop()

    return handler


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold the stops of :func:`stop_on_signal` handlers until the block ends (also around the start of Dr.Jit
    and Mitsuba, whose C++ aborts or crashes on an exception raised inside it). The count is the process's,
    not a thread's: a stop held while another thread writes would be raised in that thread (no thread
    writes outputs today)."""
    global _held, _pending
    _held += 1
    try:
        yield
    finally:
        _held -= 1
        if not _held and _pending is not None:
            stop, _pending = _pending, None
            raise stop()


def _make_temp(path: Path, suffix: str, temps: List[Path]) -> None:
    """Create a temporary for ``path`` and append it to ``temps`` (with signals held in between)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with signals_deferred():
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix, dir=path.parent)
            temps.append(Path(tmp))
            os.close(fd)
    except OSError as exc:
        raise _write_error(path, exc) from None


def _publish(tmp: Path, path: Path) -> None:
    # mkstemp creates 0600 files; give the result the permissions a plain open() would.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    os.replace(tmp, path)


@contextlib.contextmanager
def atomic_path(path: PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path next to ``path``; move it onto ``path`` on success.

    The temporary file lives in the destination directory so the final
    ``os.replace`` is atomic. On any exception the temporary file is removed
    and an existing ``path`` is left untouched; an ``OSError`` (no space, no
    permission) becomes an :class:`InputError` naming ``path``.

    Args:
        path: final destination.
        suffix: extension for the temporary file (some writers pick the
            format from it); defaults to the destination's own suffix.
    """
    with atomic_paths([path], [suffix]) as (tmp,):
        yield tmp


@contextlib.contextmanager
def atomic_paths(paths: Sequence[PathLike], suffixes: Optional[Sequence[str]] = None) -> Iterator[List[Path]]:
    """Write several files all or none: yield temporaries, rename them all on success.

    Every file is first written completely to its temporary (next to its
    destination); only when the ``with`` block ends without an exception are
    they renamed into place, one ``os.replace`` each. On any exception every
    temporary is removed and no destination is touched.

    Args:
        paths: final destinations (distinct).
        suffixes: per-path temporary suffixes (default: each destination's own).
    """
    paths = [Path(p) for p in paths]
    if len({os.path.abspath(p) for p in paths}) != len(paths):
        raise ValueError(f"atomic_paths: duplicate destinations in {[str(p) for p in paths]}")
    suffixes = list(suffixes) if suffixes is not None else [""] * len(paths)
    temps: List[Path] = []
    try:
        for path, suffix in zip(paths, suffixes):
            _make_temp(path, suffix, temps)
        def destination(name: object) -> Optional[Path]:
            """The destination whose temporary ``name`` is (or was written through)."""
            if not isinstance(name, str):
                return None
            base = os.path.basename(name)
            for tmp, path in zip(temps, paths):
                if base == tmp.name or base.startswith(f".{tmp.name}."):
                    return path
            return None

        try:
            yield list(temps)
            with signals_deferred():  # all or none: no signal between two renames
                for tmp, path in zip(temps, paths):
                    _publish(tmp, path)
        except OSError as exc:
            raise _write_error(destination(exc.filename) or paths[0], exc) from None
        except InputError as exc:
            # A nested atomic writer named our temporary: name the real destination instead.
            target = destination(exc.source)
            if target is None:
                raise
            raise InputError(target, exc.problem, exc.hint) from None
    except BaseException:
        with signals_deferred():  # a second stop does not cut the clean-up short
            for tmp in temps:
                with contextlib.suppress(OSError):
                    tmp.unlink()
        raise


def same_file(a: PathLike, b: PathLike) -> bool:
    """Whether two paths name the same file (``os.path.samefile`` when both exist, else resolved paths)."""
    try:
        if os.path.exists(a) and os.path.exists(b):
            return os.path.samefile(a, b)
    except OSError:
        pass
    return Path(a).resolve() == Path(b).resolve()


def _file_key(path: Path) -> tuple:
    """What :func:`same_file` compares, as a key: the device and inode of an existing file, else the
    resolved path (two paths have the same key exactly when ``same_file`` says they are one file)."""
    try:
        if os.path.exists(path):
            st = os.stat(path)
            return ("inode", st.st_dev, st.st_ino)
    except OSError:
        pass
    return ("path", str(Path(path).resolve()))


def check_out_file(out: PathLike, flag: str = "--out", example: str = "brdf.npz") -> None:
    """An output named as a file stem (``X`` for ``X.npz`` and the files beside it) must not name a folder,
    an existing one or one written with a trailing separator (``o/new/``, which the path would otherwise read
    as the file ``o/new.npz``, beside the folder), nor a device, pipe or socket (``/dev/null`` would become
    ``/dev/null.npz``): :class:`InputError` naming ``out``, its hint naming ``flag`` and ``example``, a file
    name the caller writes."""
    text = os.fspath(out)
    if text and (Path(text).is_dir() or text.endswith(("/", os.sep))):
        raise InputError(text, f"{flag} is a folder", "give a file name, e.g. " + os.path.join(text, example))
    if text and Path(text).exists() and not Path(text).is_file():
        raise InputError(text, f"{flag} is a device, pipe or socket, not a file",
                         "the command writes files: give a file name, e.g. " + example)


def check_outputs(outputs: Iterable[PathLike], inputs: Iterable[Optional[PathLike]] = (),
                  flag: str = "--out") -> None:
    """Refuse outputs that would clobber an input or cannot be written, before any work is done.

    ``flag``: the option that names the outputs, for the hint (``--out``, ``--out-dir``).

    Raises:
        InputError: naming the output, if it is one of ``inputs`` (same file by
            ``os.path.samefile`` or resolved path), two outputs coincide, it is
            an existing directory or special file (a device, pipe or socket), its parent
            is a file, or its folder (the
            nearest existing one) is not writable: a temporary file is made and
            removed there, which also catches what permissions do not say
            (a read-only or special file system such as ``/proc``).
    """
    outputs = [Path(o) for o in outputs]
    inputs = [Path(i) for i in inputs if i is not None and str(i)]
    seen = set()        # the outputs' identities so far (one pass, not a pair per two outputs)
    probed = set()      # folders where a file was made
    for out in outputs:
        for inp in inputs:
            if same_file(out, inp):
                raise InputError(out, f"output would overwrite the input {inp}", f"choose another {flag}")
        key = _file_key(out)
        if key in seen:
            raise InputError(out, "is written twice by this command", f"choose another {flag}")
        seen.add(key)
        if out.is_dir():
            raise InputError(out, "output is a directory", "give a file name")
        if out.exists() and not out.is_file():  # the rename would replace a device or pipe with a file
            raise InputError(out, "output is a device, pipe or socket, not a file", "give a file name")
        parent = out.parent
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
        if parent in probed:
            continue
        if not parent.is_dir():
            raise InputError(out, f"cannot be written: {parent} is not a folder", f"choose another {flag}")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise InputError(out, f"cannot be written: the folder {parent} is not writable",
                             f"choose another {flag}")
        try:  # what os.access cannot tell (root, read-only or special file systems such as /proc)
            with tempfile.TemporaryFile(dir=parent):
                pass
        except OSError as error:
            raise InputError(out, f"cannot be written: a file cannot be made in {parent} "
                             f"({error.strerror or error})", f"choose another {flag}") from None
        probed.add(parent)
