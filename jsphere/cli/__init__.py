"""The `jsphere` command line (`jsphere.cli.app`); `main` and `console` are imported when first
asked for, so that `python -m jsphere.cli.app` runs a module that is not imported yet."""


def __getattr__(name: str):
    if name in ("main", "console"):
        from . import app

        return getattr(app, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
