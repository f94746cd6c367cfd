"""The ``mi-bivariate`` command: the console script and ``python -m mi_bivariate`` (:func:`main`)."""

import sys


def main() -> int:
    """:func:`mi_bivariate.cli.run`, with the Ctrl-C that comes before the command has set up its own stop.

    Loading numpy and the command line takes the first ~0.1-0.3 s of a process; a Ctrl-C then used
    to end in a traceback from inside an import. It now ends as a later one does
    (:func:`mi_bivariate.cli.run`): one line, ``mi-bivariate: interrupted``, exit status 130.
    """
    try:
        from mi_bivariate.cli import run  # deliberately here, inside the guard: it loads numpy
        return run()
    except KeyboardInterrupt:  # the command's own stop handles every later one (cli._stopped)
        print("mi-bivariate: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
