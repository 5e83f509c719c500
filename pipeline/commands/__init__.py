"""CLI sub-commands: one module per command group, each with ``register(subparsers)``.

:mod:`pipeline.cli` discovers the modules of this package; a module's
``register`` adds its parser(s) and sets ``func`` to a callable taking the
parsed ``argparse.Namespace`` and returning an exit code.
"""
