"""The solve as :func:`mi_bivariate.recover.recover` runs it: the smoothness prior, then the basis prior."""

from __future__ import annotations

from typing import Any, Optional

from mi_bivariate.basis_prior import BasisPrior
from mi_bivariate.prior import Prior
from mi_bivariate.solve.data_term import DataTerm
from mi_bivariate.solve.evidence import DEFAULT_PAIR_RULE
from mi_bivariate.solve.regularised import SolveResult, solve_prepared


def solve_stages(data: DataTerm, prior: Prior, alpha: Any = None,
                 basis: Optional[BasisPrior] = None,
                 pair_rule: str = DEFAULT_PAIR_RULE) -> SolveResult:
    """The solve as :func:`recover` runs it: the smoothness prior, then the basis prior.

    Stage 1 chooses alpha (``alpha``) and, per channel, the weight pair (``pair_rule``; both
    as :func:`mi_bivariate.solve.solve`). Stage 2, with a basis prior, adds its per-node
    Gaussian, predicted from the first table and its confidence, and solves again with the
    first stage's alphas and pairs (the result keeps the first stage's rule names). The first stage's
    residuals, which only its result would report, are not computed when a second stage follows.
    """
    first = solve_prepared(data, prior, alpha, pair_rule=pair_rule, residuals=basis is None)
    if basis is None:
        return first
    mean, std = basis.predict(first.table, first.resolution, first.posterior_std)
    pairs = tuple(p for p in first.pairs if p in first.winner)
    # recover() saves every confidence map of the second stage: computed on the channels' threads.
    second = solve_prepared(data, prior, first.alphas, mean=mean, mean_std=std, pairs=pairs,
                                      winner=first.winner, maps=("resolution", "posterior_std", "measured"))
    second.alpha_rule, second.pair_rule, second.alpha_choice = first.alpha_rule, first.pair_rule, first.alpha_choice
    return second
