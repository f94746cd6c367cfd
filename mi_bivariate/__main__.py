"""``python -m mi_bivariate``: the ``mi-bivariate`` command (:func:`mi_bivariate.cli.run`)."""

import sys

from mi_bivariate.cli import run

if __name__ == "__main__":
    sys.exit(run())
