"""``mi-bivariate demo``: the paper's experiment on one material, end to end.

Render a sphere of a measured material (MERL-NBRDF, full 3D table) under one
probe, recover its bivariate BRDF from that single image, re-render the
recovery under a novel probe next to the ground truth, and show a figure with
the error numbers. Without the shared data folder it uses an analytic
Cook-Torrance/GGX material (not bivariate) under two synthetic environments.

The input is path-traced (``spp`` samples per pixel, like a photograph's
noise). The images that are *scored* under the novel probe (the truth, the
recovery and the exact reduction's table) come from the converged reference
renderer (:mod:`mi_bivariate.reference`, at most 128 px, its default
directions scaled by ``min(1, spp / 256)``). Headline numbers: the relight
error and its floor (the exact reduction's table rendered the same way), the
scoring renders' own noise (the truth's render against a second seed, over
sqrt 2), Eq. 1 over the observed cells, and the exact and grid floors
(:func:`mi_bivariate.bivariate.floors`).

A shared MERL-NBRDF material is recovered with priors learnt from the other 72
(:func:`mi_bivariate.training_set.leave_one_out_priors`): the packaged ones saw
it. Any other material gets the packaged priors. The summary says which.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Optional, Tuple

from mi_bivariate import adequacy, metrics, nbrdf, reference, render, report, training_set
from mi_bivariate.atomic import atomic_paths
from mi_bivariate.bivariate import BivariateBRDF, floors
from mi_bivariate.common import finite_json
from mi_bivariate.errors import InputError
from mi_bivariate.images import write_exr
from mi_bivariate.merl import MERLBRDF, check_reflects
from mi_bivariate.probes import Probe, check_lit
from mi_bivariate.recover import recover
from mi_bivariate.sources import DEFAULT_ANALYTIC, have_shared_data, load_brdf, load_probe

DEFAULT_MATERIAL = "gold-metallic-paint3"
#: The demo's probes (shared ones: without the shared data they get synthetic stand-ins).
DEFAULT_INPUT_PROBE, DEFAULT_NOVEL_PROBE = "grace_latlong_1k", "pisa_256"


def _materials_and_probes(material: Optional[str], input_probe: str, novel_probe: str,
                          data_dir: Optional[str]) -> Tuple[str, str, MERLBRDF, Probe, Probe]:
    """``(label, spec, 3D truth, input probe, novel probe)``: shared data if present, else analytic + synthetic."""
    if material is not None and Path(material).suffix.lower() == ".npz":
        raise InputError(material, "is a bivariate table: the demo measures a 3D BRDF and scores against it",
                         "give a MERL .binary file, a MERL-NBRDF name or an analytic spec")
    if have_shared_data(data_dir):
        spec = material or DEFAULT_MATERIAL
        label = f"MERL-NBRDF {spec}" if spec in nbrdf.ALL_NBRDF_MATERIALS else spec
        probes = [load_probe(input_probe, data_dir), load_probe(novel_probe, data_dir)]
        for name, probe in zip((input_probe, novel_probe), probes):
            check_lit(probe, name)
        return (label, spec, _reflecting(load_brdf(spec, data_dir), spec), *probes)
    if data_dir is not None or (material is not None and material in nbrdf.ALL_NBRDF_MATERIALS):
        nbrdf.data_dir(data_dir)  # raises the helpful "set MI_BIVARIATE_DATA" error
    spec = material or DEFAULT_ANALYTIC
    # Without the shared data only the default (shared) probes get synthetic stand-ins; probes the
    # user named (files, synthetic:N, or another shared name, which then fails with its own error) are used.
    probes, replaced = [], []
    for name, default, stand_in in ((input_probe, DEFAULT_INPUT_PROBE, "synthetic:1"),
                                    (novel_probe, DEFAULT_NOVEL_PROBE, "synthetic:7")):
        if name == default:
            probes.append(load_probe(stand_in, data_dir))
            replaced.append(f"{name} -> {stand_in}")
        else:
            probes.append(load_probe(name, data_dir))
            check_lit(probes[-1], name)
    print("shared data not found (set MI_BIVARIATE_DATA): "
          + ("using an analytic material" if material is None else f"material {spec}")
          + (f"; synthetic probes for the shared defaults ({', '.join(replaced)})" if replaced else ""))
    return spec, spec, _reflecting(load_brdf(spec, data_dir), spec), probes[0], probes[1]


def _reflecting(truth: MERLBRDF, spec: str) -> MERLBRDF:
    """``truth``, refused (naming ``spec``) if it reflects no light: its input image would be black."""
    check_reflects(truth.table, spec)
    return truth


#: The files :func:`run_demo` writes into its folder (all or none).
OUTPUTS = ("recovered.npz", "recovered_table.exr", "input.exr", "novel_recovered.exr", "novel_truth.exr",
           "demo.png", "metrics.json")


def run_demo(out_dir: Path = Path("out/demo"), material: Optional[str] = None,
             input_probe: str = DEFAULT_INPUT_PROBE, novel_probe: str = DEFAULT_NOVEL_PROBE,
             data_dir: Optional[str] = None, spp: int = 256, seed: int = 0, resolution: int = 256) -> int:
    """Run the demo and write its outputs to ``out_dir``; returns a process exit code."""
    out_dir = Path(out_dir)
    t_start = time.perf_counter()
    label, spec, truth, probe_in, probe_novel = _materials_and_probes(material, input_probe, novel_probe, data_dir)

    print(f"[1/4] rendering the input: {label} under {probe_in.source} ({resolution}^2, {spp} spp)")
    truth_bsdf = render.bsdf_dict(truth)
    shot = render.render_sphere(truth_bsdf, probe_in, resolution=resolution, spp=spp, seed=seed)

    priors, prior_note = {}, "packaged (learnt from the 73 shared MERL-NBRDF materials)"
    shared = next((n for n in (spec, Path(spec).stem) if n in nbrdf.ALL_NBRDF_MATERIALS), None)
    if shared is not None:  # the packaged priors saw it (also as a MERL file named after it): leave it out
        priors = dict(zip(("prior", "basis_prior"), training_set.leave_one_out_priors(shared, data_dir=data_dir)))
        prior_note = f"leave-one-out (learnt from the other {len(nbrdf.ALL_NBRDF_MATERIALS) - 1} shared materials)"
    print(f"[2/4] recovering the bivariate BRDF from that one image; priors {prior_note}")
    rec = recover(shot.image, probe_in, shot.geometry, seed=seed, **priors)
    print("      " + rec.summary().replace("\n", "\n      "))

    print(f"[3/4] re-rendering recovery, exact reduction and ground truth under the novel probe "
          f"{probe_novel.source} (reference renderer)")
    floor = BivariateBRDF.reduce(truth, n_t=rec.brdf.n_t, n_s=rec.brdf.n_s)
    ref_res = min(int(resolution), 128)
    directions = reference.scaled_directions(min(1.0, spp / 256.0))
    novel_truth, novel_rec, novel_floor, second_truth = (
        reference.render_reference(b, probe_novel, resolution=ref_res, seed=s, directions=directions)
        for b, s in ((truth, seed + 1), (rec.brdf, seed + 1), (floor, seed + 1), (truth, seed + 2)))
    # the scoring renders' own noise: the truth's render against another seed's, over sqrt 2
    noise = metrics.image_relative_rmse(second_truth.image, novel_truth.image, novel_truth.mask) / math.sqrt(2.0)

    print("[4/4] errors and figure")
    n_t, n_s = rec.brdf.n_t, rec.brdf.n_s
    observed = adequacy.observed_nodes(rec.lighting_matrix, n_t, n_s)
    errors = metrics.brdf_errors(truth, rec.brdf, observed_nodes=observed)
    relight = metrics.relight_errors(novel_rec.image, novel_floor.image, novel_truth.image, novel_truth.mask)
    floor_values = floors(truth, n_t, n_s)
    numbers = {
        "material": label,
        "priors": prior_note,
        "input_probe": probe_in.source,
        "novel_probe": probe_novel.source,
        "relight_error": relight["rel_rmse"],
        "relight_floor": relight["floor"],
        "relight_ratio": relight["ratio"],
        "brdf_error_recovered_eq1_observed": errors["eq1_observed"],
        "observed_cell_fraction": errors["observed_fraction"],
        "exact_floor": floor_values["exact_floor"],
        "grid_floor": floor_values["grid_floor"],
        "brdf_error_recovered_eq1": errors["eq1"],
        "image_relative_rmse_novel": relight["rel_rmse"],
        "image_psnr_novel_db": relight["psnr"],
        "reference": {"resolution": ref_res, "directions": list(directions), "noise": noise},
        "relative_residual_input": rec.relative_residual(),
        "prior_winner_rgb": list(rec.solution.winner),
        "timings_s": {k: round(v, 3) for k, v in rec.timings.items()},
    }

    # All outputs together (all or none): a failure leaves an earlier demo's files as they were.
    with atomic_paths([out_dir / n for n in OUTPUTS]) as tmp:
        rec.brdf.save(tmp[0])
        rec.brdf.save_exr(tmp[1])
        write_exr(tmp[2], shot.image)
        write_exr(tmp[3], novel_rec.image)
        write_exr(tmp[4], novel_truth.image)
        report.write_demo_figure(tmp[5], shot, novel_rec, novel_truth, rec, truth, floor, numbers)
        tmp[6].write_text(json.dumps(finite_json(numbers), indent=2, allow_nan=False))
    figure = out_dir / "demo.png"
    numbers["total_s"] = time.perf_counter() - t_start

    print()
    print(f"  material                                {label}")
    print(f"  priors                                  {prior_note}")
    print(f"  relight error (novel probe, rel. RMSE)  {numbers['relight_error']:.4f}")
    ratio = numbers["relight_ratio"]
    print(f"  relight floor (exact reduction's table) {numbers['relight_floor']:.4f}   ratio "
          + (f"{ratio:.2f}" if math.isfinite(ratio) else "n/a (the floor is below the references' noise)"))
    print(f"  reference noise (truth, two seeds)      {noise:.4f}")
    observed = numbers["brdf_error_recovered_eq1_observed"]
    print("  BRDF error, Eq. 1 on observed cells     " + (f"{observed:.4f}" if math.isfinite(observed) else "n/a")
          + f"   ({numbers['observed_cell_fraction']:.0%} of the cells)")
    print(f"  exact floor (Eq. 1, phi_d average)      {numbers['exact_floor']:.4f}")
    print(f"  {f'grid floor (Eq. 1, {n_t}x{n_s} table)':<40}{numbers['grid_floor']:.4f}")
    print(f"  BRDF error, Eq. 1 on all cells          {numbers['brdf_error_recovered_eq1']:.4f}")
    print(f"  total time                              {numbers['total_s']:.1f} s")
    print(f"  figure: {figure}    outputs: {out_dir}/")
    return 0
