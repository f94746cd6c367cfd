"""Regenerate the packaged priors from the shared MERL-NBRDF materials (all 73, 32 x 32).

    MI_BIVARIATE_DATA=../shared/data python scripts/make_priors.py

writes ``mi_bivariate/data/default_prior.npz`` (the smoothness prior of Eq. 6) and
``mi_bivariate/data/basis_prior.npz`` (the data-driven table prior). Numbers reported
on a shared material never use these: the evaluation learns leave-one-out priors
(:func:`mi_bivariate.training_set.leave_one_out_priors`).
"""

import argparse

from mi_bivariate import training_set
from mi_bivariate.basis_prior import DEFAULT_BASIS_PRIOR_PATH
from mi_bivariate.nbrdf import ALL_NBRDF_MATERIALS
from mi_bivariate.prior import DEFAULT_PRIOR_PATH


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()  # --help prints this, writes nothing
    smooth, basis = training_set.learn_priors_from_merl(list(ALL_NBRDF_MATERIALS), 32, 32)
    smooth.save(DEFAULT_PRIOR_PATH)
    basis.save(DEFAULT_BASIS_PRIOR_PATH)
    print(f"wrote {DEFAULT_PRIOR_PATH} ({len(smooth.provenance['materials'])} materials) and "
          f"{DEFAULT_BASIS_PRIOR_PATH} ({basis.basis.shape[1]} components)")


if __name__ == "__main__":
    main()
