"""Batch evaluation: the paper's experiments over a set of materials (``mi-bivariate evaluate``).

Per material (a MERL ``.binary``, a MERL-NBRDF name or an analytic spec) and
per input probe:

1. render the input image of the full 3D BRDF (``merl`` plugin, trilinear)
   with the converged reference renderer (:mod:`mi_bivariate.reference`,
   deterministic hemisphere quadrature; ``renderer="path"`` path-traces
   instead), clean unless ``noise`` adds the camera noise of
   :mod:`mi_bivariate.noise`;
2. :func:`~mi_bivariate.recover.recover` the bivariate BRDF from it;
3. render under every novel probe, with the *same* renderer and the same
   quadrature seed: the recovery (``bivariate`` plugin), the exact reduction's
   ``n_t x n_s`` table and the 3D truth; the *relight floor* is the reduction's
   image error against the truth, and the recovery's error is reported with
   its ratio to that floor (:func:`mi_bivariate.metrics.relight_errors`); the truth's own noise is measured by a
   second render of another seed (``"reference_noise"`` per novel probe);
4. fit the parametric baselines (:mod:`mi_bivariate.baselines`) to the same
   observations through the same lighting matrix;
5. record the BRDF errors of :class:`mi_bivariate.metrics.BRDFErrors` (Eq. 1
   over all cells, over the cells the input observes
   (:func:`mi_bivariate.adequacy.observed_nodes` and
   :func:`mi_bivariate.metrics.observed_cells`) and over f > 1e-3;
   cosine-weighted; log-space; per region) for the recovery, the grid table
   and the baselines; the *exact floor* and the *grid floor*
   (:func:`mi_bivariate.bivariate.floors`); the adequacy diagnostics and
   timings.

Reference renders of the truth and of the reduction's table depend on the
material and the probe only, not on the solver: they are cached in
``references/`` (one ``.npz`` per material, probe and render settings), so a
rerun after a solver change renders only the recoveries.

Results are one JSON line per finished material in ``results.jsonl``, with the
recovery's warnings named after the material and the input probe (``"warnings"``,
also said by the process that writes the file); a rerun skips the materials
already there with the same configuration hash (:meth:`EvalConfig.hash`) and, for
a MERL file, the same file and bytes (``"spec"``, ``"source_sha256"``). Materials
run in parallel in worker processes or on a Dask cluster. Every random choice is
seeded, so the same command reproduces the same numbers.

The package, one concept per module:

- :mod:`~mi_bivariate.evaluate.config`: :class:`EvalConfig`, its hash, the solver's identity;
- :mod:`~mi_bivariate.evaluate.protocol`: :func:`evaluate_material`, the steps above as functions;
- :mod:`~mi_bivariate.evaluate.renders`: the scored renders and their cache;
- :mod:`~mi_bivariate.evaluate.results`: results, artifacts, ``summary.csv``, tables, figures;
- :mod:`~mi_bivariate.evaluate.runner`: :func:`run_evaluation` (in-process, processes, Dask).

Materials and probes are named as in :mod:`mi_bivariate.sources`; analysis by
synthesis is :mod:`mi_bivariate.synthesis`.
"""

from __future__ import annotations

from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.evaluate.config import (
    DEFAULT_INPUT_PROBES,
    DEFAULT_NOVEL_PROBES,
    PROTOCOL_VERSION,
    QUICK_ANALYTIC,
    QUICK_NBRDF,
    EvalConfig,
    quick_materials,
)
from mi_bivariate.evaluate.protocol import INCIDENT_VIEWS, NOISE_SEED_OFFSET, MaterialTask, evaluate_material
from mi_bivariate.evaluate.results import (
    DATA_DIGESTS,
    HEADLINE_COLUMNS,
    REJECTED_FILE,
    RESULTS_FILE,
    SUMMARY_COLUMNS,
    SUMMARY_FILE,
    append_record,
    artifact_path,
    format_summary,
    load_artifacts,
    make_figures,
    markdown_table,
    read_records,
    repair_results,
    same_data,
    save_artifacts,
    summary_rows,
    write_summary_csv,
)
from mi_bivariate.evaluate.runner import (
    LOCK_FILE,
    REFERENCE_DIR,
    run_evaluation,
    threads_per_job,
)
from mi_bivariate.sources import MaterialSpec, have_shared_data, load_probe, load_truth, probe_label, resolve_materials

__all__ = [
    "DATA_DIGESTS", "DEFAULT_INPUT_PROBES", "DEFAULT_NOVEL_PROBES", "HEADLINE_COLUMNS", "INCIDENT_VIEWS", "InputError",
    "InputWarning", "LOCK_FILE", "MaterialSpec", "MaterialTask", "NOISE_SEED_OFFSET", "PROTOCOL_VERSION",
    "QUICK_ANALYTIC", "QUICK_NBRDF", "REFERENCE_DIR", "REJECTED_FILE", "RESULTS_FILE", "SUMMARY_COLUMNS",
    "SUMMARY_FILE", "EvalConfig", "append_record", "artifact_path", "evaluate_material",
    "format_summary", "have_shared_data", "load_artifacts", "load_probe", "load_truth", "make_figures",
    "markdown_table", "probe_label", "quick_materials", "read_records", "repair_results", "resolve_materials",
    "run_evaluation", "same_data", "save_artifacts", "summary_rows", "threads_per_job", "write_summary_csv",
]
