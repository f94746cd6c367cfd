"""An evaluation's files: ``results.jsonl`` (read, repair, append), the per-material
artifacts, ``summary.csv``, Markdown tables and the figures drawn from them.

``results.jsonl`` holds one JSON line per finished material, appended,
flushed and fsynced by the parent process only, so an interrupted run loses
nothing that finished; damaged lines (a last line cut by a kill, bytes that
are not JSON) are set aside and their materials recomputed. Small
per-material artifacts (tables, float16 renders, incident-plane curves of the
truth) go to ``materials/<config hash>/<slug>.npz`` so that
:func:`make_figures` needs no recomputation.
"""

from __future__ import annotations

import collections
import csv
import io
import json
import math
import os
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from mi_bivariate.atomic import atomic_path
from mi_bivariate.common import PathLike, finite_json
from mi_bivariate.errors import InputWarning
from mi_bivariate.figures import evaluation_figures
from mi_bivariate.npzio import read_npz
from mi_bivariate.sources import input_label, probe_label

RESULTS_FILE = "results.jsonl"
SUMMARY_FILE = "summary.csv"
REJECTED_FILE = "results.rejected.jsonl"


def _parse_record(line: bytes) -> Optional[dict]:
    """A results line as a record, or ``None`` if damaged (not UTF-8, not JSON, not a record)."""
    try:
        rec = json.loads(line.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        return None
    if not isinstance(rec, dict) or not isinstance(rec.get("material"), str) \
            or not isinstance(rec.get("config_hash"), str):
        return None
    return rec


def read_records(path: PathLike, config_hash: Optional[str] = None) -> List[dict]:
    """Records of a ``results.jsonl`` (optionally only those with ``config_hash``).

    Damaged lines (a last line cut by an interruption, bytes that are not
    UTF-8, invalid JSON, a record without ``material`` or ``config_hash``) are
    skipped; :func:`repair_results` sets them aside. With ``config_hash``, only
    the last record of each material (a MERL file evaluated again once its content
    changed appends a new one), in the order of those last records.
    """
    path = Path(path)
    if not path.is_file():
        return []
    records = []
    for line in path.read_bytes().splitlines():
        rec = _parse_record(line)
        if rec is not None and (config_hash is None or rec.get("config_hash") == config_hash):
            records.append(rec)
    if config_hash is None:
        return records
    latest: Dict[str, dict] = {}
    for rec in records:
        latest.pop(rec["material"], None)
        latest[rec["material"]] = rec
    return list(latest.values())


#: The digests of the bytes a material's evaluation read that its record keeps: a MERL file's
#: (``source_sha256``) and the shared data folder's probes and weights (``shared_data_sha256``).
DATA_DIGESTS = ("source_sha256", "shared_data_sha256")


def same_data(record: dict, digests: Dict[str, Optional[str]]) -> bool:
    """Whether ``record`` (an evaluation's, or ``evaluate --abs``'s) came from the bytes ``digests`` names
    (``{name in DATA_DIGESTS: digest, or None where nothing of that kind is read}``), so a rerun may reuse it.

    A MERL file's digest must be the same (a record without one, written before it was kept, is evaluated
    again). The shared data's may be missing from the record: written before it was kept, when shared
    names alone entered the config hash, such a record is reused as it was.
    """
    source, shared = (digests.get(name) for name in DATA_DIGESTS)
    return record.get("source_sha256") == source and record.get("shared_data_sha256", shared) == shared


def repair_results(path: PathLike) -> int:
    """Set damaged lines of a results file aside so that their materials are recomputed.

    Damaged lines (see :func:`read_records`) are appended, as they were, to
    ``results.rejected.jsonl`` beside it, and the results file is rewritten
    (atomically) with the good lines only, ending in a newline. Returns the
    number of lines set aside. Every complete record is kept, whatever its
    configuration.
    """
    path = Path(path)
    if not path.is_file():
        return 0
    raw = path.read_bytes()
    lines = [line for line in raw.splitlines() if line.strip()]
    good = [line for line in lines if _parse_record(line) is not None]
    bad = [line for line in lines if _parse_record(line) is None]
    if bad:
        rejected = path.with_name(REJECTED_FILE)
        with open(rejected, "ab") as f:
            f.write(b"".join(line + b"\n" for line in bad))
            f.flush()
            os.fsync(f.fileno())
        warnings.warn(f"{path}: {len(bad)} damaged line(s) set aside in {rejected}; their materials are "
                      "recomputed", InputWarning, stacklevel=2)
    if bad or (raw and not raw.endswith(b"\n")) or len(lines) != len(raw.splitlines()):
        with atomic_path(path) as tmp:
            tmp.write_bytes(b"".join(line + b"\n" for line in good))
    return len(bad)


def _nulls_as_nan(value: Any) -> Any:
    """A record read back with its ``null`` numbers (written for NaN or Infinity) as NaN, for the tables and
    figures (which only read numbers from it)."""
    if isinstance(value, dict):
        return {k: _nulls_as_nan(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_nulls_as_nan(v) for v in value]
    return float("nan") if value is None else value


def append_record(path: PathLike, record: dict) -> None:
    """Append one JSON line, flushed and fsynced (the only writer is the parent process).

    The line is valid JSON: a non-finite number (a PSNR of identical images, a ratio to a zero
    floor) is written as ``null``, not as the bare ``NaN``/``Infinity`` other readers refuse.
    """
    line = json.dumps(finite_json(record), sort_keys=True, allow_nan=False)
    with open(path, "a", encoding="utf-8") as f:
        f.write(line + "\n")
        f.flush()
        os.fsync(f.fileno())


def save_artifacts(path: PathLike, arrays: Dict[str, np.ndarray]) -> None:
    """Write a material's artifact arrays as a compressed ``.npz`` (atomic)."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)


def artifact_path(out_dir: PathLike, record_or_slug: Union[dict, str], config_hash: Optional[str] = None) -> Path:
    """``out_dir/materials/<config hash>/<slug>.npz``: one folder per configuration, so a
    rerun with another configuration never overwrites the artifacts of recorded results."""
    if isinstance(record_or_slug, dict):
        slug, config_hash = record_or_slug["slug"], record_or_slug["config_hash"]
    else:
        slug = record_or_slug
    return Path(out_dir) / "materials" / str(config_hash) / f"{slug}.npz"


def load_artifacts(path: PathLike) -> Dict[str, np.ndarray]:
    """Read a material's artifacts (all arrays into memory); :class:`~mi_bivariate.errors.InputError`
    naming the file if it is missing or damaged."""
    return read_npz(path, "material's artifacts file", text=())


def summary_rows(records: Sequence[dict]) -> List[dict]:
    """One flat row per (material, input probe): the numbers of ``summary.csv``."""
    rows = []
    for r in map(_nulls_as_nan, records):
        for probe, e in r["inputs"].items():
            row = {"material": r["material"], "input_probe": probe}
            for key in ("eq1", "eq1_min", "cosine", "log"):
                row[f"floor_{key}"] = r["floor"][key]
                row[f"recovered_{key}"] = e["recovered"][key]
                for fam, b in e.get("baselines", {}).items():
                    row[f"{fam}_{key}"] = b["errors"][key]
            rmse = [v["rel_rmse"] for v in e["images"].values()]
            psnr = [v["psnr"] for v in e["images"].values() if math.isfinite(v["psnr"])]
            floor_rmse = [v["rel_rmse"] for v in r["floor_images"].values()]
            row["image_rel_rmse_mean"] = float(np.mean(rmse)) if rmse else float("nan")
            row["image_psnr_mean"] = float(np.mean(psnr)) if psnr else float("nan")
            row["floor_image_rel_rmse_mean"] = float(np.mean(floor_rmse)) if floor_rmse else float("nan")
            noise = [v for v in r.get("reference_noise", {}).values() if math.isfinite(v)]
            if noise:  # the truth renders' own noise, the largest over the novel probes (older records: none)
                row["reference_noise_max"] = float(max(noise))
            for key in ("exact_floor", "grid_floor", "exact_floor_min", "grid_floor_min"):
                if key in r.get("floors", {}):
                    row[key] = r["floors"][key]
            if "eq1_observed" in e["recovered"]:
                row["recovered_eq1_observed"] = e["recovered"]["eq1_observed"]
                row["grid_floor_observed"] = e.get("grid_floor_observed", float("nan"))
                row["exact_floor_observed"] = e.get("exact_floor_observed", float("nan"))
                row["observed_fraction"] = e["recovered"]["observed_fraction"]
            if "confident" in e:  # the cells the recovery's own per-node confidence (> 0.5) calls measured
                row["recovered_eq1_confident"] = e["confident"]["eq1"]
                row["grid_floor_confident"] = e["confident"]["floor_eq1"]
                row["exact_floor_confident"] = e["confident"].get("exact_floor_eq1", float("nan"))
                row["confident_fraction"] = e["confident"]["node_fraction"]
            for region, v in e["recovered"].get("regions", {}).items():
                row[f"recovered_eq1_{region}"] = v["eq1"]
                row[f"recovered_share_{region}"] = v["share"]
            ratios = [v["ratio"] for v in e["images"].values() if "ratio" in v]
            if ratios:
                row["relight_rmse_median"] = float(np.median(rmse))
                row["relight_floor_median"] = float(np.median([v["floor"] for v in e["images"].values()]))
                # over the novel probes whose floor is above the references' noise (the others' ratios
                # are null), as scripts/issue9_targets.py takes it; NaN when there is none
                finite = [v for v in ratios if math.isfinite(v)]
                row["relight_ratio_median"] = float(np.median(finite)) if finite else float("nan")
                for novel, v in e["images"].items():
                    row[f"relight_{novel}"] = v["rel_rmse"]
                    row[f"relight_floor_{novel}"] = v["floor"]
            row["relative_residual"] = e["relative_residual"]
            row["rank_fraction"] = e["adequacy"]["rank_fraction"]
            row["adequate"] = e["adequacy"]["adequate"]
            row["recover_s"] = sum(v for k, v in e["timings"].items()
                                   if k in ("observations", "lighting matrix", "adequacy", "solve"))
            row["material_total_s"] = r["timings"]["total"]
            rows.append(row)
    return rows


def write_summary_csv(records: Sequence[dict], path: PathLike) -> Path:
    """``summary.csv`` from :func:`summary_rows` (atomic)."""
    rows = summary_rows(records)
    keys: List[str] = []
    for row in rows:
        keys += [k for k in row if k not in keys]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=keys)
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue())
    return path


def make_figures(out_dir: PathLike, records: Optional[Sequence[dict]] = None,
                 formats: Sequence[str] = ("png",), fig_dir: Optional[PathLike] = None,
                 dpi: int = 100) -> List[Path]:
    """Draw the evaluation figures from ``results.jsonl`` and the artifacts (no recomputation).

    Figures (in ``out_dir/figures`` unless ``fig_dir``): ``fig3_reduction``,
    ``fig5_validation``, ``fig6_incident``, ``fig6_errors``, ``fig7_environment``,
    ``tables``, ``baselines``; one file per format in ``formats`` (png, pdf).
    """
    out = Path(out_dir)
    if records is None:
        config = json.loads((out / "config.json").read_text())
        records = read_records(out / RESULTS_FILE, config["config_hash"])
    records = list(records)
    if not records:
        return []
    fig_dir = Path(fig_dir) if fig_dir is not None else out / "figures"
    arts = {r["material"]: load_artifacts(artifact_path(out, r)) for r in records}
    inputs, novel = _probe_order(out, records[0])
    return evaluation_figures([_nulls_as_nan(r) for r in records], arts, fig_dir, formats=formats, dpi=dpi,
                              novel_probes=novel, input_probes=inputs)


def _probe_order(out: Path, record: dict) -> Tuple[Optional[List[str]], Optional[List[str]]]:
    """The labels of ``record``'s inputs and of its novel probes, each in its configuration's order
    (``out/config.json``'s, for a record of that configuration); ``None`` for either where that file is
    unreadable or of another configuration.

    A record's dicts come back from ``results.jsonl`` in alphabetical order (it is written with sorted
    keys): the figures' "first input" and "first novel probe" are the configuration's first, not the
    alphabetically first.
    """
    try:
        config = json.loads((out / "config.json").read_text())
    except (OSError, ValueError):
        return None, None
    if not isinstance(config, dict) or config.get("config_hash") != record.get("config_hash"):
        return None, None
    inputs = [input_label(str(name)) for name in config.get("input_probes") or ()]
    novel = [probe_label(str(name)) for name in config.get("novel_probes") or ()]
    return ([label for label in inputs if label in record.get("inputs", {})] or None,
            [label for label in novel if label in record.get("floor_images", {})] or None)


def _fmt(v: Any, digits: int = 3) -> str:
    if isinstance(v, bool) or v is None:
        return str(v)
    if isinstance(v, (int, float)) and not math.isfinite(v):
        return "inf" if v > 0 else ("nan" if v != v else "-inf")
    if isinstance(v, float):
        return f"{v:.{digits}g}" if abs(v) >= 1e3 or abs(v) < 1e-2 else f"{v:.{digits}f}"
    return str(v)


#: The results page's per-material table (:func:`markdown_table`): floors, where the image looks, relighting.
HEADLINE_COLUMNS = (("material", "material"), ("input_probe", "input"),
                    ("exact_floor", "exact floor"), ("grid_floor", "grid floor"),
                    ("recovered_eq1", "rec. Eq.1"), ("recovered_eq1_observed", "rec. Eq.1 obs."),
                    ("grid_floor_observed", "grid floor obs."), ("observed_fraction", "obs. cells"),
                    ("recovered_eq1_min", "rec. Eq.1>1e-3"), ("recovered_cosine", "rec. cos"),
                    ("recovered_log", "rec. log"),
                    ("recovered_eq1_specular", "Eq.1 spec."), ("recovered_eq1_retro", "Eq.1 retro"),
                    ("recovered_eq1_grazing", "Eq.1 grazing"), ("recovered_eq1_rest", "Eq.1 rest"),
                    ("relight_rmse_median", "relight"), ("relight_floor_median", "relight floor"),
                    ("relight_ratio_median", "ratio"))

SUMMARY_COLUMNS = (("material", "material"), ("input_probe", "input"),
                   ("floor_log", "floor log"), ("recovered_log", "rec. log"),
                   ("ggx_log", "GGX log"), ("ward_log", "Ward log"),
                   ("floor_eq1", "floor Eq.1"), ("recovered_eq1", "rec. Eq.1"),
                   ("floor_eq1_min", "floor Eq.1>1e-3"), ("recovered_eq1_min", "rec. Eq.1>1e-3"),
                   ("ggx_eq1_min", "GGX Eq.1>1e-3"), ("ward_eq1_min", "Ward Eq.1>1e-3"),
                   ("floor_cosine", "floor cos"), ("recovered_cosine", "rec. cos"),
                   ("image_rel_rmse_mean", "img RMSE"), ("floor_image_rel_rmse_mean", "floor img RMSE"),
                   ("image_psnr_mean", "PSNR dB"), ("rank_fraction", "rank"))


def markdown_table(records: Sequence[dict], columns: Sequence[Tuple[str, str]] = SUMMARY_COLUMNS) -> str:
    """The summary rows as a Markdown table (columns absent from every row are left out)."""
    rows = summary_rows(records)
    cols = [(k, h) for k, h in columns if any(k in r for r in rows)]
    lines = ["| " + " | ".join(h for _, h in cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(_fmt(r.get(k, "")) for k, _ in cols) + " |" for r in rows]
    return "\n".join(lines)


def format_summary(records: Sequence[dict]) -> str:
    """A short plain-text summary: medians over materials per input probe, and the slowest stage."""
    rows = summary_rows(records)
    if not rows:
        return "no results"
    lines = [f"{len(records)} materials"]
    sources = collections.Counter(str(entry.get("prior", "?")).split(":")[0].split(" (")[0]
                                  for r in records for entry in r.get("inputs", {}).values())
    if sources:  # packaged priors saw the shared materials: a score needs leave-one-out ones
        lines.append("  priors: " + ", ".join(f"{k} ({v} recoveries)" for k, v in sorted(sources.items())))
    noise = [v for r in records for v in (r.get("reference_noise") or {}).values()
             if isinstance(v, float) and math.isfinite(v)]
    if noise:  # what the relight errors and floors cannot resolve
        lines.append(f"  reference noise (the truth's renders under the novel probes; two seeds): median "
                     f"{np.median(noise):.2g}, largest {max(noise):.2g}"
                     + ("" if len(noise) == sum(len(r.get("floor_images", {})) for r in records)
                        else " (some renders have none: records written before it was measured, or a black "
                             "truth render)"))
    for probe in dict.fromkeys(r["input_probe"] for r in rows):
        sel = [r for r in rows if r["input_probe"] == probe]
        parts = []
        for key, label in (("exact_floor", "exact floor"), ("grid_floor", "grid floor"),
                           ("recovered_eq1_observed", "recovered Eq.1 observed"),
                           ("recovered_log", "recovered log"), ("ggx_log", "GGX log"), ("ward_log", "Ward log"),
                           ("recovered_eq1_min", "recovered Eq.1>1e-3"),
                           ("relight_rmse_median", "relight"), ("relight_floor_median", "relight floor"),
                           ("relight_ratio_median", "relight/floor")):
            vals = [r[key] for r in sel if key in r and math.isfinite(r[key])]
            if vals:
                parts.append(f"{label} {np.median(vals):.3f}")
                if key == "relight_ratio_median" and len(vals) < len(sel):  # floors below the references' noise
                    parts[-1] += f" (over {len(vals)} of {len(sel)} materials: the others' floors are noise)"
        lines.append(f"  input {probe}: median " + ", ".join(parts))
    return "\n".join(lines)
