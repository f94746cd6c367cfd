"""mi_bivariate: passive reflectometry with bivariate BRDFs for Mitsuba 3."""

__version__ = "0.1.0"
