"""The renders an evaluation scores, with a cache of the ones that do not depend on the solver.

One renderer for every scored image (:mod:`mi_bivariate.reference` by
default, Mitsuba path tracing with ``renderer="path"``). Renders of the truth
and of the exact reduction depend on the material and the probe only: they
are cached as ``<cache_dir>/<key hash>.npz`` so that a rerun after a solver
change renders only the recoveries.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import mitsuba as mi
import numpy as np

from mi_bivariate import reference, render
from mi_bivariate.errors import InputError
from mi_bivariate.evaluate.config import EvalConfig
from mi_bivariate.evaluate.results import save_artifacts
from mi_bivariate.geometry import SphereGeometry
from mi_bivariate.npzio import read_npz
from mi_bivariate.probes import Probe
from mi_bivariate.sources import MaterialSpec


@dataclass
class Shot:
    """A rendered sphere as the protocol uses it."""

    image: np.ndarray
    mask: np.ndarray
    geometry: Any


class Renderer:
    """The protocol's renders: one renderer for every image that is scored, with a cache.

    Renders of the truth and of the exact reduction (``cache_key`` given)
    are cached as ``<cache_dir>/<key hash>.npz`` (image, mask, geometry). The key holds the
    material's name and, given ``truth`` (its 3D table, ``MERLBRDF``), a digest of the table's
    values: a cached render is never reused for another truth, whether its file or the code
    that decodes it changed (as when the neural truths moved from float32 to float64 decoding), and a
    touched file with the same values still hits the cache. Without ``truth``, a MERL file's size and
    modification time stand in for its values.
    """

    def __init__(self, cfg: EvalConfig, material: MaterialSpec, cache_dir: Optional[str], truth: Any = None):
        self.cfg = cfg
        self.cache_dir = Path(cache_dir) if cache_dir else None
        identity = {"label": material.label, "kind": material.kind, "spec": material.spec}
        if truth is not None:
            identity["truth_sha256"] = truth.content_digest()[:16]
        elif material.kind == "merl":  # no values to hash: the file's size and time stand in for them
            try:
                st = os.stat(material.spec)
                identity["file"] = [st.st_size, st.st_mtime_ns]
            except OSError:
                pass
        self.identity = identity
        self.seconds = 0.0
        self.renders = 0
        self.cached = 0

    def _settings(self, resolution: int, seed: int, spp: int) -> dict:
        if self.cfg.renderer == "reference":
            return {"renderer": "reference", "version": reference.REFERENCE_VERSION, "resolution": int(resolution),
                    "seed": int(seed), "directions": list(self.cfg.reference_directions)}
        return {"renderer": "path", "resolution": int(resolution), "seed": int(seed), "spp": int(spp)}

    def render(self, bsdf: Any, probe: Probe, probe_spec: str, resolution: int, seed: int, spp: int,
               cache_key: Optional[str] = None) -> Shot:
        """Render ``bsdf`` (a plugin object or anything render.bsdf_dict takes) under ``probe``."""
        settings = self._settings(resolution, seed, spp)
        path = None
        if cache_key is not None and self.cache_dir is not None:
            key = json.dumps({"material": self.identity, "what": cache_key, "probe": probe_spec,
                              "probe_sha": probe.content_digest()[:16], **settings}, sort_keys=True)
            path = self.cache_dir / f"{hashlib.sha256(key.encode()).hexdigest()[:24]}.npz"
            if path.is_file():
                try:
                    npz = read_npz(path, "render cache", required=("image", "mask", "geometry", "camera_to_world"),
                                   text=())
                    g = npz["geometry"]
                    shot = Shot(np.asarray(npz["image"], np.float32), np.asarray(npz["mask"], bool),
                                SphereGeometry(float(g[0]), float(g[1]), float(g[2]),
                                               np.asarray(npz["camera_to_world"], np.float64)))
                    self.cached += 1
                    return shot
                except (InputError, ValueError, IndexError):
                    pass                               # damaged: render again and overwrite
        t0 = time.perf_counter()
        if self.cfg.renderer == "reference":
            out = reference.render_reference(bsdf, probe, resolution=resolution, seed=seed,
                                             directions=self.cfg.reference_directions)
        else:
            source = render.bsdf_dict(bsdf) if not hasattr(bsdf, "sampler") else bsdf
            out = render.render_sphere(source, probe, resolution=resolution, spp=spp, seed=seed)
        self.seconds += time.perf_counter() - t0
        self.renders += 1
        shot = Shot(np.asarray(out.image, np.float32), np.asarray(out.mask, bool), out.geometry)
        if path is not None:
            g = shot.geometry
            with contextlib.suppress(OSError):
                path.parent.mkdir(parents=True, exist_ok=True)
                save_artifacts(path, {"image": shot.image, "mask": shot.mask,
                                      "geometry": np.array([g.cx, g.cy, g.radius]),
                                      "camera_to_world": np.asarray(g.camera_to_world, np.float64)})
        return shot


def plugin(source: Any, renderer: str) -> Any:
    """A loaded BSDF plugin (reference renderer: built once, used for every probe) or a BSDF dict."""
    bsdf = render.bsdf_dict(source)
    return mi.load_dict(bsdf) if renderer == "reference" else bsdf
