"""The ``mi-bivariate`` command: the console script, ``python -m mi_bivariate`` and ``python -m mi_bivariate.cli``
(:func:`main`)."""

import sys


def main() -> int:
    """:func:`mi_bivariate.cli.run`, with the Ctrl-C that comes before the command has set up its own stop.

    Loading numpy and the command line takes the first ~0.1-0.3 s of a process; a Ctrl-C then used
    to end in a traceback from inside an import. It now ends as a later one does
    (:func:`mi_bivariate.cli.run`): one line, ``mi-bivariate: interrupted``, exit status 130.
    Before numpy loads, the BLAS libraries are set to start with one thread
    (:func:`mi_bivariate.process.one_blas_thread_at_load`).
    """
    try:
        from mi_bivariate import process  # the standard library only: numpy is not loaded yet

        process.one_blas_thread_at_load()  # before numpy and scipy load their BLAS libraries
        from mi_bivariate.cli import run  # deliberately here, inside the guard: it loads numpy
        return run()
    except KeyboardInterrupt:  # the command's own stop handles every later one (cli._stopped)
        print("mi-bivariate: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
