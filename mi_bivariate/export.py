"""What a recovery writes: the table (``.npz``), its EXR view, a MERL ``.binary`` and the report, all or none."""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Iterable, List, Optional

from mi_bivariate.atomic import atomic_paths, check_out_file, check_outputs
from mi_bivariate.common import PathLike
from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.merl import check_values
from mi_bivariate.recover import Recovery
from mi_bivariate.report import recovery_report_panels, write_recovery_report
from mi_bivariate.report_worker import ReportWorker


def output_paths(out: PathLike, merl: bool = False, report: bool = True) -> List[Path]:
    """The files :func:`write_outputs` writes for ``out``: ``.npz``, ``.exr``, [``.binary``], [``_report.png``]."""
    out = Path(out)
    if out.suffix.lower() != ".npz":
        out = out.with_suffix(".npz")
    paths = [out, out.with_suffix(".exr")]
    if merl:
        paths.append(out.with_suffix(".binary"))
    if report:
        paths.append(out.with_name(out.stem + "_report.png"))
    return paths


def recovery_input_files(result: Recovery) -> List[Path]:
    """The files a recovery is known to have read: its probes' files (:attr:`Probe.source
    <mi_bivariate.probes.Probe.source>`, when that is a file) and the photos its table's provenance
    names (``provenance["photos"]``, which ``mi-bivariate recover`` sets). A :class:`Recovery` holds its
    images' pixels, not their paths: a photo read in Python is known only when the caller says so."""
    names = [getattr(probe, "source", None) for probe in result.probes]
    names += list(result.brdf.provenance.get("photos") or [])
    return [Path(name) for name in names if isinstance(name, (str, os.PathLike)) and os.path.isfile(name)]


def write_outputs(result: Recovery, out: PathLike, merl: bool = False, report: bool = True,
                  report_render: bool = False, inputs: Iterable[PathLike] = (),
                  report_worker: Optional[ReportWorker] = None) -> List[Path]:
    """Write the table (``.npz``), its EXR view, optionally a MERL ``.binary`` and a PNG report.

    The report's re-render is the model's prediction ``L f`` unless ``report_render``
    asks for a path-traced one (:func:`mi_bivariate.report.write_recovery_report`). A
    ``report_worker`` (:class:`~mi_bivariate.report_worker.ReportWorker`) draws it in its process.

    All or none: every file is written to a temporary first and they are
    renamed into place together (:func:`mi_bivariate.atomic.atomic_paths`).
    Never over an input: before anything is written, the outputs are checked
    (:func:`mi_bivariate.atomic.check_outputs`) against the files the recovery
    knows it read (:func:`recovery_input_files`: its probes' files, and the photos
    its provenance names) and ``inputs``. The recovery does not know the path of a
    photo loaded in Python: give it in ``inputs`` (``inputs=["photo.exr"]``) or
    record it as ``result.brdf.provenance["photos"]`` to protect it.
    Returns the paths written. An output of the set that this call does not write (a ``.binary`` or a
    report) left beside ``out`` by an earlier run is warned about (:class:`InputWarning`), not deleted.

    Raises:
        InputError: naming ``out``, if an output would replace one of those inputs,
            or cannot be written (a directory, a folder that is not writable), or ``out`` names a
            folder (an existing one, or one ending in a separator: give a file name in it).
    """
    paths = output_paths(out, merl=merl, report=report)
    protected = recovery_input_files(result) + [Path(p) for p in inputs]
    try:
        check_out_file(out, flag="out")  # a folder's name would write X.npz beside it, not in it
        check_outputs(paths, protected, flag="out")
    except InputError as exc:
        raise InputError("out", f"{exc.source}: {exc.problem}", exc.hint) from None
    merl_table = result.brdf.to_merl() if merl else None
    if merl_table is not None:  # checked before anything is written, naming the output (not its temporary)
        check_values(merl_table.table, paths[2], "a MERL reader would refuse it: leave --merl out")
    with atomic_paths(paths) as temps:
        result.brdf.save(temps[0])
        result.brdf.save_exr(temps[1])
        if merl_table is not None:
            merl_table.write(temps[2], validate=False)
        if report and report_worker is not None:
            report_worker.write(recovery_report_panels(result, path_trace=report_render), temps[-1])
        elif report:
            write_recovery_report(result, temps[-1], path_trace=report_render)
    # An earlier run's .binary or report beside the new table would read as part of this set.
    stale = [p for p in output_paths(out, merl=True, report=True) if p not in paths and p.is_file()]
    if stale:
        them = "it" if len(stale) == 1 else "them"
        warnings.warn(f"out: {', '.join(p.name for p in stale)} beside {paths[0].name} {'was' if them == 'it' else 'were'} "
                      f"not written by this run and may belong to an earlier table (delete {them}, or write "
                      f"{them} again: --merl, the report)", InputWarning, stacklevel=2)
    return paths
