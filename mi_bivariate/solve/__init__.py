"""The constrained, regularised solve of Eq. 6.

Per colour channel k the table f (``N = n_t n_s`` nodes, column ``it * n_s + is``)
minimises

    E(f) = (1/M) ||(I_k - L_k f) / sigma_k||^2  +  alpha_k (1/N) ||R f / level_k||^2
           [ + (1/M) ||(f - mean_k) / mean_std_k||^2 ],            subject to f >= 0,

with ``R`` the prior's weighted differences (``||Λs^-1 Ds f||^2 + ||Λt^-1 Dt f||^2``,
:mod:`mi_bivariate.prior`). This is the paper's Eq. 6 with three changes, each
measured (``docs/recovery.md``, "Recovering BRDFs that hold up under new light"):

- **Noise-aware rows.** ``sigma`` is each observation's noise standard deviation
  (:func:`row_sigma`): a relative model error every prediction carries plus the
  camera's ``a I + b``. Rows are thus weighted by information, not brightness:
  several images combine by their own scale and noise (an image 50x brighter no
  longer carries 2500x the weight), dim pixels, which hold the low-valued nodes,
  count, and a noisy image is not over-fitted.
- **Scale-free alpha.** ``level_k`` is the best constant (Lambertian) table, the
  paper's starting point, so alpha is dimensionless: a brighter probe, image or
  material changes nothing. ``alpha`` is chosen by the discrepancy principle
  (:func:`discrepancy_alpha`: one alpha for the channels, the largest, at most
  :data:`DEFAULT_ALPHA`, whose fit leaves the residual the rows' expected error
  allows), per channel by generalised cross-validation (:func:`gcv_curve`), or given.
- **A table prior** (optional): a per-node Gaussian from the data-driven basis
  prior (:mod:`mi_bivariate.basis_prior`), which carries what measured materials do
  into the nodes the image does not pin down.

The non-negative least-squares problem is solved on the normal equations
``X f = b`` (``X = L^T W L / M + lambda R^T R [+ diag]``, float64, ``N x N``) with Kim &
Park's block principal pivoting (with Murty's single-exchange fallback), starting from
the paper's Lambertian initialisation. Every answer's KKT conditions are verified; if
they fail, the problem is re-solved with ``scipy.optimize.nnls`` on an eigen-reduced
``N x N`` system and the result says so. The solve is done once per weight pair (with the
discrepancy principle both pairs use the alpha chosen on the first pair's curve); per
channel the pair kept is the one under whose prior the image has the higher evidence
(marginal likelihood, :mod:`.evidence`: the fit and what the prior paid for it; the paper
kept the lower data residual, ``pair_rule="residual"``), with GCV the pair with the lower
GCV score. Each solution carries a per-node
confidence: the diagonal of the model resolution matrix ``X^-1 L^T W L / M`` (1: the
node's value comes from the image; 0: from the priors) and the posterior spread.

The package has one algorithm per module (as scipy's ``optimize/_lsq``), and this
front door re-exports their public names:

==========================  ===========================================================
:mod:`.data_term`           noise-weighted rows (:func:`row_sigma`), normal equations
                            (:func:`prepare_data_term`, built once, shared by every
                            prior variant, alpha and stage)
:mod:`.nnls`                the constrained solve: block principal pivoting
                            (:func:`nnls_gram`), KKT check, scipy fallback
:mod:`.discrepancy`         alpha by the discrepancy principle (:func:`discrepancy_alpha`,
                            the default)
:mod:`.gcv`                 alpha by generalised cross-validation (:func:`gcv_curve`)
:mod:`.evidence`            which prior variant is kept: the evidence of the image
                            (:func:`log_evidence`)
:mod:`.confidence`          resolution, posterior spread, measured share, from one
                            factorisation, computed on first use
:mod:`.regularised`         the front door: :func:`solve`, :func:`solve_prepared`,
                            :func:`alpha_sweep`; validates once, dispatches
:mod:`.stages`              the solve as ``recover`` runs it (:func:`solve_stages`: the
                            smoothness prior, then the basis prior)
:mod:`.image_weights`       several images weighted by leave-one-image-out prediction
                            (:func:`cross_image_factors`)
:mod:`.common`              constants, input checks, SPD linear algebra
==========================  ===========================================================
"""

from __future__ import annotations

from mi_bivariate.solve.common import ALPHA_RULES, DEFAULT_ALPHA, DEFAULT_ALPHA_RULE, KKT_TOLERANCE, check_alpha
from mi_bivariate.solve.confidence import Confidence
from mi_bivariate.solve.data_term import (
    DARK_FRACTION,
    MODEL_ERROR,
    MODEL_ERROR_FORMS,
    DataTerm,
    prepare_data_term,
    row_sigma,
)
from mi_bivariate.solve.discrepancy import DISCREPANCY_ALPHAS, DISCREPANCY_TARGET, DiscrepancyChoice, discrepancy_alpha
from mi_bivariate.solve.evidence import DEFAULT_PAIR_RULE, PAIR_RULES, check_pair_rule, log_evidence, penalty_log_pdet
from mi_bivariate.solve.gcv import GCV_ALPHAS, GCV_PROBES, GCVCurve, gcv_curve
from mi_bivariate.solve.image_weights import CROSS_FLOOR, IMAGE_WEIGHTS, cross_image_factors
from mi_bivariate.solve.nnls import NNLSResult, kkt_violation, nnls_gram
from mi_bivariate.solve.regularised import PairSolution, SolveResult, SweepPoint, alpha_sweep, solve, solve_prepared
from mi_bivariate.solve.stages import solve_stages

__all__ = [
    "ALPHA_RULES", "DEFAULT_ALPHA", "DEFAULT_ALPHA_RULE", "DEFAULT_PAIR_RULE", "PAIR_RULES", "check_pair_rule",
    "log_evidence",
    "penalty_log_pdet", "DISCREPANCY_ALPHAS", "DISCREPANCY_TARGET",
    "DiscrepancyChoice", "check_alpha", "discrepancy_alpha", "KKT_TOLERANCE", "DARK_FRACTION", "MODEL_ERROR",
    "MODEL_ERROR_FORMS", "GCV_ALPHAS",
    "GCV_PROBES", "Confidence", "DataTerm", "GCVCurve", "NNLSResult", "PairSolution", "SolveResult",
    "SweepPoint", "alpha_sweep", "gcv_curve", "kkt_violation", "nnls_gram", "prepare_data_term", "row_sigma",
    "solve", "solve_prepared", "solve_stages", "CROSS_FLOOR", "IMAGE_WEIGHTS", "cross_image_factors",
]
