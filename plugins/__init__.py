"""Mitsuba BSDF plugins of mi_bivariate (placeholder until the plugins land)."""


def register() -> None:
    pass
