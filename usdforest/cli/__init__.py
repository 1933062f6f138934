"""The ``usdforest`` command line: parse, call the library (:mod:`usdforest.api` and the
stages' modules), print, map errors to exit codes (0 success, 1 a check failed, 2 bad input,
3 an internal error, 130 interrupted, 143 terminated). Each module registers its commands on
``app``, in the order ``--help`` lists them: one tree, forests and stages, stand patterns,
sensors, surveys, templates."""

# isort: off
from usdforest.cli import grow, stages, stands, sensors, surveys, templates  # noqa: F401  (registers them)

# isort: on
from usdforest.cli.app import app, main

__all__ = ["app", "main"]
