"""A slow, plainly written numpy lighting matrix: the reference for tests and the benchmark.

It uses the same light directions as :func:`mi_bivariate.lighting.lighting_matrix`
(:func:`mi_bivariate.lighting.light_directions`) but computes everything else
independently: radiance through :meth:`Probe.eval` (numpy in, numpy out),
Rusinkiewicz angles through :func:`mi_bivariate.coordinates.half_diff_from_dirs`
on local-frame vectors in float64, and the bilinear splat with ``np.add.at``.
"""

from __future__ import annotations

from typing import Any, Sequence, Union

import numpy as np

from mi_bivariate.capture import Observations
from mi_bivariate.coordinates import half_diff_from_dirs, st_from_half_diff
from mi_bivariate.lighting import direction_pairs, hemisphere_offsets, light_directions


def lighting_matrix_reference(obs: Observations, probes: Union[Any, Sequence[Any]], n_t: int = 32,
                              n_s: int = 32, n_dirs: int = 32000, seed: int = 0,
                              rows: Any = None, block: int = 8, cosine: bool = True) -> np.ndarray:
    """Eq. 4 row by row: ``(len(rows), n_t * n_s, 3) float64``.

    Args:
        rows: optional subset of rows (indices into ``obs``), e.g. to time a
            part of a big job; the per-row shifts are those of the full job.
        block: rows per numpy step (bounds memory: ``block * K`` directions).
        cosine: include Eq. 3's ``cos theta_u`` (``False`` only for the
            negative controls of the model-agreement test).
    """
    probes = list(probes) if isinstance(probes, (list, tuple)) else [probes]
    rows = np.arange(len(obs)) if rows is None else np.asarray(rows)
    offsets = hemisphere_offsets(len(obs), seed)
    k_total = 2 * direction_pairs(n_dirs)
    out = np.zeros((len(rows), n_t * n_s, 3))
    for start in range(0, len(rows), block):
        sel = rows[start:start + block]
        n = obs.normals[sel] / np.linalg.norm(obs.normals[sel], axis=1, keepdims=True)
        v = obs.views[sel] / np.linalg.norm(obs.views[sel], axis=1, keepdims=True)
        dirs, cos_u = light_directions(n, v, n_dirs, offsets[sel])          # (b, K, 3), (b, K)
        radiance = np.empty(dirs.shape)
        for b, r in enumerate(sel):
            radiance[b] = probes[obs.probe_index[r]].eval(dirs[b])

        # Local frame: any orthonormal frame about n works for an isotropic BRDF.
        helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        tx = np.cross(helper, n)
        tx /= np.linalg.norm(tx, axis=1, keepdims=True)
        ty = np.cross(n, tx)
        frame = np.stack([tx, ty, n], axis=1)                                # (b, 3, 3) rows = axes
        wi = np.einsum("bij,bkj->bki", frame, dirs)
        wo = np.einsum("bij,bj->bi", frame, v)[:, None, :]
        theta_h, _, theta_d, _ = half_diff_from_dirs(wi, np.broadcast_to(wo, wi.shape))
        s, t = st_from_half_diff(theta_h, theta_d)

        fs, ft = np.clip(s, 0, 1) * (n_s - 1), np.clip(t, 0, 1) * (n_t - 1)
        i_s = np.minimum(np.floor(fs).astype(int), n_s - 2)
        i_t = np.minimum(np.floor(ft).astype(int), n_t - 2)
        ws, wt = fs - i_s, ft - i_t
        foreshortening = cos_u if cosine else np.ones_like(cos_u)
        value = radiance * (foreshortening * (2.0 * np.pi / k_total))[..., None]  # (b, K, 3)
        row_of = np.broadcast_to(np.arange(len(sel))[:, None], i_s.shape) + start
        for di, dj, w in ((0, 0, (1 - wt) * (1 - ws)), (0, 1, (1 - wt) * ws),
                          (1, 0, wt * (1 - ws)), (1, 1, wt * ws)):
            col = (i_t + di) * n_s + (i_s + dj)
            np.add.at(out, (row_of.ravel(), col.ravel()), (value * w[..., None]).reshape(-1, 3))
    return out
