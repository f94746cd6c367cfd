"""What a recovery writes: the table (``.npz``), its EXR view, a MERL ``.binary`` and the report, all or none."""

from __future__ import annotations

from pathlib import Path
from typing import List

from mi_bivariate.atomic import atomic_paths
from mi_bivariate.common import PathLike
from mi_bivariate.recover import Recovery
from mi_bivariate.report import write_recovery_report


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


def write_outputs(result: Recovery, out: PathLike, merl: bool = False, report: bool = True,
                  report_render: bool = False) -> List[Path]:
    """Write the table (``.npz``), its EXR view, optionally a MERL ``.binary`` and a PNG report.

    The report's re-render is the model's prediction ``L f`` unless ``report_render``
    asks for a path-traced one (:func:`mi_bivariate.report.write_recovery_report`).

    All or none: every file is written to a temporary first and they are
    renamed into place together (:func:`mi_bivariate.atomic.atomic_paths`).
    Returns the paths written.
    """
    paths = output_paths(out, merl=merl, report=report)
    with atomic_paths(paths) as temps:
        result.brdf.save(temps[0])
        result.brdf.save_exr(temps[1])
        if merl:
            result.brdf.to_merl().write(temps[2])
        if report:
            write_recovery_report(result, temps[-1], path_trace=report_render)
    return paths
